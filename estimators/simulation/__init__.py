"""Simulated rigs with ground truth: scene geometry and ray casting (``scene``), board images
(``rendering``), and whole dataset folders from a rig and a layout (``simulator``).

May import: ``geometry``, ``estimators.errors``, ``estimators.measurements``, ``io`` (to write the dataset
folder), ``lidar`` (beam models) and its own modules; never ``solvers``, ``analysis``, the pipeline or the CLI.
"""
