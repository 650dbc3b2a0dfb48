"""The board's edges as measurements (solvers.board_edges): the factor's Jacobians, its likelihood against
simulated ring crossings, the refinement with edges on weakly spread boards, and the outline checks."""
from dataclasses import replace

import numpy as np
import pytest

from estimators.simulation.simulator import default_rig, sample_layout
from estimators.solvers.board_edges import BEAM_SD_RAD, crossings, edge_residuals, nuisance_jacobians
from estimators.solvers.closed_form import solve_closed_form
from estimators.solvers.observation_model import (Layout, board_returns, cramer_rao_bound, simulate_measurements,
                                                  with_outline_error)
from estimators.solvers.chi_square import isf as chi2_isf
from estimators.solvers.outline_check import shift_fit
from estimators.solvers.refinement import refine
from estimators.solvers.refinement_options import measurement_model_options
from geometry.board import BoardModel
from geometry.rotations import T_exp, T_inverse, T_log


def _layout(seed: int, lidar: str = "vlp16", n: int = 6, weak: bool = False, noise_m: float = 0.02) -> Layout:
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, lidar, noise_m)
    # weak: normals within 3-12 degrees of the viewing axis, so planes leave the in-plane translation weak
    poses = sample_layout(rig, "weak" if weak else "spread", n, rng)
    return Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, noise_m)


def _weak_start(seed: int, noise_seed: int, n: int) -> tuple[Layout, list, np.ndarray]:
    """A VLP-16 layout of ``n`` weakly spread boards, its simulated frames and their closed-form start."""
    layout = _layout(seed, "vlp16", n=n, weak=True)
    frames = simulate_measurements(layout, np.random.default_rng(noise_seed))
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames],
                           allow_weak=True).T_camera_lidar
    return layout, frames, T0


def _refined(layout: Layout, frames: list, T0: np.ndarray, edges: bool, range_model: str = "none"):
    """The refinement of ``frames`` from ``T0``, with or without the board's edges."""
    return refine(frames, layout.board, layout.camera, T0,
                  measurement_model_options(range_model=range_model, edges=edges))


def _crossings(layout: Layout, i: int, pointing=None, beam_sd_rad: float = BEAM_SD_RAD):
    dirs, ranges, rings, _ = board_returns(layout, i, pointing)
    T_bl = T_inverse(layout.T_camera_board[i]) @ layout.T_camera_lidar
    return crossings(dirs * ranges[:, None], rings, T_bl, layout.board, beam_sd_rad)


def _standardised_end_residuals(beam_sd_rad: float = 0.0, lidar: str = "hdl64e") -> tuple[np.ndarray, np.ndarray]:
    """Every end's residual under the truth over its model standard deviation (with the footprint
    ``beam_sd_rad``), and its side, on six layouts whose beams are off their nominal directions by
    ``beam_sd_rad`` (0: exact)."""
    z, sides = [], []
    for seed in range(6):
        layout = _layout(seed, lidar)
        for i in range(layout.n_frames):
            pointing = (np.random.default_rng(100 * seed + i), beam_sd_rad) if beam_sd_rad else None
            e = _crossings(layout, i, pointing, beam_sd_rad)
            r, _, _ = edge_residuals(layout.T_camera_lidar, layout.T_camera_board[i], e, layout.board,
                                     jacobian=False)
            z.extend(r / e.sd_m)
            sides.extend(e.sides)
    return np.array(z), np.array(sides)


def test_edge_jacobians_match_finite_differences():
    layout = _layout(1)
    T, h = layout.T_camera_lidar, 1e-6
    for i in range(layout.n_frames):
        e, Tb = _crossings(layout, i), layout.T_camera_board[i]
        assert e.size >= 8
        g, d = np.array([0.003, -0.002]), np.array([0.004, 0.001])
        r, H_x, H_b = edge_residuals(T, Tb, e, layout.board, g, d)
        N_x, N_b = np.zeros_like(H_x), np.zeros_like(H_b)
        for k in range(6):
            x = np.zeros(6)
            x[k] = h
            f = lambda Ta, Tbb: edge_residuals(Ta, Tbb, e, layout.board, g, d, jacobian=False)[0]  # noqa: E731
            N_x[:, k] = (f(T @ T_exp(x), Tb) - f(T @ T_exp(-x), Tb)) / (2 * h)
            N_b[:, k] = (f(T, Tb @ T_exp(x)) - f(T, Tb @ T_exp(-x))) / (2 * h)
        np.testing.assert_allclose(H_x, N_x, atol=1e-6)
        np.testing.assert_allclose(H_b, N_b, atol=1e-6)
        H_g, H_s = nuisance_jacobians(e)
        for k in range(2):
            u = np.zeros(2)
            u[k] = 1e-4
            moved_g = edge_residuals(T, Tb, e, layout.board, g + u, d, False)[0]
            moved_d = edge_residuals(T, Tb, e, layout.board, g, d + u, False)[0]
            np.testing.assert_allclose(H_g[:, k], (moved_g - r) / 1e-4, atol=1e-9)
            np.testing.assert_allclose(H_s[:, k], (moved_d - r) / 1e-4, atol=1e-9)


