"""What is said about calibrations and layouts: layout conditioning and pose advice (``layout_analysis``),
solver-comparison studies (``study``), uncertainty coverage studies (``coverage_study``) and the HTML report
(``report``). Figures are drawn on ``matplotlib.figure.Figure`` objects, never through pyplot, so the library
leaves a notebook's plotting state alone.

May import everything below the CLI: ``geometry``, ``io``, ``camera``, ``lidar``, ``solvers``, ``simulation``,
the pipelines (``estimators.calibration``, ``estimators.rig_calibration`` and their stages, ``estimators.pipeline``)
and the top-level records; never the CLI.
"""
