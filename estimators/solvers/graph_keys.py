"""The variables' keys of the one factor graph (``solvers.factor_graph``): sensor ``k``'s pose, frame ``j``'s board
pose, a camera's intrinsics, a LiDAR's range terms, its view of the board's outline and its outline shift in a frame.
A camera-LiDAR pair is the rig of sensors 0 (the camera) and 1 (the LiDAR): :data:`EXTRINSIC` and its kin.
"""
from __future__ import annotations

import gtsam


def sensor_key(k: int) -> int:
    return gtsam.symbol("s", k)


def frame_key(j: int) -> int:
    return gtsam.symbol("f", j)


def intrinsics_key(k: int) -> int:
    return gtsam.symbol("k", k)


def terms_key(k: int) -> int:
    """A LiDAR's range terms (a vector, m: ``range_model.RangeTerms``, the global offset first)."""
    return gtsam.symbol("o", k)


def outline_key(k: int) -> int:
    """A LiDAR's view of the board's outline (``board_edges``: its sides' growth, the pattern's offset)."""
    return gtsam.symbol("g", k)


def edge_shift_key(k: int, j: int) -> int:
    """Sensor ``k``'s outline shift in frame ``j``."""
    return gtsam.symbol("e", 100000 * k + j)


def edge_deviation_key(k: int, j: int) -> int:
    """Sensor ``k``'s board plane against the camera's in frame ``j``, for its ends
    (``board_edges.deviation_prior``)."""
    return gtsam.symbol("d", 100000 * k + j)


# A pair's LiDAR is sensor 1 of the rig of two: its pose in the camera's frame is ``T_camera_lidar``.
PAIR_LIDAR = 1
EXTRINSIC = sensor_key(PAIR_LIDAR)
RANGE = terms_key(PAIR_LIDAR)
INTRINSICS = intrinsics_key(0)  # the pair's camera's
OUTLINE = outline_key(PAIR_LIDAR)


def shift_key(j: int) -> int:
    """The pair's LiDAR's outline shift in frame ``j``."""
    return edge_shift_key(PAIR_LIDAR, j)


def deviation_key(j: int) -> int:
    """The pair's LiDAR's board plane deviation in frame ``j``."""
    return edge_deviation_key(PAIR_LIDAR, j)


board_key = frame_key
