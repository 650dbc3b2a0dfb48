"""The LiDAR side of a frame: the board's points found in a 3D sweep (``board_segmentation``) or a 2D scan
(``scan_segmentation``), and the beam models of common sensors (``lidar_models``). Works on point arrays;
reading scan files is ``io``'s job.

May import: ``geometry``, ``estimators.errors``, ``estimators.measurements`` and its own modules; never ``io``,
``solvers``, ``analysis``, ``simulation``, the pipeline or the CLI.
"""
