"""The pipeline's stages below its orchestration (``estimators.calibration``): ``measurement``, a dataset's frames
measured and cached; ``result``, the result record and its JSON. A rig's (below ``estimators.rig_calibration``):
``rig_measurement``, ``rig_terms``, ``rig_edges``, ``rig_modes`` and ``rig_result``.

May import: ``geometry`` and every subpackage but ``analysis`` (the result's ``report()`` imports the report
inside the method) and the CLI.
"""
