"""2D scans from a second generator (``simulation.footprint_2d``), written apart from the default simulator: beams
with a footprint and mixed returns at the board's edges, dark squares that can lose their return, noise along
the beam or isotropic in the scan plane, the first beam anywhere within a step, boards 1 x 1 m with the pattern
centred (issue 61). The segment ends' model was written against exact beams: on these scans it put the truth
outside the reported region (squared Mahalanobis distances 37-46 where the 99.9% point is 22.5) until the ends'
noise was measured from the scans (``board_edges.end_noise``). Seeds are fixed; every layout is checked."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.errors import DegenerateLayoutError
from estimators.simulation.footprint_2d import as_beam_model, layout_trial
from estimators.solvers.board_edges import BEAM_SD_RAD, end_noise
from estimators.solvers.observation_model import Layout, cramer_rao_bound
from estimators.solvers.solution_selection import select_and_refine
from geometry.rotations import T_inverse, T_log

CHI2_6_999 = 22.46  # the reported 99.9% region (Laplace covariance): chi-square, 6 dof


def _d2(T_hat: np.ndarray, cov: np.ndarray, T_true: np.ndarray) -> float:
    xi = T_log(T_inverse(T_hat) @ T_true)
    return float(xi @ np.linalg.solve(cov, xi))


def _inside_the_reported_region(rig, modes) -> tuple[bool, float]:
    """The truth inside the 99.9% region of the most probable mode, or, where a second mode holds 5% of the mass
    or more (the result says it is ambiguous), of any mode that holds mass; and its distance under the first."""
    d2 = [_d2(m.refinement.T_camera_lidar, m.refinement.covariance, rig.T_camera_lidar) for m in modes]
    ambiguous = any(m.mass >= 0.05 for m in modes[1:])
    inside = d2[0] <= CHI2_6_999 or (ambiguous and any(d <= CHI2_6_999 for d, m in zip(d2, modes) if m.mass >= 0.05))
    return inside, d2[0]


@pytest.mark.parametrize("boards", [4, 6])
def test_the_truth_lies_inside_the_reported_region_on_every_layout_of_the_second_generator(boards):
    """7 layouts of 4 and of 6 boards (seeds 0-6), 1 cm range noise, 0.25 degree steps: the truth inside the
    reported 99.9% region on every one; and the distances together like chi-square's (their sum over the layouts
    whose answer is one mode, below the 99.9% point of chi-square with 6 dof per layout: a covariance 2x too small
    in variance fails it about 65% of the time with 7 single-mode layouts, 82% with 10). The sweep (100 layouts of
    each size, coverage and the share answered) is ``make bench``'s: the footprint pages of the 2D honesty
    benchmark."""
    from scipy.stats import chi2

    total, dof = 0.0, 0
    for seed in range(7):
        rig, poses, frames = layout_trial(seed, boards)
        _, _, ref, modes, _ = select_and_refine(frames, rig.board, rig.camera)
        inside, d2 = _inside_the_reported_region(rig, modes)
        assert inside, (boards, seed, d2, [round(m.mass, 3) for m in modes])
        if len(modes) == 1:
            total, dof = total + d2, dof + 6
    assert total < chi2.ppf(0.999, dof), (total, dof)


@pytest.mark.parametrize("seed", [0, 8, 12])
def test_three_boards_whose_planes_leave_the_layout_degenerate_are_refused_or_answered_inside_their_region(seed):
    """Three boards whose planes alone leave the extrinsic degenerate (the planes' bound beyond 5 degrees or 0.5
    m): the segment ends may solve them, and then the truth lies inside the reported region; else the layout is
    refused. Never a confident answer outside it."""
    rig, poses, frames = layout_trial(seed, 3)
    layout = Layout(rig.camera, rig.board, as_beam_model(rig), rig.T_camera_lidar, tuple(poses), 0.25,
                    rig.scanner.sigma_m)
    try:
        C = cramer_rao_bound(layout)
        bound = max(np.degrees(np.sqrt(np.diag(C)[:3]).max()) / 5.0, np.sqrt(np.diag(C)[3:]).max() / 0.5)
    except np.linalg.LinAlgError:
        bound = np.inf
    assert bound >= 1.0  # degenerate for the planes, as chosen
    try:
        _, _, ref, modes, _ = select_and_refine(frames, rig.board, rig.camera)
    except DegenerateLayoutError:
        return
    inside, d2 = _inside_the_reported_region(rig, modes)
    assert inside, (seed, d2)


def test_the_ends_noise_is_the_footprint_on_exact_beams_and_the_returns_scatter_off_them():
    """On scans whose returns lie on their beams (noise in range only) the ends' noise is the footprint alone;
    where the returns scatter across their beams by about the beam spacing (isotropic noise in the plane), it is
    that scatter, 1 cm within a tenth."""
    rig, _, frames = layout_trial(0, 6, noise="range")
    exact = end_noise([(f.lidar.points, np.zeros(len(f.lidar.points), dtype=np.int64)) for f in frames if f.usable])
    assert exact.beam_sd_rad == pytest.approx(BEAM_SD_RAD, rel=1e-6) and exact.position_sd_m == 0.0
    rig, _, frames = layout_trial(0, 6, noise="xy")
    off = end_noise([(f.lidar.points, np.zeros(len(f.lidar.points), dtype=np.int64)) for f in frames if f.usable])
    assert off.position_sd_m == pytest.approx(rig.scanner.sigma_m, rel=0.1)
