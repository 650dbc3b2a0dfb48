"""When a 2D answer is refused: the scan directions' standard deviations beyond what the layout can carry, and
the posterior's spread beyond what the refinement accepts.
"""
from __future__ import annotations

import numpy as np

from ..errors import DegenerateLayoutError
from .board_edges import SIDE_NORMALS
from .closed_form import MIN_SCAN_NORMAL_SPREAD, describe_direction, normal_spread
from .plane_graph import PlaneProblem

# A 2D LiDAR's extrinsic whose standard deviation (planes and segment ends) reaches this rotation (rad) or
# translation (m) is refused: the layout leaves it unobservable in all but name, and a point estimate there
# would be a confident-looking guess. A layout is degenerate when its bound reaches 5 degrees or 0.5 m; the
# estimate's own standard deviation scatters about the bound (up to 1.5 times it on simulated mounted layouts
# whose bound is 4.4-4.7 degrees), so the limit on the estimate is 1.5 times that: at 5 degrees such layouts were
# refused, and answered inside their regions when let through.
MAX_SCAN_ROTATION_SD_RAD = np.deg2rad(7.5)
MAX_SCAN_TRANSLATION_SD_M = 0.75


def check_scan_directions(prob: PlaneProblem, active: list[int], boards: list) -> None:
    """2D: the translation is fixed along the boards' normals (their scan lines) and along the outward normals of
    the sides their segments end on (the ends). When all of these lie in one plane (spread, as
    ``closed_form.normal_spread``, below ``MIN_SCAN_NORMAL_SPREAD``: upright boards whose lines end on their
    upright sides), the translation across it is unobservable: raise :class:`DegenerateLayoutError` naming it."""
    dirs = []
    for i in active:
        dirs.append(boards[i][:3, 2])
        if prob.has_edges(i):
            dirs.extend(SIDE_NORMALS[prob.edges[i].sides] @ boards[i][:3, :2].T)
    spread, weak = normal_spread(np.array(dirs))
    if spread[-1] < MIN_SCAN_NORMAL_SPREAD:
        axis, advice = describe_direction(weak)
        raise DegenerateLayoutError(
            f"the {len(active)} board normals and the board sides their scan segments end on all lie in one plane "
            f"(spread {spread[-1]:.3f} along {axis}): translation along {axis} is unobservable", hint=advice)


# The posterior of a 3-board layout reaches further along its curved valley than its Laplace approximation: a
# mode's samples may spread this many times the refusal limits above before the answer is refused (simulated
# mounted layouts: good answers, 1 degree off, sample 6.5-7.1 degrees; a 38-degree miss sampled 15.5).
POSTERIOR_REFUSAL_FACTOR = 2.0


def scan_refusal(cov: np.ndarray, T: np.ndarray, n_frames: int, ends: bool,
                 factor: float = 1.0) -> DegenerateLayoutError | None:
    """The refusal of a 2D extrinsic whose covariance reaches ``MAX_SCAN_ROTATION_SD_RAD`` or
    ``MAX_SCAN_TRANSLATION_SD_M`` times ``factor`` (None when it does not), naming the weakest direction in camera
    axes: the refinement's covariance, or (``factor`` ``POSTERIOR_REFUSAL_FACTOR``) the posterior's about the MAP's
    mode."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    max_rot, max_trans = factor * MAX_SCAN_ROTATION_SD_RAD, factor * MAX_SCAN_TRANSLATION_SD_M
    if sd[:3].max() < max_rot and sd[3:].max() < max_trans:
        return None
    part = "translation" if sd[3:].max() / max_trans >= sd[:3].max() / max_rot else "rotation"
    block = cov[3:, 3:] if part == "translation" else cov[:3, :3]
    weak = T[:3, :3] @ np.linalg.eigh(block)[1][:, -1]  # LiDAR axes to camera axes
    axis, advice = describe_direction(weak)
    what = "scan lines and their segment ends on the boards' edges" if ends else "scan lines"
    return DegenerateLayoutError(
        f"the {n_frames} {what} leave the "
        f"extrinsic's {part} nearly unobservable (standard deviations up to {np.degrees(sd[:3].max()):.1f} deg and "
        f"{1000 * sd[3:].max():.0f} mm; weakest along {axis})",
        hint=f"record more board poses; {advice}")