def test_edge_likelihood_matches_simulated_ring_crossings():
    # Exact beams on a fixed azimuth grid: under the truth each end's residual is uniform over its azimuth step
    # (about the step's middle), so over the step's own standard deviation (no footprint) the residuals have
    # mean 0, variance 1 and lie within the uniform's half-width, sqrt 3.
    z, _ = _standardised_end_residuals()
    assert len(z) > 500
    assert abs(z.mean()) < 3 * z.std() / np.sqrt(len(z))
    assert abs(z.var() - 1.0) < 0.1
    assert np.max(np.abs(z)) < np.sqrt(3.0) * 1.01


def test_edges_shrink_the_in_plane_error_on_weak_layouts():
    # Ten boards tilted 3-12 degrees: planes leave the translation along them weak, the edges fix it.
    err = {False: [], True: []}
    d2, p_values = [], []
    for seed in range(6):
        layout, frames, T0 = _weak_start(seed, seed + 100, 10)
        for edges in (False, True):
            ref = _refined(layout, frames, T0, edges)
            xi = T_log(T_inverse(ref.T_camera_lidar) @ layout.T_camera_lidar)
            err[edges].append(xi)
            if edges:
                d2.append(float(xi @ np.linalg.solve(ref.covariance, xi)))
                assert ref.edges is not None and ref.edges["ends"] > 100
                p_values.append(ref.edges["planes_against_edges"]["p_value"])
    rms = {k: np.sqrt(np.mean(np.array(v) ** 2, axis=0)) for k, v in err.items()}
    assert np.linalg.norm(rms[True][:3]) < 0.7 * np.linalg.norm(rms[False][:3])   # rotation
    assert np.linalg.norm(rms[True][3:]) < np.linalg.norm(rms[False][3:])          # translation
    assert 2.0 < np.mean(d2) < 10.0  # 6 expected; six datasets
    # Nothing is biased here: the planes-against-edges test at 1% rejects at most one of the six (two or more:
    # 0.15% by chance).
    assert np.sum(np.array(p_values) < 0.01) <= 1


def _with_lidar_board(frames, lidar_layout: Layout, seed: int):
    """The camera's ``frames`` with the LiDAR's returns of ``lidar_layout``."""
    lidar_frames = simulate_measurements(lidar_layout, np.random.default_rng(seed))
    return [replace(f, lidar=g.lidar) for f, g in zip(frames, lidar_frames)]


@pytest.mark.parametrize("edges", [True, False])
@pytest.mark.parametrize("error", ["pattern_offset", "size"])
def test_outline_errors_in_the_dataset_are_caught(error, edges):
    """The dataset's board differs from the real one: the pattern printed 3 cm off centre along the board's x, or
    the board 5 cm larger than given. The camera places the given board; the LiDAR sees the real one. In each of
    3 layouts the warning names the error and its size: the outline 20-40 mm off along the board's x (with the
    edges, the outline's offset; without, the outlines' mean shift), or the board seen 40-60 mm wider."""
    import re

    caught = 0
    for seed in range(3):
        layout = _layout(seed + 10, "hdl64e", n=8)
        real = (with_outline_error(layout, pattern_shift_m=(0.03, 0.0)) if error == "pattern_offset" else
                with_outline_error(layout, size_error_m=0.05))
        frames = _with_lidar_board(simulate_measurements(layout, np.random.default_rng(seed)), real, seed + 5)
        T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
        ref = _refined(layout, frames, T0, edges)
        # Without --edges the ends check the planes' estimate, and say the same (solvers.outline_check); with
        # them, the planes-only estimate made beside is checked too.
        assert ref.edges is not None and ref.edges["used"] == edges
        assert not edges or ref.edges["planes_only_check"]["mean_shift_dof"] > 0
        said = " ".join(ref.warnings)
        if error == "size":
            found = re.search(r"board edges: the LiDAR sees the board ([+-]\d+) mm wider", said)
            caught += found is not None and 40 <= int(found.group(1)) <= 60
        elif edges:
            found = re.search(r"board edges: the board's outline sits ([+-]\d+) mm along its x", said)
            caught += found is not None and 20 <= int(found.group(1)) <= 40
        else:
            found = re.search(r"board edges: the LiDAR's board outlines sit (\d+) mm off the camera's on average "
                              r".*a wrong board.pattern_offset or board.size", said)
            caught += found is not None and 20 <= int(found.group(1)) <= 40
    assert caught == 3


def test_the_check_of_a_right_dataset_stays_quiet_and_its_mean_shift_is_consistent():
    # Planes alone on weakly spread boards (the translation along the boards weak): the ends check the estimate.
    # A right dataset gives no warning, and the mean shift's d2 against its covariance stays near its dof.
    d2, dof = [], []
    for seed in range(4):
        layout = _layout(seed + 30, "vlp16", n=10, weak=True)
        frames = simulate_measurements(layout, np.random.default_rng(seed), azimuth_phase=True,
                                       beam_sd_rad=BEAM_SD_RAD)
        T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames],
                               allow_weak=True).T_camera_lidar
        ref = refine(frames, layout.board, layout.camera, T0,
                     measurement_model_options(range_model="none", edges=False))
        assert ref.edges is not None and not ref.edges["used"] and ref.edges["ends"] > 100
        assert not any(w.startswith("board edges:") for w in ref.warnings)
        if seed < 2:  # with the edges, the planes-only estimate's check beside them is as quiet
            with_edges = refine(frames, layout.board, layout.camera, T0,
                                measurement_model_options(range_model="none", edges=True))
            assert with_edges.edges["planes_only_check"]["mean_shift_p_value"] > 0.01
            assert not any("under the planes alone" in w for w in with_edges.warnings)
        d2.append(ref.edges["mean_shift_d2"])
        dof.append(ref.edges["mean_shift_dof"])
    assert np.sum(d2) < chi2_isf(0.001, np.sum(dof))  # 4 datasets: far below the 0.1% tail


