"""Data in and out: the dataset folder and its contract (``dataset``), image and point-cloud readers
(``image_io``, ``pointcloud_io``), ROS message decoding and bag extraction (``ros_messages``, ``bag_extract``),
exports to other stacks (``export``) and atomic output (``output``). Everything that touches a file lives here.

May import: ``geometry``, ``estimators.errors``, ``estimators.measurements`` and its own modules; never
``solvers``, ``analysis``, ``simulation``, the pipeline or the CLI.
"""
