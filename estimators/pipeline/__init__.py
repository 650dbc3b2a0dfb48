"""The pipeline's stages below its orchestration (``estimators.calibration``): ``measurement``, a dataset's frames
measured and cached; ``result``, the result record and its JSON.

May import: ``geometry`` and every subpackage but ``analysis`` (the result's ``report()`` imports the report
inside the method) and the CLI.
"""