def test_the_checks_sensitivity_to_the_extrinsic_and_board_poses_matches_finite_differences():
    layout = _layout(3, "hdl64e", n=5)
    boards = list(layout.T_camera_board)
    edges = [_crossings(layout, i) for i in range(layout.n_frames)]
    T, h = layout.T_camera_lidar @ T_exp(np.array([0.002, -0.001, 0.001, 0.004, -0.003, 0.002])), 1e-6
    theta, _, G, scale = shift_fit(T, boards, edges, layout.board)
    N = np.zeros_like(G)
    for k in range(6 + 6 * len(boards)):
        x = np.zeros(6)
        x[k % 6] = h
        f = []
        for sign in (1, -1):
            Ts, bs = T, list(boards)
            if k < 6:
                Ts = T @ T_exp(sign * x)
            else:
                bs[k // 6 - 1] = boards[k // 6 - 1] @ T_exp(sign * x)
            f.append(shift_fit(Ts, bs, edges, layout.board, scale)[0])
        N[:, k] = (f[0] - f[1]) / (2 * h)
    # Gauss-Newton's sensitivity leaves out the loss's curvature times the residuals: within 0.5% of the largest.
    np.testing.assert_allclose(G, N, atol=5e-3 * np.abs(N).max())


def test_edges_are_found_where_the_planes_leave_the_boards_beyond_the_ends_cut():
    # Ten boards facing the camera's axis (normal spread 0.014): the planes alone put the boards 0.18 m off along
    # them, beyond the ends' 0.15 m cut, so every end was dropped and --edges silently gave the planes' answer.
    # The ends within half the board's side are fitted first, then assigned again under that estimate.
    rng = np.random.default_rng(85)
    rig = default_rig(rng, "vlp16", 0.02)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar,
                    tuple(sample_layout(rig, "handheld", 10, rng)), 0.2, 0.02)
    frames = simulate_measurements(layout, np.random.default_rng(85 + 10**6), azimuth_phase=True,
                                   beam_sd_rad=BEAM_SD_RAD)
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames],
                           allow_weak=True).T_camera_lidar
    planes, edges = (_refined(layout, frames, T0, e) for e in (False, True))
    err = {k: np.linalg.norm(r.T_camera_lidar[:3, 3] - layout.T_camera_lidar[:3, 3]) for k, r in
           (("planes", planes), ("edges", edges))}
    assert err["planes"] > 0.15  # the premise: beyond the cut
    assert edges.edges is not None and edges.edges["used"] and edges.edges["ends"] > 100
    # The bound with the edges is 15 mm here (RMS over the axes); 3 of it.
    assert err["edges"] < 0.045
    xi = T_log(T_inverse(edges.T_camera_lidar) @ layout.T_camera_lidar)
    assert float(xi @ np.linalg.solve(edges.covariance, xi)) < chi2_isf(0.001, 6)


def test_edges_that_cannot_be_used_are_said_to_be_unused():
    # The real board is 1 m larger than dataset.yaml says: every ring end lies 0.5 m beyond the given outline,
    # further than half its side, so no end is an edge; the answer is the planes' and says so.
    layout = _layout(4, "hdl64e", n=5)
    frames = _with_lidar_board(simulate_measurements(layout, np.random.default_rng(4)),
                               with_outline_error(layout, size_error_m=1.0), 9)
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    ref = _refined(layout, frames, T0, True)
    assert ref.edges is None or not ref.edges["used"]
    assert any(w.startswith("board edges: no ring end") for w in ref.warnings)


def test_boards_turned_about_their_normals_let_the_edges_fix_both_directions_along_them():
    # Upright boards: the rings leave them by their left and right sides, which fix the horizontal only. Turned
    # 35-55 degrees (the "diamond" layouts, as the shared recordings hold their boards), every ring leaves by
    # slanted sides: the edges' bound on the translation falls well below the planes' (2.5x on the benchmark's
    # VLP-16 diamond layouts, against 1.55x upright).
    def gain(family: str) -> float:
        tr = {False: [], True: []}
        for seed in range(4):
            rng = np.random.default_rng(seed)
            rig = default_rig(rng, "vlp16", 0.02)
            poses = sample_layout(rig, family, 10, rng)
            if family == "diamond":
                for T in poses:  # each board's x axis turned 35-55 degrees from the camera's x in its plane
                    n = T[:3, 2]
                    x0 = np.array([1.0, 0.0, 0.0]) - n[0] * n
                    turn = np.degrees(np.arccos(np.clip(T[:3, 0] @ x0 / np.linalg.norm(x0), -1.0, 1.0)))
                    assert 35.0 - 1e-6 <= turn <= 55.0 + 1e-6
            layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, 0.02)
            for edges in (False, True):
                tr[edges].append(np.trace(cramer_rao_bound(layout, edges=edges)[3:, 3:]))
        return float(np.sqrt(np.mean(tr[False]) / np.mean(tr[True])))

    weak, diamond = gain("weak"), gain("diamond")
    assert diamond > 2.0
    assert diamond > 1.3 * weak


