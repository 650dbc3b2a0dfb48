"""Validation without ground truth: score frames a calibration did not use, K-fold over frames, and two
disjoint halves.

A held-out frame's score is its whitened plane residual under the calibration: ``e = W pi(T, b)`` with
``b`` the camera's own board pose (PnP), ``W`` the board points' range-moment square root, and covariance
``C = sigma_r^2 I + W H_b Sigma_b H_b^T W^T + W H_x Sigma_T H_x^T W^T`` (+ the calibration's per-board plane
error): the point noise, the camera's board-pose uncertainty and the calibration's own covariance. Under a
right calibration ``e^T C^-1 e`` is chi-square with ``k`` (3 for a plane, 2 for a scan line) degrees of
freedom; the verdict tests their sum. Each frame also gets its plane residual in mm at the board's centre
and the offset (px) of its LiDAR board points' centroid from the camera's board centre, projected into
the image (the outline check a user does by eye).

Two halves: the first and last halves of the frames (in name order) calibrated apart; their difference
``xi = Log(T_1^-1 T_2)`` should be explained by the two covariances, ``xi^T (S_1 + S_2)^-1 xi`` being
chi-square with 6 dof. If it is not, the model misses an error (docs/benchmarks.md, recorded data).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import T_inverse, T_log, skew, transform_points

from ..errors import DegenerateLayoutError, LidarcamError
from ..measurements import FrameMeasurement
from ..solvers import chi_square as chi2
from ..solvers.factors import corner_residuals, lidar_plane, lidar_residual, nuisance_residual
from ..solvers.noise_levels import frame_noise, plane_noise, pooled_range_noise_m
from ..solvers.range_model import RangeTerms, frame_labels, frame_whiteners

SIGNIFICANCE = 0.01


@dataclass(frozen=True)
class FrameScore:
    name: str
    chi2: float
    dof: int
    p_value: float
    plane_offset_mm: float
    predicted_offset_sd_mm: float
    outline_offset_px: float
    flagged: bool

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def score_frames(frames: list[FrameMeasurement], board, camera, T_camera_lidar: np.ndarray, covariance: np.ndarray,
                 corner_noise_px: float, range_noise_m: float | None = None, plane_floor_m: float = 0.0,
                 range_terms: RangeTerms | None = None, range_values_m=None, range_cov=None,
                 range_scatter_m: float = 0.0) -> list[FrameScore]:
    """Each usable frame's agreement with a calibration (``T_camera_lidar`` and its 6x6 covariance, and its
    LiDAR range terms with their values and covariance when it has them)."""
    usable = [f for f in frames if f.usable]
    if not usable:
        return []
    sigma_r = range_noise_m or pooled_range_noise_m([f.lidar for f in usable])
    half = 0.5 * float(np.mean(board.extent))
    beta = None if range_terms is None else np.asarray(range_values_m, dtype=float)
    # Held-out frames: their black squares placed by geometry under the calibration and blurred by its
    # covariance, as the calibration's own were.
    labels = frame_labels(usable, board, T_camera_lidar, placement_cov=covariance) if range_terms is not None else None
    fws = frame_whiteners(usable, pooled_range_noise_m([f.lidar for f in usable]), range_terms, labels)
    out = []
    for f, fw in zip(usable, fws):
        b = f.camera.T_camera_board
        _, J = corner_residuals(b, f.camera.corners_board(board), f.camera.corners_px, camera)
        cov_b = corner_noise_px**2 * np.linalg.pinv(J.T @ J)
        W = fw.W
        pi, H_x, H_b = lidar_plane(T_camera_lidar, b)
        if range_terms is None:
            e, D = lidar_residual(W, pi, f.lidar.is_scan_line)
            C = plane_noise(D, f.lidar.plane.normal, sigma_r, plane_floor_m, half, centre=fw.centre)
        else:
            e, D, H_beta = nuisance_residual(W, fw.S, fw.m_away, pi, beta, f.lidar.is_scan_line, fw.e0)
            C = frame_noise(fw, f.lidar.plane.normal, sigma_r, plane_floor_m, half, tau_m=range_scatter_m)
            if range_cov is not None:
                C = C + H_beta @ np.asarray(range_cov) @ H_beta.T
        C = C + D @ (H_b @ cov_b @ H_b.T + H_x @ covariance @ H_x.T) @ D.T
        c2 = float(e @ np.linalg.solve(C, e))
        k = int(W.shape[0])
        # The plane's distance at the board centre: the LiDAR points' centroid against the camera's plane.
        centre_l = f.lidar.points.mean(0) if not f.lidar.is_scan_line else np.append(f.lidar.points.mean(0)[:2], 0.0)
        centre_c = transform_points(T_camera_lidar, centre_l[None])[0]
        n = b[:3, 2]
        offset = float(n @ (centre_c - b[:3, 3]))
        g = np.concatenate([n @ T_camera_lidar[:3, :3] @ -skew(centre_l), n @ T_camera_lidar[:3, :3]])
        sd = float(np.sqrt(g @ covariance @ g + sigma_r**2 / max(f.lidar.n_points, 1)))
        board_centre = transform_points(b, board.outline()).mean(0)
        px = np.linalg.norm(camera.project(centre_c[None])[0] - camera.project(board_centre[None])[0])
        p = float(chi2.sf(c2, k))
        out.append(FrameScore(f.name, c2, k, p, 1000 * offset, 1000 * sd, float(px), p < SIGNIFICANCE))
    return out


def terms_from_json(section: dict | None, scatter_m: float | None = None) -> tuple:
    """``score_frames``'s range-model arguments from a pair calibration.json's ``lidar_range_model`` section (a
    list of terms in mm) or a rig LiDAR's ``range_model`` (terms by name, in m; its boards' scatter given)."""
    terms = (section or {}).get("terms") or []
    if not terms:
        return None, None, None, 0.0
    if isinstance(terms, dict):
        names = tuple(terms)
        values = np.array([float(t["value_m"]) for t in terms.values()])
        sd = np.array([float(t["sd_m"]) for t in terms.values()])
    else:
        names = tuple(str(t["term"]) for t in terms)
        values = np.array([float(t["value_mm"]) for t in terms]) / 1000.0
        sd = np.array([float(t["std_mm"]) for t in terms]) / 1000.0
    rings = tuple(int(n.split()[1]) for n in names if n.startswith("ring "))
    if scatter_m is None:
        scatter_m = float(((section or {}).get("board_terms_consistency") or {}).get("board_scatter_m", 0.0))
    return RangeTerms(names, tuple(sd.tolist()), rings), values, np.diag(sd**2), scatter_m


@dataclass(frozen=True, eq=False)
class PairCalibration:
    """What scoring a camera-LiDAR pair's frames takes from a calibration.json: the transform and its covariance,
    the noise levels it was weighed with, its LiDAR range terms (``score_frames``' arguments), the frames it
    used and the folder it calibrated."""

    T_camera_lidar: np.ndarray
    covariance: np.ndarray
    corner_noise_px: float
    range_noise_m: float
    plane_floor_m: float
    range_terms: tuple
    used: frozenset
    dataset: str

    def score(self, frames: list[FrameMeasurement], board, camera) -> list[FrameScore]:
        """``frames`` scored under this calibration (:func:`score_frames`)."""
        return score_frames(frames, board, camera, self.T_camera_lidar, self.covariance, self.corner_noise_px,
                            self.range_noise_m, self.plane_floor_m, *self.range_terms)


def pair_calibration(cal: dict, camera: str | None = None, lidar: str | None = None) -> PairCalibration:
    """A camera-LiDAR pair's :class:`PairCalibration` from a pair's calibration.json, or from a rig's (``rig:
    true``) for its sensors ``camera`` and ``lidar`` (None: its one camera and one LiDAR). Raises KeyError,
    TypeError or ValueError on a file that lacks what it needs, and LidarcamError for a rig of several cameras
    or LiDARs without the pair named."""
    if not cal.get("rig"):
        noise = cal["noise"]
        return PairCalibration(np.array(cal["T_camera_lidar"], dtype=float).reshape(4, 4),
                               np.array(cal["covariance"], dtype=float).reshape(6, 6),
                               float(noise["corner_noise_px"]), float(noise["range_noise_m"]),
                               float(noise.get("plane_floor_m") or 0.0), terms_from_json(cal.get("lidar_range_model")),
                               frozenset(f["name"] for f in cal.get("frames", []) if f.get("used")),
                               str(cal.get("dataset", "")))
    sensors = {s["name"]: s for s in cal["sensors"]}
    if camera is None or lidar is None:
        cams = [n for n, s in sensors.items() if s["type"] == "camera"]
        lidars = [n for n, s in sensors.items() if s["type"] != "camera"]
        if len(cams) != 1 or len(lidars) != 1:
            raise LidarcamError(f"a rig's calibration of {len(cams)} camera(s) and {len(lidars)} LiDAR(s), where a "
                                "camera-LiDAR pair's folder is given", hint="validate the rig's folder with it")
        camera, lidar = cams[0], lidars[0]
    pair, cam, lid = cal["transforms"][f"T_{camera}_{lidar}"], sensors[camera]["noise"], sensors[lidar]["noise"]
    return PairCalibration(np.array(pair["T"], dtype=float).reshape(4, 4),
                           np.array(pair["covariance"], dtype=float).reshape(6, 6), float(cam["corner_noise_px"]),
                           float(lid["range_noise_m"]), float(lid["plane_floor_m"]),
                           terms_from_json(sensors[lidar].get("range_model"), float(lid["board_scatter_m"])),
                           frozenset(sensors[lidar]["frames"] if "frames" in sensors[lidar] else
                                     cal["frames_used"][lidar]), str(cal.get("dataset", "")))


def verdict(scores: list[FrameScore]) -> dict:
    """One verdict over the scored frames: the sum of their chi-squares against its degrees of freedom."""
    if not scores:
        return {"frames": 0, "verdict": "no frame to score"}
    stat, dof = sum(s.chi2 for s in scores), sum(s.dof for s in scores)
    p = float(chi2.sf(stat, dof))
    return {"frames": len(scores), "chi2": stat, "dof": dof, "p_value": p,
            "flagged": [s.name for s in scores if s.flagged],
            "verdict": ("consistent with the covariance and the noise" if p >= SIGNIFICANCE else
                        "NOT consistent: the held-out frames disagree with the calibration beyond its covariance "
                        "and the noise (an unmodelled error, or wrong segments)")}


def refuse_runs(frames: int, folds: int | None = None, split: str | None = None,
                what: str = "frames with a board") -> None:
    """Raises the one-line error of ``--cross-validate K`` (``folds``) or ``--split`` (``split``) that ``frames``
    frames cannot serve; the command line asks before it writes or prints the calibration they follow."""
    if folds is not None and (folds < 2 or folds > frames):
        raise LidarcamError(f"--cross-validate {folds}: needs 2 <= K <= the rig's {frames} frames with a board",
                            hint="choose a smaller K")
    if split is not None and frames < 6:
        raise LidarcamError(f"--split {split} needs at least 6 {what} (3 per half), got {frames}",
                            hint="record more board poses")


def cross_validate_rig(measurements, board, k: int, solve) -> dict:
    """K-fold over a rig's frames (``measurements``: ``RigMeasurements``; its stems in name order, round robin):
    each fold's camera-LiDAR pairs scored on their held-out frames under the rig calibrated from the others
    (``solve(stems)`` -> a ``RigResult``), as ``lidarcam validate`` scores a rig (:func:`pair_calibration` of the
    fold's calibration.json). One verdict per camera-LiDAR pair (two pairs share a LiDAR's boards)."""
    stems = sorted(measurements.stems)
    refuse_runs(len(stems), folds=k)
    folds, scores = [], {}
    for j in range(k):
        held = [st for i, st in enumerate(stems) if i % k == j]
        try:
            cal = solve([st for i, st in enumerate(stems) if i % k != j]).to_json()
        except DegenerateLayoutError as exc:
            folds.append({"fold": j, "held_out": held, "error": exc.message})
            continue
        fold = {}
        for (cam, lid), frames in measurements.pairs.items():
            try:
                pc = pair_calibration(cal, cam, lid)
            except KeyError:  # a sensor the fold's graph could not hold
                continue
            s = pc.score([f for f in frames if f.usable and f.name in held], board, measurements.cameras[cam])
            scores.setdefault(f"T_{cam}_{lid}", []).extend(s)
            fold[f"T_{cam}_{lid}"] = [x.to_dict() for x in s]
        folds.append({"fold": j, "held_out": held, "pairs": fold})
    return {"k": k, "folds": folds, "pairs": {n: verdict(s) for n, s in scores.items()}}


SPLITS = ("halves", "interleaved")


def _solved_halves(items: list, solve, how: str, what: str) -> tuple[list, list | str]:
    """``items`` (in name order) in two halves, the first and last (``halves``) or the even and odd
    (``interleaved``), and ``solve`` of each; the reason instead of the solutions when a half cannot be solved."""
    if how not in SPLITS:
        raise ValueError(f"Expected how in {SPLITS}, got {how!r}")
    refuse_runs(len(items), split=how, what=what)
    h = len(items) // 2
    halves = [items[:h], items[h:]] if how == "halves" else [items[0::2], items[1::2]]
    try:
        return halves, [solve(part) for part in halves]
    except DegenerateLayoutError as exc:
        return halves, f"a half could not be calibrated alone ({exc.message})"


def split_rig_halves(stems: list[str], solve, how: str = "halves") -> dict:
    """A rig's frames (``stems``, in name order) in two halves (:func:`_solved_halves`), each calibrated
    apart (``solve(stems)`` -> a ``RigResult``), and their difference tested against the sum of their covariances:
    every sensor's pose together (chi-square on 6 per sensor but the reference) and each camera-LiDAR pair alone
    (6 dof each: the sharper test of one sensor that moved, which the joint test's many degrees of freedom dilute)."""
    halves, res = _solved_halves(stems, solve, how, "frames with a board")
    if isinstance(res, str):
        return {"split": how, "halves": halves, "verdict": res}
    sol = res[0].solution
    names = [n for n in sol.names if n != sol.reference]
    xi = np.concatenate([T_log(T_inverse(sol.T_ref[n]) @ res[1].solution.T_ref[n]) for n in names])
    idx = np.concatenate([np.arange(6 * k, 6 * k + 6) for k, n in enumerate(sol.names) if n != sol.reference])
    d2, dof = chi2.mahalanobis(xi, sum(r.solution.covariance_joint[np.ix_(idx, idx)] for r in res))
    pairs = {}
    for a, b in res[0].pairs():
        if a in res[0].cameras and b not in res[0].cameras:
            (T1, C1), (T2, C2) = (r.solution.transform(a, b) for r in res)
            x = T_log(T_inverse(T1) @ T2)
            pd2, pdof = chi2.mahalanobis(x, C1 + C2)
            pairs[f"T_{a}_{b}"] = {"difference_rotation_deg": float(np.degrees(np.linalg.norm(x[:3]))),
                                   "difference_translation_mm": float(1000 * np.linalg.norm(x[3:])),
                                   "mahalanobis_d2": pd2, "dof": pdof, "p_value": float(chi2.sf(pd2, pdof))}
    limit = float(chi2.ppf(1 - SIGNIFICANCE, dof))
    return {"split": how, "halves": halves, "mahalanobis_d2": d2, "dof": dof, "limit_99": limit,
            "p_value": float(chi2.sf(d2, dof)), "pairs": pairs,
            "verdict": ("the halves agree within their covariances" if d2 <= limit else
                        "the halves disagree beyond their covariances: an error the model does not hold "
                        "(range biases, intrinsics, a moved sensor)")}
