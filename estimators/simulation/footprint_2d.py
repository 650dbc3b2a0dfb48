"""A second 2D generator, written apart from the default simulator so that a claim about 2D scans does not rest on
one generator's assumptions.

Where ``simulator`` casts one exact ray per beam against 3D patches, this one works in the scan plane: the scene
is a set of 2D segments (the room's walls, pillars, each board's cut by the scan plane, its stand's posts), and
each beam is a bundle of sub-rays across its divergence, weighted by a Gaussian profile. A beam returns from the
nearest surface that holds enough of its weighted, reflectance-scaled energy; where two surfaces share the
footprint within the pulse's resolution, the range is their energy-weighted mix (a mixed return at the board's
edge). Black squares reflect little, so a beam half on a black square and half on the wall behind can return the
wall. Noise is along the beam or isotropic in the plane; the scanner's first beam sits at any angle (not a
multiple of its step); scans are given as (N, 2) points, as a recording is read.

The camera's side is measured from the board's inner corners projected through the camera model with pixel
noise, and its pose fitted as a detection's (``camera.board_pose``); the LiDAR's board segment is found in the
whole scan by the pipeline's own segmentation (``lidar.scan_segmentation``) over the static scene of all scans.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, transform_points

from ..camera.board_pose import estimate_board_pose
from ..camera.detection import CornerDetection
from ..errors import MeasurementError
from ..lidar.lidar_models import scanner2d
from ..lidar.scan_segmentation import ScanSegmentationParams, scan_candidates
from ..lidar.static_scene import build_static_scene
from ..measurements import FrameMeasurement

NOISE_KINDS = ("range", "xy")


@dataclass(frozen=True)
class Scanner:
    """A single-line scanner: its beams' angles (``first_rad + k step_rad``), range noise (``noise``: along the
    beam, or isotropic in the scan plane), the beam's divergence (full width of the Gaussian profile at 1/e^2), the
    share of a beam's energy a surface must return to be seen, and the range within which two surfaces in one
    footprint mix into one return."""

    first_rad: float = -np.deg2rad(135.0)
    step_rad: float = np.deg2rad(0.25)
    beams: int = 1081
    sigma_m: float = 0.01
    noise: str = "range"
    divergence_rad: float = np.deg2rad(0.3)
    detect_share: float = 0.35
    mix_m: float = 0.3
    max_range_m: float = 30.0
    sub_rays: int = 9

    def angles(self) -> np.ndarray:
        return self.first_rad + self.step_rad * np.arange(self.beams)


@dataclass(frozen=True)
class Segment:
    """A surface in the scan plane from ``a`` to ``b`` (2D, LiDAR frame); ``reflectance(s)`` at the share ``s`` of
    its length (a constant, or a function for a board's squares)."""

    a: np.ndarray
    b: np.ndarray
    reflectance: object
    label: str = ""

    def reflect(self, s: np.ndarray) -> np.ndarray:
        return self.reflectance(s) if callable(self.reflectance) else np.full(len(s), float(self.reflectance))


def _hits(origin_dirs: np.ndarray, segments: list[Segment]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of unit rays from the origin against the segments: range (inf: none), segment index (-1) and
    reflectance."""
    n = len(origin_dirs)
    best = np.full(n, np.inf)
    which = np.full(n, -1)
    refl = np.zeros(n)
    for k, seg in enumerate(segments):
        e = seg.b - seg.a
        # origin + t d = a + s e  ->  [d, -e] [t, s]^T = a
        det = origin_dirs[:, 0] * (-e[1]) - origin_dirs[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (seg.a[0] * (-e[1]) - seg.a[1] * (-e[0])) / det
            s = (origin_dirs[:, 0] * seg.a[1] - origin_dirs[:, 1] * seg.a[0]) / det
        ok = np.isfinite(t) & (t > 1e-6) & (s >= 0) & (s <= 1) & (t < best)
        best[ok] = t[ok]
        which[ok] = k
        refl[ok] = seg.reflect(s[ok])
    return best, which, refl


def scan(scanner: Scanner, segments: list[Segment], rng: np.random.Generator) -> np.ndarray:
    """One scan: (N, 2) points of the beams that return (module docstring)."""
    angles = scanner.angles()
    sd = scanner.divergence_rad / 4.0  # the profile's 1/e^2 half width is two standard deviations
    offsets = np.linspace(-2.0, 2.0, scanner.sub_rays) * sd
    weights = np.exp(-0.5 * (offsets / max(sd, 1e-12)) ** 2)
    weights /= weights.sum()
    a = (angles[:, None] + offsets[None, :]).ravel()
    r, which, refl = _hits(np.column_stack([np.cos(a), np.sin(a)]), segments)
    r, which, refl = (x.reshape(len(angles), -1) for x in (r, which, refl))
    energy = np.where(np.isfinite(r) & (r <= scanner.max_range_m), weights[None, :] * refl, 0.0)
    out_r = np.full(len(angles), np.nan)
    for i in range(len(angles)):
        total = energy[i].sum()
        if total <= 0:
            continue
        surfaces = [k for k in np.unique(which[i]) if k >= 0]
        shares = {k: energy[i][which[i] == k].sum() / total for k in surfaces}
        means = {k: float(np.average(r[i][which[i] == k], weights=weights[which[i] == k])) for k in surfaces}
        seen = sorted((means[k], k) for k in surfaces if shares[k] >= scanner.detect_share)
        if not seen:
            continue
        first_r, first = seen[0]
        # Surfaces within the pulse's resolution of the first one mix into its return, by energy.
        near = [k for k in surfaces if abs(means[k] - first_r) <= scanner.mix_m and energy[i][which[i] == k].sum() > 0]
        w = np.array([shares[k] for k in near])
        out_r[i] = float(np.dot(w, [means[k] for k in near]) / w.sum())
    keep = np.isfinite(out_r)
    ang, rr = angles[keep], out_r[keep]
    if scanner.noise == "range":
        rr = rr + rng.normal(0.0, scanner.sigma_m, len(rr))
        return np.column_stack([rr * np.cos(ang), rr * np.sin(ang)])
    P = np.column_stack([rr * np.cos(ang), rr * np.sin(ang)])
    return P + rng.normal(0.0, scanner.sigma_m, P.shape)


def board_cut(board: BoardModel, T_lidar_board: np.ndarray, black: float = 0.06, white: float = 0.8
              ) -> Segment | None:
    """The board's cut by the scan plane (z = 0 of the LiDAR) as a segment whose reflectance follows the squares
    it crosses (the border white), or None when the plane misses the board."""
    w, h = board.extent
    R, o = T_lidar_board[:3, :3], T_lidar_board[:3, 3]
    pts = []
    # z(u, v) = o_z + u R_20 + v R_21 = 0 on the rectangle [0, w] x [0, h].
    for u in (0.0, w):
        if abs(R[2, 1]) > 1e-12:
            v = -(o[2] + u * R[2, 0]) / R[2, 1]
            if 0.0 <= v <= h:
                pts.append((u, v))
    for v in (0.0, h):
        if abs(R[2, 0]) > 1e-12:
            u = -(o[2] + v * R[2, 1]) / R[2, 0]
            if 0.0 <= u <= w:
                pts.append((u, v))
    if len(pts) < 2:
        return None
    pts = np.array(pts)
    i, j = np.unravel_index(np.argmax(np.linalg.norm(pts[:, None] - pts[None], axis=2)), (len(pts), len(pts)))
    uv0, uv1 = pts[i], pts[j]
    if np.linalg.norm(uv1 - uv0) < 1e-6:
        return None
    ox, oy = board.offset
    nx, ny = board.squares
    sq = board.square_size

    def reflectance(s: np.ndarray) -> np.ndarray:
        uv = uv0[None] + s[:, None] * (uv1 - uv0)[None]
        i_ = np.floor((uv[:, 0] - ox) / sq)
        j_ = np.floor((uv[:, 1] - oy) / sq)
        inside = (i_ >= 0) & (i_ < nx) & (j_ >= 0) & (j_ < ny)
        dark = inside & ((i_ + j_) % 2 == 0)
        return np.where(dark, black, white)

    a3 = R @ np.array([uv0[0], uv0[1], 0.0]) + o
    b3 = R @ np.array([uv1[0], uv1[1], 0.0]) + o
    return Segment(a3[:2], b3[:2], reflectance, "board")


def room(rng: np.random.Generator) -> list[Segment]:
    """Walls of a room 8-14 m by 6-10 m around the scanner (off centre) and two square pillars."""
    x0, x1 = -rng.uniform(2.0, 4.0), rng.uniform(6.0, 10.0)
    y0, y1 = -rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0)
    c = [np.array(p) for p in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    segs = [Segment(c[k], c[(k + 1) % 4], 0.6, "wall") for k in range(4)]
    for _ in range(2):
        px, py = rng.uniform(5.0, x1 - 0.5), rng.choice([-1.0, 1.0]) * rng.uniform(2.0, y1 - 0.5)
        s = 0.2
        q = [np.array(p) for p in ((px - s, py - s), (px + s, py - s), (px + s, py + s), (px - s, py + s))]
        segs += [Segment(q[k], q[(k + 1) % 4], 0.5, "pillar") for k in range(4)]
    return segs


@dataclass(frozen=True, eq=False)
class Rig2D:
    """The second generator's rig: the camera, the scanner, the board (1 x 1 m, pattern centred),
    ``T_camera_lidar``, the scanner's height above the floor and the camera's corner noise (px)."""

    camera: CameraModel
    scanner: Scanner
    board: BoardModel
    T_camera_lidar: np.ndarray
    height_m: float
    corner_noise_px: float = 0.25


def second_camera() -> CameraModel:
    K = np.array([[820.0, 0.0, 645.0], [0.0, 820.0, 478.0], [0.0, 0.0, 1.0]])
    return CameraModel(K=K, dist=np.array([-0.18, 0.05, 0.0002, 0.0003, 0.0]), width=1280, height=960,
                       source="second 2D generator")


def second_rig(rng: np.random.Generator, sigma_m: float = 0.01, noise: str | None = None) -> Rig2D:
    """A rig of this generator: the scanner 0.4-1.0 m above the floor, the camera 8-25 cm above it and up to 10
    cm to either side, looking ahead within 4 degrees; the beam's divergence 0.1-0.6 degrees; the first beam
    anywhere within a step; noise along the beam or in the plane (at random unless given)."""
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]) @ R_from_rotvec(
        rng.normal(0.0, np.deg2rad(2.0), 3))
    camera_in_lidar = np.array([rng.uniform(-0.05, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.08, 0.25)])
    step = np.deg2rad(0.25)
    scanner = Scanner(first_rad=-np.deg2rad(135.0) + rng.uniform(0.0, step), step_rad=step, sigma_m=sigma_m,
                      noise=noise or str(rng.choice(NOISE_KINDS)),
                      divergence_rad=np.deg2rad(rng.uniform(0.1, 0.6)))
    board = BoardModel(squares=(8, 7), square_size=0.11, size=(1.0, 1.0))
    return Rig2D(second_camera(), scanner, board, T_from_Rt(R, -R @ camera_in_lidar), rng.uniform(0.4, 1.0))


def second_poses(rig: Rig2D, n: int, rng: np.random.Generator, max_tries: int = 20000) -> list[np.ndarray]:
    """``n`` board poses (``T_camera_board``): the board 1.2-5 m ahead within the camera's view, facing the rig
    within 60 degrees, leaning up to 25 degrees back or forward and rolled up to 20, its bottom above the floor,
    the scan plane crossing it between a fifth and four fifths of its height; every inner corner 10 px inside the
    image."""
    w, h = rig.board.extent
    poses = []
    for k in range(n):
        for _ in range(max_tries):
            dist = rng.uniform(1.2, 5.0)
            bearing = rng.uniform(-0.6, 0.6)
            cross = rng.uniform(0.2, 0.8)
            yaw = rng.uniform(-np.deg2rad(60.0), np.deg2rad(60.0))
            lean = rng.uniform(-np.deg2rad(25.0), np.deg2rad(25.0))
            roll = rng.uniform(-np.deg2rad(20.0), np.deg2rad(20.0))
            # Board axes in the LiDAR frame facing it: x to the right (-y), y down (-z), z away (+x).
            R0 = np.column_stack([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
            R = R_from_rotvec([0.0, 0.0, bearing + yaw]) @ R0 @ R_from_rotvec([lean, 0.0, 0.0]) @ R_from_rotvec(
                [0.0, 0.0, roll])
            # The board's point at (w/2, cross h) on the scan plane, ``dist`` ahead along ``bearing``.
            anchor = np.array([dist * np.cos(bearing), dist * np.sin(bearing), 0.0])
            T_lb = T_from_Rt(R, anchor - R @ np.array([w / 2, cross * h, 0.0]))
            corners = transform_points(T_lb, rig.board.outline())
            if corners[:, 2].min() < -rig.height_m + 0.05:
                continue
            T_cb = rig.T_camera_lidar @ T_lb
            if T_cb[:3, 2] @ T_cb[:3, 3] <= 0:
                continue
            uv = rig.camera.project(transform_points(T_cb, rig.board.inner_corners()))
            if not np.all(rig.camera.in_image(uv, margin_px=10.0)):
                continue
            cut = board_cut(rig.board, T_lb)
            if cut is None or np.linalg.norm(cut.b - cut.a) < 0.4:
                continue
            poses.append(T_cb)
            break
        else:
            raise RuntimeError(f"no feasible pose for board {k} in {max_tries} tries")
    return poses


def stand_posts(board: BoardModel, T_lidar_board: np.ndarray) -> list[Segment]:
    """The stand under a board, where the scan plane passes below it: two posts 3 cm wide under its lower
    corners, 4 cm behind it."""
    o = transform_points(T_lidar_board, board.outline())
    if o[:, 2].min() <= 0.0:
        return []
    n = T_lidar_board[:3, 2]
    lows = o[np.argsort(o[:, 2])[:2]]
    segs = []
    for p in lows:
        c = p[:2] + 0.04 * n[:2] / max(np.linalg.norm(n[:2]), 1e-9)
        along = np.array([-n[1], n[0]]) / max(np.linalg.norm(n[:2]), 1e-9)
        segs.append(Segment(c - 0.015 * along, c + 0.015 * along, 0.4, "stand"))
    return segs


def measure(rig: Rig2D, poses: list[np.ndarray], rng: np.random.Generator, walls: list[Segment] | None = None
            ) -> list[FrameMeasurement]:
    """Each pose's frame as the pipeline measures it: the camera's board pose from noisy corners, the LiDAR's
    board segment found in the whole scan over the static scene of every scan (the best candidate where the
    camera puts the board)."""
    walls = room(rng) if walls is None else walls
    T_lidar_camera = T_inverse(rig.T_camera_lidar)
    scans, cams = [], []
    for T_cb in poses:
        T_lb = T_lidar_camera @ T_cb
        cut = board_cut(rig.board, T_lb)
        scans.append(scan(rig.scanner, [cut] + stand_posts(rig.board, T_lb) + walls, rng))
        uv = rig.camera.project(transform_points(T_cb, rig.board.inner_corners()))
        uv = uv + rng.normal(0.0, rig.corner_noise_px, uv.shape)
        try:
            cams.append((estimate_board_pose(CornerDetection(uv, "simulated"), rig.board, rig.camera), None))
        except MeasurementError as exc:
            cams.append((None, f"board pose: {exc.message}"))
    scene = build_static_scene(scans)
    frames = []
    for k, (cam, why) in enumerate(cams):
        name = f"{k:04d}"
        if cam is None:
            frames.append(FrameMeasurement(name, None, None, why))
            continue
        try:
            found = scan_candidates(scans[k], rig.board, cam, ScanSegmentationParams(),
                                    foreground=scene.frame_foreground(k))
        except MeasurementError as exc:
            frames.append(FrameMeasurement(name, cam, None, f"LiDAR board: {exc.message}"))
            continue
        frames.append(FrameMeasurement(name, cam, found[0][1], None))
    return frames


def layout_trial(seed: int, n_boards: int, sigma_m: float = 0.01, noise: str | None = None
                 ) -> tuple[Rig2D, list[np.ndarray], list[FrameMeasurement]]:
    """One layout of this generator: the rig, its ``n_boards`` poses and their measured frames."""
    rng = np.random.default_rng([seed, 2026])
    rig = second_rig(rng, sigma_m, noise)
    poses = second_poses(rig, n_boards, rng)
    return rig, poses, measure(rig, poses, rng)


def as_beam_model(rig: Rig2D):
    """The scanner as the project's beam model (its angles and noise; no footprint): for the bound."""
    s = rig.scanner
    return replace(scanner2d(s.sigma_m), azimuth_step_rad=s.step_rad,
                   azimuth_limits_rad=(s.first_rad, s.first_rad + s.step_rad * (s.beams - 1)))