def test_a_board_of_unknown_size_falls_back_to_planes_with_a_warning():
    layout = _layout(4, "hdl64e", n=5)
    unknown = BoardModel(layout.board.squares, layout.board.square_size)  # no size: the outline is not known
    layout = replace(layout, board=unknown)
    frames = simulate_measurements(layout, np.random.default_rng(4))
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    ref = refine(frames, unknown, layout.camera, T0, measurement_model_options(range_model="none", edges=True))
    assert ref.edges is None
    assert any("board's size is not given" in w for w in ref.warnings)


def test_the_posterior_holds_the_edges():
    # On weakly spread boards the planes alone leave the in-plane translation wide; the posterior with the
    # edges' share must be as narrow as the refinement's covariance with the edges (its Laplace approximation;
    # 20% on a standard deviation: 1000 effective samples, and the sampled camera-noise scale), centred
    # on the estimate, and narrower than the planes' alone.
    from .numeric import sampled

    layout, frames, T0 = _weak_start(1, 101, 10)
    sd = {}
    for edges in (False, True):
        ref = _refined(layout, frames, T0, edges)
        xi, *_ = sampled(ref, np.random.default_rng(1), 1000)  # the engine's chain on the pair's likelihood
        sd[edges] = xi.std(axis=0)
        np.testing.assert_allclose(sd[edges] / np.sqrt(np.diag(ref.covariance)), 1.0, atol=0.2)
        assert np.all(np.abs(xi.mean(axis=0)) < 0.3 * sd[edges])
    assert np.all(sd[True] <= sd[False] * 1.05)
    assert np.linalg.norm(sd[True][:3]) < 0.7 * np.linalg.norm(sd[False][:3])  # rotation
    assert np.linalg.norm(sd[True][3:]) < 0.95 * np.linalg.norm(sd[False][3:])  # translation


def test_the_bound_with_edges_matches_the_edges_error_and_the_layout_analysis_reports_it():
    # The edges' Cramer-Rao bound (planes, edges, the outline's nuisances) against the spread of the refinement
    # with edges over repeated draws of one weak layout: the estimator reaches it (an RMS within 0.7-1.4 of the
    # bound over 12 draws, the beams exact so the ends' noise is the azimuth step's), well below the planes'.
    # Each draw's sweeps fire at a random phase: on a fixed firing grid the ends' errors would repeat.
    from estimators.analysis.layout_analysis import analyse

    layout = _layout(2, "os64", n=10, weak=True)
    planes, edges = cramer_rao_bound(layout), cramer_rao_bound(layout, edges=True, beam_sd_rad=0.0)
    assert np.trace(edges[:3, :3]) < 0.3 * np.trace(planes[:3, :3])
    err = []
    for seed in range(12):
        frames = simulate_measurements(layout, np.random.default_rng(300 + seed), azimuth_phase=True)
        T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames],
                               allow_weak=True).T_camera_lidar
        ref = refine(frames, layout.board, layout.camera, T0, measurement_model_options(range_model="none",
                                                                                         edges=True))
        err.append(T_log(T_inverse(ref.T_camera_lidar) @ layout.T_camera_lidar))
    err = np.array(err)
    for part in (slice(0, 3), slice(3, 6)):
        ratio = np.sqrt(np.mean(np.sum(err[:, part] ** 2, axis=1)) / np.trace(edges[part, part]))
        assert 0.7 < ratio < 1.4
    # The layout analysis (lidarcam layout on a plan) prints the bound with the model's beam footprint.
    a = analyse(layout)
    model = cramer_rao_bound(layout, edges=True)
    np.testing.assert_allclose(a.edges["translation_std_mm"], 1000 * np.sqrt(np.diag(model)[3:]), rtol=1e-9)
    assert "with the ring ends on the boards' edges (used by default" in a.format()


def test_a_measured_dataset_with_edges_has_their_bound_and_report(tmp_path):
    # lidarcam layout DATASET: the measured returns keep their rings, so the ends are found and the bound with
    # the edges is printed; it is tighter than the planes' alone in rotation.
    from estimators.analysis.layout_analysis import analyse, layout_from_result
    from estimators.calibration import calibrate_pair
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset

    from estimators.solvers.refinement_options import RefinementOptions

    path = simulate_dataset(tmp_path / "sim", n_poses=5, seed=3, lidar="vlp16")
    ds = load_dataset(path)
    result = calibrate_pair(ds, samples=0, options=RefinementOptions(edges=True))
    layout, _, names = layout_from_result(result, ds.board, "vlp16")
    a = analyse(layout, names)
    assert a.edges is not None
    assert np.linalg.norm(a.edges["rotation_std_deg"]) < np.linalg.norm(a.std_rotation_deg)
    # The report (the engine's, as `lidarcam calibrate` writes it) has the edges' section: the mean shift, the test
    # and each frame's shift.
    from estimators import calibrate

    page = calibrate(ds, samples=0, options=RefinementOptions(edges=True)).report(tmp_path / "report").read_text()
    assert "lidar0: Board edges</h2>" in page and "outline shift x [mm]" in page and "planes alone against" in page


