"""The camera side of a frame: checkerboard corner detection (``chessboard``), ChArUco corners with their ids,
whole or partly seen (``charuco``), the board pose and its plane
with their covariances (``board_pose``), and intrinsics from the boards when the dataset has none
(``intrinsics``). Works on pixel arrays; reading image files is ``io``'s job.

May import: ``geometry``, ``estimators.errors``, ``estimators.measurements`` and its own modules; never ``io``,
``solvers``, ``analysis``, ``simulation``, the pipeline or the CLI.
"""