def test_edge_likelihood_matches_beams_with_a_footprint():
    # Beams off their nominal direction by the model's footprint and pointing spread (the simulator's
    # beam_sd_rad): the ends' standardised residuals have mean 0 and variance 1 (within 10%, ~2000 ends).
    z, sides = _standardised_end_residuals(BEAM_SD_RAD)
    assert len(z) > 1500
    assert abs(z.mean()) < 3 * z.std() / np.sqrt(len(z))
    assert abs(z.var() - 1.0) < 0.1


def test_a_footprint_counts_across_the_top_and_bottom_sides_as_across_the_others():
    # A ring that leaves a rolled board by its top or bottom side runs nearly along it: the footprint's
    # elevation, not its azimuth, sets where it stops. On six OS1-64 layouts (boards rolled up to 20 degrees)
    # those ends' standardised residuals have variance 1 as the left and right sides' do (within 20%; a few
    # hundred ends); a footprint counted in azimuth alone gave them 3-4.
    z, sides = _standardised_end_residuals(BEAM_SD_RAD, "os64")
    for across_y in (False, True):
        m = (sides >= 2) == across_y
        assert m.sum() > (100 if across_y else 1000)
        assert abs(z[m].var() - 1.0) < 0.2


def test_a_board_off_its_declared_outline_moves_a_scan_lines_ends_by_that_error():
    """``Layout.outline_error_m`` (the physical board's growth and offset against the declared outline, as the
    edge model's nuisance): a 2D scan line's returns end where the physical board does, within the scanner's
    angular step."""
    from estimators.simulation.simulator import default_rig_2d, sample_board_poses

    rng = np.random.default_rng(3)
    rig = default_rig_2d(rng, 0.0)
    poses = sample_board_poses(rig, 3, rng)
    exact = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, 0.0)
    error = (0.04, 0.0, 0.03, 0.0)  # 4 cm wider on each x side, moved 3 cm along x
    off = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, 0.0,
                 outline_error_m=error)
    w = rig.board.extent[0]
    for i in range(3):
        T_board_lidar = T_inverse(poses[i]) @ rig.T_camera_lidar
        x = []
        for lay in (exact, off):
            dirs, ranges, _, _ = board_returns(lay, i)
            pts = (T_board_lidar[:3, :3] @ (dirs * ranges[:, None]).T).T + T_board_lidar[:3, 3]
            x.append((pts[:, 0].min(), pts[:, 0].max()))
        step = 0.25 * np.pi / 180 * 4.0  # the scanner's step at the farthest board, m
        assert abs(x[0][0] - 0.0) < step and abs(x[0][1] - w) < step
        assert abs(x[1][0] - (0.03 - 0.04)) < step and abs(x[1][1] - (w + 0.04 + 0.03)) < step


def test_planes_and_edges_in_conflict_are_a_check_whose_covariance_holds_both_answers(capsys):
    """A planes-against-edges test below p = 0.01 is a conflict: the verdict is CHECK with the reason (UNTRUSTED
    when the two answers lie further apart than a frame may disagree, 3 degrees or 50 mm), calibration.json holds
    it, and ``--strict`` exits 3 on UNTRUSTED only; at p = 0.02 none of that."""
    from estimators.calibration import EXIT_AMBIGUOUS, solve
    from estimators.cli.commands import exit_code
    from estimators.cli.parser import build_parser
    from estimators.cli.printing import print_result

    layout = _layout(0, "vlp16", n=8, weak=True)
    frames = simulate_measurements(layout, np.random.default_rng(100))
    result = solve(frames, layout.board, layout.camera, samples=0,
                   options=measurement_model_options(range_model="none"))
    test = result.refinement.edges["planes_against_edges"]
    assert test is not None and test["p_value"] > 0.01 and result.contradicted is None
    assert result.refinement.conflict_covariance is None
    strict = build_parser().parse_args(["calibrate", "data", "--out", "out", "--strict"])
    small = np.r_[np.deg2rad([0.3, 0.0, 0.0]), 0.006, 0.0, 0.0]
    for p_value, delta, level in ((2e-2, small, None), (1e-5, small, "CHECK"), (1e-5, 12 * small, "UNTRUSTED")):
        edges = {**result.refinement.edges, "planes_against_edges": {**test, "p_value": p_value,
                                                                     "difference_tangent": delta.tolist()}}
        moved = replace(result, refinement=replace(result.refinement, edges=edges))
        assert bool(moved.contradicted) == (level is not None)
        assert moved.to_dict()["contradicted"] == moved.contradicted
        capsys.readouterr()
        print_result(moved)
        out = capsys.readouterr().out
        assert out.startswith(f"{level}: the boards' planes and their ring ends") == (level is not None)
        assert ("the covariance holds both answers" in out.splitlines()[0]) == (level == "CHECK")
        assert exit_code(strict, moved) == (EXIT_AMBIGUOUS if level == "UNTRUSTED" else 0)


def test_planes_and_edges_that_conflict_are_both_held_by_the_covariance():
    """Every return 2 cm long, with no range terms to take it: the boards' planes move, the ends (beam directions)
    do not, and the two conflict (p < 0.01). The covariance holds both answers: the planes-only answer lies within
    one standard deviation of the estimate along their difference (d2 at most 1), and the verdict is CHECK with
    that reason. (A board declared larger than it is, or its pattern off centre, does not conflict: the outline's
    growth and offset take it.)"""
    from estimators.calibration import solve
    from estimators.simulation.range_bias import RangeBias

    layout = _layout(0, "vlp16", n=8, weak=True)
    frames = simulate_measurements(layout, np.random.default_rng(100), RangeBias(0.02))
    result = solve(frames, layout.board, layout.camera, samples=0,
                   options=measurement_model_options(range_model="none"))
    ref = result.refinement
    test = ref.edges["planes_against_edges"]
    assert test["p_value"] < 0.01 and ref.conflict_covariance is not None
    xi = T_log(T_inverse(ref.T_camera_lidar) @ np.asarray(test["planes_only_T_camera_lidar"]))
    assert float(xi @ np.linalg.solve(ref.covariance, xi)) <= 1.0 + 1e-6
    own = np.asarray(test["edges_own_offset_tangent"])
    assert float(own @ np.linalg.solve(ref.covariance, own)) <= 1.0 + 1e-6
    # here the planes are the biased witness: the truth, 30 mm off, lay at d2 566 with the planes' answer alone held
    # and lies at 46 with the edges' own too (seeds 101 and 102 of this layout's kind: 931 -> 6, 1035 -> 14)
    truth = T_log(T_inverse(ref.T_camera_lidar) @ layout.T_camera_lidar)
    planes_only_held = ref.covariance - np.outer(own, own)
    assert float(truth @ np.linalg.solve(ref.covariance, truth)) < \
        0.1 * float(truth @ np.linalg.solve(planes_only_held, truth))
    assert result.verdict.level == "CHECK" and "the covariance holds both answers" in result.verdict.line


def test_the_edges_own_answer_is_read_from_the_two_informations():
    """Two Gaussian witnesses of a 6-vector (information ``I_p`` and ``I_e``) combined: from the planes' answer,
    the combined one and the two covariances, ``edges_own_offset`` gives where the edges' own answer lies from the
    combined one, its part beyond the noise (all of it, 40 standard deviations off), and nothing along directions
    the edges do not see or where the two agree within their noise."""
    from estimators.solvers.edges_in_graph import edges_own_offset

    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    I_p = A @ A.T + 6 * np.eye(6)
    B = rng.normal(size=(6, 3))
    I_e = B @ B.T  # the edges see three directions
    x_p = np.zeros(6)
    x_e = np.linalg.pinv(I_e) @ (B @ rng.normal(size=3))  # an answer where the edges see
    d2 = x_e @ np.linalg.solve(np.linalg.inv(I_p) + np.linalg.pinv(I_e), x_e)
    x_e *= 40.0 / np.sqrt(d2)
    x_c = np.linalg.solve(I_p + I_e, I_p @ x_p + I_e @ x_e)
    own = edges_own_offset(x_c - x_p, np.linalg.inv(I_p), np.linalg.inv(I_p + I_e))
    # along what the edges see, the edges' answer less its noise's share (a few per cent, 40 sd off)
    gap = I_e @ (x_e - x_c)
    assert np.linalg.norm(I_e @ own - gap) < 0.03 * np.linalg.norm(gap)
    close = x_c - x_p
    assert not np.any(edges_own_offset(1e-3 * close, np.linalg.inv(I_p), np.linalg.inv(I_p + I_e)))


def test_a_3d_lidars_range_terms_are_chosen_on_its_planes_as_without_the_edges():
    # A 3D LiDAR's range terms are chosen on the planes alone (the choice validated on rooms and recordings), the
    # edges added after: the planes' tests are the same with the edges as without them; with the edges, a global
    # offset the planes do not support is tested once more with the ring ends in the graph (not supported here).
    layout, frames, T0 = _weak_start(3, 7, 8)
    tests = {edges: _refined(layout, frames, T0, edges, "auto").range_model.tests for edges in (False, True)}
    ended = [t for t in tests[True] if t.get("with_ring_ends")]
    assert not tests[False][0]["included"] and len(ended) == 1 and not ended[0]["included"]
    tests[True] = [t for t in tests[True] if not t.get("with_ring_ends")]
    assert [t["model"] for t in tests[True]] == [t["model"] for t in tests[False]]
    assert [t["consistency_dof"] for t in tests[True]] == [t["consistency_dof"] for t in tests[False]]
    np.testing.assert_allclose([t["p_value"] for t in tests[True]], [t["p_value"] for t in tests[False]])


def test_the_mean_shift_is_tested_against_the_scatter_its_shifts_were_estimated_under():
    """A VLP-16 layout of 10 weak boards whose outline is off the dataset's by errors within the edge model's
    priors (a fixed seed where the boards' in-plane scatter shrinks to its floor over more rounds than are
    solved): the engine's record states the scatter its last solve used, and the mean outline shift of this right
    answer passes its 99% test. Testing it against the next round's scatter (0.1 mm where the shifts were solved
    under several) had put it beyond its limit with d2 near 3e6 and read CHECK."""
    from estimators.io.measurement_store import Measurements
    from estimators.rig_calibration import calibrate
    from estimators.solvers.board_edges import GROWTH_PRIOR_SD_M, OFFSET_PRIOR_SD_M

    seed = 11
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "vlp16", 0.02)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(sample_layout(rig, "weak", 10, rng)),
                    0.2, 0.02)
    frames = simulate_measurements(layout, np.random.default_rng(seed + 10**6), azimuth_phase=True,
                                   beam_sd_rad=BEAM_SD_RAD)
    draw = np.random.default_rng(seed + 7)
    real = replace(layout, outline_error_m=tuple(np.r_[draw.normal(0.0, GROWTH_PRIOR_SD_M, 2),
                                                       draw.normal(0.0, OFFSET_PRIOR_SD_M, 2)]))
    seen = simulate_measurements(real, np.random.default_rng(seed + 10**6), azimuth_phase=True,
                                 beam_sd_rad=BEAM_SD_RAD)
    frames = [replace(f, lidar=g.lidar) for f, g in zip(frames, seen)]
    res = calibrate(Measurements(layout.camera, layout.board, "3d", tuple(frames)), rng=np.random.default_rng(seed),
                    options=measurement_model_options(range_model="none", edges=True), samples=0)
    record = res.edges["lidar0"]
    view, = res.lidar_views
    assert record["board_scatter_in_plane_m"] == view.edge_tau_m > 1e-3  # the scatter solved with, in mm
    assert record["mean_shift_p_value"] > 0.01
    assert not any("on average" in w for w in res.warnings)


def test_the_cut_to_the_outline_grows_with_the_consensus_uncertainty():
    """A recorded hard case, in small: boards that face the rig alike leave the consensus extrinsic (the cut's)
    free along their planes; cut 5 cm outside the camera's outline under a consensus 8 cm off along camera x, a
    strip of real board went from one side of every board, and the edges then put the extrinsic off under an OK
    verdict (NEES 63 on 9 simulated poses). Weakly spread boards: under that consensus every board keeps its
    extent (its returns' reach along its sides, to 1 cm). Spread boards under the true extrinsic: a holder's
    returns 12 cm beyond a side are cut, the boards' extents kept."""
    from estimators.lidar.board_segmentation import SegmentationParams
    from estimators.measurements import observe_lidar_board
    from estimators.pipeline.measurement import _trimmed_to_outlines
    from geometry.rotations import transform_points

    def extent(f, T):  # the returns' reach in the board's frame (under T): x min, x max, y min, y max
        q = transform_points(T_inverse(f.camera.T_camera_board) @ T, f.lidar.points)
        return np.array([q[:, 0].min(), q[:, 0].max(), q[:, 1].min(), q[:, 1].max()])

    layout, frames, T0 = _weak_start(3, 4, 8)
    T = layout.T_camera_lidar
    shifted = T.copy()
    shifted[0, 3] += 0.08  # along camera x: along every board
    for before, after in zip(frames, _trimmed_to_outlines(frames, shifted, layout.board, SegmentationParams(), {})):
        np.testing.assert_allclose(extent(after, T), extent(before, T), atol=0.01)

    layout = _layout(5, "vlp16", n=8)
    T = layout.T_camera_lidar
    frames = simulate_measurements(layout, np.random.default_rng(6))
    f = frames[0]
    w, h = layout.board.extent
    hand_b = np.column_stack([np.full(30, w + 0.12), np.linspace(0.3 * h, 0.7 * h, 30), np.zeros(30)])
    hand = transform_points(T_inverse(T) @ f.camera.T_camera_board, hand_b)
    held = replace(f, lidar=observe_lidar_board(np.vstack([f.lidar.points, hand])))
    assert extent(held, T)[1] > w + 0.1
    out = _trimmed_to_outlines([held] + frames[1:], T, layout.board, SegmentationParams(), {})
    for before, after in zip(frames, out):
        np.testing.assert_allclose(extent(after, T), extent(before, T), atol=0.01)


def test_a_ring_end_whose_ring_goes_on_in_the_boards_plane_is_no_edge():
    # One ring on a board, returns a step apart; the sweep's returns beyond each end decide: a return at the next
    # firing (in the board's plane band, not taken) makes that end open, one two steps on or on another ring not.
    from estimators.solvers.board_edges import open_ends, ring_ends

    step = np.radians(0.2)
    phi = np.arange(10) * step
    board = 5.0 * np.column_stack([np.cos(phi), np.sin(phi), np.zeros(10)])
    rings = np.zeros(10, dtype=np.int64)
    others = 5.0 * np.array([[np.cos(a), np.sin(a), 0.0] for a in (-step, 11 * step, 10 * step)])
    flags = open_ends(board, rings, others[:2], np.array([0, 0]))
    assert flags[0] and not flags[1:].any()  # beyond the first return: the next firing; beyond the last: two on
    assert open_ends(board, rings, others[2:], np.array([0]))[9]
    assert not open_ends(board, rings, others, np.array([1, 1, 1])).any()
    assert len(ring_ends(board, rings)) == 2 and len(ring_ends(board, rings, flags)) == 1


def test_a_range_offset_leaves_out_the_ring_ends_the_boards_window_cut(tmp_path):
    # HDL-64E boards ranged 5 cm long: their returns lie on a plane further off, where the beams spread wider than
    # the board, and the board's window (its size on the returns' positions) cut the outermost, so that their
    # rings ended a step inside the edge and biased the translation along the boards' normals (truth d2 9.2 over
    # 12 datasets of 10 poses, 5.1 without the offset). Those ends are open (their ring goes on in the plane) and
    # left out: the ends used sit on the true outline on average, the open ones about a step inside it.
    from estimators.io.dataset import load_dataset
    from estimators.pipeline.measurement import measure_frames
    from estimators.simulation.simulator import simulate_dataset
    from estimators.solvers.board_edges import ring_ends
    from geometry.planes import cut_with_board

    path = simulate_dataset(tmp_path / "d", n_poses=5, seed=52, lidar="hdl64e", range_bias=(0.05, 0.0, 0.0))
    ds = load_dataset(path)
    truth = ds.ground_truth()
    _, frames, _ = measure_frames(ds, np.random.default_rng(0))
    w, h = ds.board.extent
    offsets = {True: [], False: []}
    for f in (f for f in frames if f.usable):
        used = {(r, np.sign(s)) for r, _, s in ring_ends(f.lidar.points, f.lidar.rings, f.lidar.open_ends)}
        T_board_lidar = T_inverse(f.camera.T_camera_board) @ truth
        for r, beam, s in ring_ends(f.lidar.points, f.lidar.rings):
            q = cut_with_board(T_board_lidar, beam[None])[0][0]
            off = max(-q[0], q[0] - w, -q[1], q[1] - h)  # outward of the outline (m)
            if abs(off) < 0.1:
                offsets[(r, np.sign(s)) in used].append(off)
    kept, open_ = np.array(offsets[True]), np.array(offsets[False])
    # ~350 ends used, each within its azimuth step (~15 mm, sd ~4 mm): the mean's sd is ~0.25 mm.
    assert len(kept) > 200 and abs(kept.mean()) < 0.001
    assert len(open_) >= 5 and open_.mean() < -0.003


def test_an_offset_on_boards_facing_the_rig_is_found_with_the_ring_ends():
    """A VLP-16 ranging 2 cm long, 8 boards tilted 3-12 degrees from the viewing axis: on their planes alone the
    offset is nearly the translation along their normals and its test passes it over (p = 0.21 here); the engine's
    answer then lay 21 mm off at d2 934 and read OK. Tested again with the ring ends in the graph it is taken (p =
    0.0003), and the answer holds its truth (d2 within 16.8, the 99% point; within 10 mm). The same boards ranging
    right take no offset. (Seeds 100-105 of this kind: taken in 5 of 6 at 2 cm, the sixth at p = 0.005.)"""
    from estimators import calibrate
    from estimators.io.measurement_store import Measurements
    from estimators.simulation.range_bias import RangeBias

    layout = _layout(5, "vlp16", n=8, weak=True)
    for offset, rng in ((0.02, 105), (0.0, 105)):
        frames = simulate_measurements(layout, np.random.default_rng(rng), RangeBias(offset))
        res = calibrate(Measurements(layout.camera, layout.board, "3d", tuple(frames)),
                        rng=np.random.default_rng(5), samples=0)
        record = res.range_models.get("lidar0") or {}
        tests = record.get("tests") or []
        assert any(t.get("with_ring_ends") for t in tests), tests
        xi = T_log(T_inverse(res.T_camera_lidar) @ layout.T_camera_lidar)
        assert xi @ np.linalg.solve(res.covariance, xi) < 16.8 and 1000 * np.linalg.norm(xi[3:]) < 10.0
        assert ("offset" in (record.get("terms") or {})) == (offset > 0), record
        assert record.get("weak_offset") is None


def test_an_offset_its_test_half_supports_is_held_in_the_covariance():
    """The one of those six layouts (layout 3, VLP-16 ranging 2 cm long) whose offset the test with the ring ends
    passed over at p = 0.005 (the test takes terms at 0.001): its answer, 19 mm off, lay beyond d2 100 under a
    covariance without the offset, reading OK. Half supported (p below 0.05), the offset is held in the
    covariance beside the answer without it (the shift it would make, as an outer product): the truth then lies
    within 16.8 (the 99% point). The estimate is the answer without it."""
    from estimators import calibrate
    from estimators.io.measurement_store import Measurements
    from estimators.pipeline.rig_result import range_model_words
    from estimators.simulation.range_bias import RangeBias

    layout = _layout(3, "vlp16", n=8, weak=True)
    frames = simulate_measurements(layout, np.random.default_rng(103), RangeBias(0.02))
    res = calibrate(Measurements(layout.camera, layout.board, "3d", tuple(frames)), rng=np.random.default_rng(3),
                    samples=0)
    record = res.range_models["lidar0"]
    weak = record["weak_offset"]
    assert weak["with_ring_ends"] and 0.001 <= weak["p_value"] < 0.05 and "offset" not in (record.get("terms") or {})
    assert 10 < weak["offset_mm"] < 30  # the 2 cm it ranges long, found but not taken
    assert "held in the covariance" in record["reason"]
    assert f"an offset of {weak['offset_mm']:+.1f} mm (p = {weak['p_value']:.2g} < 0.05) held in the covariance" in \
        range_model_words(record)
    xi = T_log(T_inverse(res.T_camera_lidar) @ layout.T_camera_lidar)
    d = np.asarray(weak["difference_tangent"])
    C = np.asarray(res.covariance)
    assert xi @ np.linalg.solve(C - np.outer(d, d), xi) > 100
    assert xi @ np.linalg.solve(C, xi) < 16.8
