"""Simulated calibration datasets with ground truth: rendered images and ray-cast LiDAR sweeps.

The default rig follows the published planar method's setup: a 1024 x 768 camera with f ~ 940 px, a
1 m x 1 m board with 9 x 7 squares of 10 cm, an HDL-64E-like LiDAR, the camera about 15 cm ahead of and
20 cm below the LiDAR. The scene (LiDAR frame, z up) holds the board on a thin stand, the ground and
four walls.
"""
from __future__ import annotations

import contextlib
import json
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from geometry.board import CHARUCO, PATTERNS, BoardModel
from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, transform_points

from ..camera.charuco import pattern_reflectance
from ..io.dataset import dataset_spec, write_dataset_yaml
from ..io.output import atomic_directory, check_output_folder
from ..io.pointcloud_io import write_scan, write_scan_2d
from ..lidar.lidar_models import BEAM_MODELS, RING_PRIOR_SHARE, BeamModel, range_accuracy_for
from .office import SCENES, board_fraction_in_fov, hall_layout, holder, office_layout
from .range_bias import RangeBias
from .rendering import add_pixel_noise, pixel_rays, render_clean
from .scene import Background, Patch, cast, cast_background, infinite_plane, rectangle

# LiDAR (x forward, y left, z up) to camera (x right, y down, z forward) axes.
R_CAMERA_LIDAR_NOMINAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True, eq=False)
class Rig:
    camera: CameraModel
    beams: BeamModel
    board: BoardModel
    T_camera_lidar: np.ndarray
    lidar_height_m: float = 1.8
    pixel_noise: float = 2.0
    min_distance_m: float = 2.0
    max_distance_m: float = 5.0
    # 2D: the scan plane must cut the board over at least this share of its smaller side.
    min_crossing: float = 0.4
    # What holds the board in the default scene (STANDS): "post" (one thin post under it), "uprights" (an
    # aluminium stand: two uprights just beside the board's ends, a few centimetres behind it, from the ground to
    # above it, on feet) or "tripod" (a head behind the board's centre, a column and three splayed legs).
    stand: str = "post"
    # The scanner's mounting against the world: the rotation from the LiDAR's axes to the level frame (the
    # LiDAR's origin, z up), in which the ground lies ``lidar_height_m`` below and the stands stand; None: level
    # (an upside-down or tilted scanner has another).
    R_level_lidar: np.ndarray | None = None
    # 2D: every board's centre at this height (m) in the level frame (boards on stands of one height); None:
    # heights vary with where the board is in the image.
    board_height_m: float | None = None

    @property
    def level(self) -> np.ndarray:
        """``R_level_lidar`` (identity for a level scanner)."""
        return np.eye(3) if self.R_level_lidar is None else self.R_level_lidar


STANDS = ("post", "uprights", "tripod")


def rotated_patches(patches: list[Patch], R: np.ndarray) -> list[Patch]:
    """Scene pieces turned by the rotation ``R`` about the origin (the LiDAR's): from the level frame into the
    LiDAR's with ``R = R_level_lidar^T``."""
    if np.allclose(R, np.eye(3)):
        return list(patches)
    return [replace(p, normal=R @ p.normal, origin=None if p.origin is None else R @ p.origin,
                    u=None if p.u is None else R @ p.u, v=None if p.v is None else R @ p.v) for p in patches]


def default_camera() -> CameraModel:
    K = np.array([[940.0, 0.0, 512.0], [0.0, 940.0, 384.0], [0.0, 0.0, 1.0]])
    return CameraModel(K=K, dist=np.array([-0.10, 0.06, 0.0005, -0.0004, 0.0]), width=1024, height=768,
                       source="simulator")


def default_board() -> BoardModel:
    return BoardModel(squares=(9, 7), square_size=0.10, size=(1.0, 1.0))


def as_charuco(board: BoardModel, dictionary: str = "DICT_5X5_100") -> BoardModel:
    """The same board printed as ChArUco: markers of 70% of the square in the white squares."""
    return replace(board, pattern=CHARUCO, marker_size=0.7 * board.square_size, dictionary=dictionary)


def board_reflectance(board: BoardModel):
    """The board's reflectance as a function of board coordinates (NaN outside): the checkerboard's own, or
    for a ChArUco board OpenCV's printed pattern (its markers included); ``camera.charuco.pattern_reflectance``."""
    return pattern_reflectance(board)


def default_rig(rng: np.random.Generator, lidar: str = "hdl64e", sigma_range_m: float = 0.02) -> Rig:
    """The published rig, with a small random deviation of the mounting from its nominal pose."""
    if lidar not in BEAM_MODELS:
        raise ValueError(f"Expected lidar in {sorted(BEAM_MODELS)}, got {lidar!r}")
    R = R_CAMERA_LIDAR_NOMINAL @ R_from_rotvec(rng.normal(0.0, np.deg2rad(1.5), 3))
    camera_in_lidar = np.array([0.15, 0.0, -0.20]) + rng.normal(0.0, 0.01, 3)
    return Rig(camera=default_camera(), beams=BEAM_MODELS[lidar](sigma_range_m), board=default_board(),
               T_camera_lidar=T_from_Rt(R, -R @ camera_in_lidar))


def default_rig_2d(rng: np.random.Generator, sigma_range_m: float = 0.01) -> Rig:
    """A 2D scanner 60 cm above the floor and the camera about 10 cm above its scan plane, boards 1.5-4 m
    away (the scan plane must cut them), with a small random deviation of the mounting."""
    R = R_CAMERA_LIDAR_NOMINAL @ R_from_rotvec(rng.normal(0.0, np.deg2rad(1.5), 3))
    camera_in_lidar = np.array([0.05, 0.0, 0.10]) + rng.normal(0.0, 0.01, 3)
    return Rig(camera=default_camera(), beams=BEAM_MODELS["2d"](sigma_range_m), board=default_board(),
               T_camera_lidar=T_from_Rt(R, -R @ camera_in_lidar), lidar_height_m=0.6, min_distance_m=1.5,
               max_distance_m=4.0)


RIGS_2D = ("default", "varied", "mounted")


def varied_rig_2d(rng: np.random.Generator, sigma_range_m: float | None = None) -> Rig:
    """A second, independent 2D configuration, drawn per rig (to check that nothing is tuned to the default):
    the scanner 0.3-1.5 m above the floor with its scan plane tilted up to 12 degrees about either horizontal
    axis against the camera; the camera 0-30 cm from the scanner in any direction; a 1024x768 (f 940 px) or
    wide 1280x800 (f 640 px) camera; boards 0.5-1.5 m wide with aspect ratios 0.6-1.6 and 6-15 cm squares;
    boards 0.5-8 m away, cut anywhere from a quarter of their height; 0.25 or 0.5 degree steps; range noise
    0.5-3 cm unless given."""
    tilt = np.deg2rad(rng.uniform(-12.0, 12.0, 2))
    R = R_CAMERA_LIDAR_NOMINAL @ R_from_rotvec([tilt[0], tilt[1], rng.normal(0.0, np.deg2rad(3.0))])
    camera_in_lidar = np.array([rng.uniform(-0.1, 0.2), rng.uniform(-0.3, 0.3), rng.uniform(-0.25, 0.3)])
    if rng.uniform() < 0.5:
        camera = default_camera()
    else:
        K = np.array([[640.0, 0.0, 640.0], [0.0, 640.0, 400.0], [0.0, 0.0, 1.0]])
        camera = CameraModel(K=K, dist=np.array([-0.25, 0.08, 0.0, 0.0, -0.01]), width=1280, height=800,
                             source="simulator")
    width = rng.uniform(0.5, 1.5)
    height = float(np.clip(width * rng.uniform(0.6, 1.6), 0.4, 1.8))
    square = rng.uniform(0.06, 0.15)
    squares = (int(np.clip((width - 0.06) // square, 4, 12)), int(np.clip((height - 0.06) // square, 4, 12)))
    square = min(square, (width - 0.05) / squares[0], (height - 0.05) / squares[1])
    board = BoardModel(squares=squares, square_size=square, size=(width, height))
    sigma = rng.uniform(0.005, 0.03) if sigma_range_m is None else sigma_range_m
    beams = replace(BEAM_MODELS["2d"](sigma), azimuth_step_rad=np.deg2rad(rng.choice([0.25, 0.5])))
    return Rig(camera=camera, beams=beams, board=board, T_camera_lidar=T_from_Rt(R, -R @ camera_in_lidar),
               lidar_height_m=rng.uniform(0.3, 1.5), min_distance_m=0.5, max_distance_m=8.0, min_crossing=0.25)


def mounted_rig_2d(rng: np.random.Generator, sigma_range_m: float | None = None) -> Rig:
    """A third 2D configuration, unlike the other two in how the scanner is mounted: upside down on half the
    rigs; then either its scan plane tilted 10-30 degrees about a horizontal axis (rolled, or pitched with the
    camera pitched to within 10 degrees of it) or the camera 0.5 m from it in a random direction. Angular steps
    0.25-1 degree, range noise 0.5-3 cm unless given, boards 0.4-1.2 m (aspect ratio 0.7-1.4, 4-10 squares a
    side) 0.8-6 m away, the scanner 0.4-1.5 m above the ground (higher where its plane falls ahead, to meet the
    ground 2.5 m ahead); on half the rigs every board's centre at one height (where the scan plane passes 1.5-3
    m ahead), else at the heights the image positions give. A rig on which 6 board poses (one per sixth of the
    normals' azimuths) are not found in 2000 tries each (a steep plane and a large board) is drawn again."""
    for _ in range(20):
        rig = _mounted_rig_once(rng, sigma_range_m)
        try:
            sample_board_poses(rig, 6, np.random.default_rng(rng.integers(2**63)), max_tries=2000)
        except RuntimeError:
            continue
        return rig
    raise RuntimeError("no mounted 2D rig with a feasible board pose in 20 draws")


def _mounted_rig_once(rng: np.random.Generator, sigma_range_m: float | None) -> Rig:
    """One draw of :func:`mounted_rig_2d`'s rig."""
    R_level_lidar = R_from_rotvec([np.pi, 0.0, 0.0]) if rng.uniform() < 0.5 else np.eye(3)
    # The camera looking ahead in the level frame, within a few degrees.
    R_level_camera = R_from_rotvec(rng.normal(0.0, np.deg2rad(3.0), 3)) @ R_CAMERA_LIDAR_NOMINAL.T
    if rng.uniform() < 0.5:
        # Tilted about the forward axis (roll), or about the sideways axis (pitch), when the camera looks up or
        # down with it to within 10 degrees (a scan plane pitched 20 degrees from the camera's axis leaves the
        # image where the camera sees a whole board).
        angle = np.deg2rad(rng.uniform(10.0, 30.0)) * rng.choice([-1.0, 1.0])
        if rng.uniform() < 0.5:
            R_level_lidar = R_from_rotvec([angle, 0.0, 0.0]) @ R_level_lidar
        else:
            R_level_lidar = R_from_rotvec([0.0, angle, 0.0]) @ R_level_lidar
            R_level_camera = R_from_rotvec([0.0, angle + np.deg2rad(rng.uniform(-10.0, 10.0)), 0.0]) @ R_level_camera
        camera_in_level = np.array([0.05, 0.0, 0.12]) + rng.normal(0.0, 0.02, 3)
    else:
        d = rng.normal(size=3)
        d[0] = 0.5 * abs(d[0])  # not far behind the scanner's origin
        camera_in_level = 0.5 * d / np.linalg.norm(d)
    R_camera_level = R_level_camera.T
    R = R_camera_level @ R_level_lidar
    camera_in_lidar = R_level_lidar.T @ camera_in_level
    width = rng.uniform(0.4, 1.2)
    height = float(np.clip(width * rng.uniform(0.7, 1.4), 0.4, 1.2))
    squares = (int(rng.integers(4, 11)), int(rng.integers(4, 11)))
    square = min((width - 0.04) / squares[0], (height - 0.04) / squares[1])
    board = BoardModel(squares=squares, square_size=square, size=(width, height))
    sigma = rng.uniform(0.005, 0.03) if sigma_range_m is None else sigma_range_m
    beams = replace(BEAM_MODELS["2d"](sigma), azimuth_step_rad=np.deg2rad(rng.uniform(0.25, 1.0)))
    n = R_level_lidar[:, 2]
    drop = n[0] / n[2]  # the scan plane's fall per metre ahead (level frame): it passes z = -drop x
    # A scan plane that falls ahead meets the ground at least 2.5 m ahead (nearer, no board both stands on the
    # ground and is seen whole by the camera where the plane cuts it).
    lidar_height = max(rng.uniform(0.4, 1.5), 2.5 * drop)
    board_height = None
    if rng.uniform() < 0.5:
        # Where the scan plane passes a point 1.5-3 m ahead (of those whose board would stand on the ground and
        # below 1.2 m; none: heights vary).
        ahead = rng.uniform(1.5, 3.0, 64)
        z = -drop * ahead
        ok = (z > -lidar_height + 0.15 + height / 2) & (z < 1.2)
        board_height = float(z[ok][0]) if ok.any() else None
    return Rig(camera=default_camera(), beams=beams, board=board, T_camera_lidar=T_from_Rt(R, -R @ camera_in_lidar),
               lidar_height_m=lidar_height, min_distance_m=0.8, max_distance_m=6.0, min_crossing=0.25,
               R_level_lidar=R_level_lidar, board_height_m=board_height)


def rig_2d(config: str, rng: np.random.Generator, sigma_range_m: float | None = None) -> Rig:
    """The 2D rig of simulator configuration ``config`` (``RIGS_2D``)."""
    if config == "default":
        return default_rig_2d(rng, 0.01 if sigma_range_m is None else sigma_range_m)
    if config == "varied":
        return varied_rig_2d(rng, sigma_range_m)
    if config == "mounted":
        return mounted_rig_2d(rng, sigma_range_m)
    raise ValueError(f"Expected config in {RIGS_2D}, got {config!r}")


def _board_rotation(ray: np.ndarray, tilt: float, azimuth: float, spin: float) -> np.ndarray:
    """Board axes (columns x, y, z) in the camera frame: normal ``z`` tilted by ``tilt`` from the viewing ray
    towards ``azimuth``, the board's x turned by ``spin`` about its normal from the camera's x."""
    a = np.cross(ray, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(ray, a)
    axis = np.cos(azimuth) * a + np.sin(azimuth) * b
    n = R_from_rotvec(axis * tilt) @ ray
    x0 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    x0 /= np.linalg.norm(x0)
    x = R_from_rotvec(n * spin) @ x0
    return np.column_stack([x, np.cross(n, x), n])


def board_pose(board: BoardModel, centre: np.ndarray, tilt: float, azimuth: float, spin: float) -> np.ndarray:
    """``T_camera_board`` of a board whose centre is at ``centre`` (camera frame, m), its normal tilted by
    ``tilt`` from the line of sight towards ``azimuth`` and turned by ``spin`` about itself (radians)."""
    c = np.asarray(centre, dtype=float)
    R = _board_rotation(c / np.linalg.norm(c), tilt, azimuth, spin)
    return T_from_Rt(R, c - R @ board.centre)


def scan_crossing_length(board: BoardModel, T_lidar_board: np.ndarray) -> float:
    """Length (m) of the board's cut by a 2D LiDAR's scan plane (the LiDAR's z = 0)."""
    w, h = board.extent
    o, a, b = T_lidar_board[:3, 3], T_lidar_board[:3, 0], T_lidar_board[:3, 1]
    # z(u, v) = o_z + u a_z + v b_z = 0 over the rectangle [0, w] x [0, h]: clip that line to it.
    pts = []
    for u in (0.0, w):
        if abs(b[2]) > 1e-12:
            v = -(o[2] + u * a[2]) / b[2]
            if 0.0 <= v <= h:
                pts.append((u, v))
    for v in (0.0, h):
        if abs(a[2]) > 1e-12:
            u = -(o[2] + v * b[2]) / a[2]
            if 0.0 <= u <= w:
                pts.append((u, v))
    if len(pts) < 2:
        return 0.0
    pts = np.array(pts)
    return float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=2)))


def corners_in_image_share(rig: Rig, T_camera_board: np.ndarray) -> float:
    """The share of the board's inner corners inside the image (15 px from its edge)."""
    return float(np.mean(rig.camera.sees(transform_points(T_camera_board, rig.board.inner_corners()), margin_px=15.0)))


def min_in_image(board: BoardModel) -> float:
    """The share of a board's inner corners that must be in the image: all of a checkerboard's; 30% of a
    ChArUco board's (and at least its 6 corners)."""
    return 1.0 if not board.is_charuco else max(0.3, 6 / len(board.inner_corners()))


def _pose_fits(rig: Rig, T_camera_board: np.ndarray, min_in_fov: float = 1.0, min_in_image: float = 1.0) -> bool:
    outline_c = transform_points(T_camera_board, rig.board.outline())
    uv = rig.camera.project(outline_c)
    if min_in_image < 1.0:
        # Possibly partly outside the image (ChArUco): at least min_in_image of the inner corners in it.
        if corners_in_image_share(rig, T_camera_board) < min_in_image:
            return False
    elif not np.all(rig.camera.in_image(uv, margin_px=15.0)):
        return False
    outline_l = transform_points(T_inverse(rig.T_camera_lidar), outline_c)
    if rig.beams.is_2d:
        # The scan plane must cut well across the board (and the board stand on the ground).
        T_lb = T_inverse(rig.T_camera_lidar) @ T_camera_board
        return (scan_crossing_length(rig.board, T_lb) >= rig.min_crossing * min(rig.board.extent)
                and bool((outline_l @ rig.level.T)[:, 2].min() > -rig.lidar_height_m + 0.1))
    el = np.arctan2(outline_l[:, 2], np.linalg.norm(outline_l[:, :2], axis=1))
    margin = np.deg2rad(0.5)
    if min_in_fov < 1.0:
        # Partly outside the LiDAR's vertical field of view, by design: at least min_in_fov of its area seen.
        if board_fraction_in_fov(outline_l, rig.beams.elevations_rad) < min_in_fov:
            return False
    elif el.min() < rig.beams.elevations_rad.min() + margin or el.max() > rig.beams.elevations_rad.max() - margin:
        return False
    return bool(outline_l[:, 2].min() > -rig.lidar_height_m + 0.3)


def sample_board_poses(rig: Rig, n: int, rng: np.random.Generator, max_tries: int = 20000,
                       partial_share: float = 0.0, outside_image_share: float = 0.0) -> list[np.ndarray]:
    """``n`` board poses (``T_camera_board``) 2-5 m away, fully seen by both sensors, with normals spread
    round the viewing axis (stratified azimuths, 15-40 degree tilts), as the planar method advises.
    ``partial_share``: that share of the poses (3D LiDAR) may leave up to 60% of the board outside the LiDAR's
    vertical field of view. ``outside_image_share``: that share of the poses is cut by the image's edge, with
    30-90% of the inner corners in the image (for ChArUco boards)."""
    return _sample_poses(rig, n, rng, lambda k: (2 * np.pi * (k + rng.uniform()) / n,
                                                 np.deg2rad(rng.uniform(15.0, 40.0))), max_tries, partial_share,
                         outside_image_share)


def _sample_poses(rig: Rig, n: int, rng: np.random.Generator, normal, max_tries: int = 20000,
                  partial_share: float = 0.0, outside_image_share: float = 0.0, spin=None) -> list[np.ndarray]:
    """``n`` feasible poses at random image positions and distances; ``normal(k)`` draws the k-th pose's
    (azimuth, tilt) in radians, ``spin(k)`` its turn about its normal (default: uniform within 20 degrees)."""
    poses = []
    cam = rig.camera
    T_level_camera = T_from_Rt(rig.level, np.zeros(3)) @ T_inverse(rig.T_camera_lidar)
    partial = set() if partial_share <= 0 else set(np.nonzero(rng.uniform(size=n) < partial_share)[0].tolist())
    # Drawn from a generator of its own, so that datasets without such poses stay as they were.
    cut_rng = np.random.default_rng(rng.integers(2**63)) if outside_image_share > 0 else None
    cut = set() if cut_rng is None else set(np.nonzero(cut_rng.uniform(size=n) < outside_image_share)[0].tolist())
    for k in range(n):
        min_in_fov = 0.4 if k in partial else 1.0
        min_share = min_in_image(rig.board) if k in cut else 1.0
        lo, hi = (-0.1, 1.1) if k in cut else (0.1, 0.9)
        for _ in range(max_tries):
            azimuth, tilt = normal(k)
            turn = np.deg2rad(rng.uniform(-20.0, 20.0)) if spin is None else spin(k)
            uv = np.array([[rng.uniform(lo, hi) * cam.width, rng.uniform(lo, hi) * cam.height]])
            ray = cam.rays(uv)[0]
            dist = rng.uniform(rig.min_distance_m, rig.max_distance_m)
            centre = ray * dist
            if rig.board_height_m is not None:  # the centre moved to the boards' one height (level frame)
                p = transform_points(T_level_camera, centre[None])[0]
                p[2] = rig.board_height_m
                centre = transform_points(T_inverse(T_level_camera), p[None])[0]
                if centre[2] <= 0.3:
                    continue
            T = board_pose(rig.board, centre, tilt, azimuth, turn)
            if k in cut and not (np.any(~rig.camera.in_image(rig.camera.project(transform_points(
                    T, rig.board.outline())))) and corners_in_image_share(rig, T) <= 0.9):
                continue  # a cut pose must be cut: part of the board and of its corners outside the image
            if _pose_fits(rig, T, min_in_fov, min_share):
                poses.append(T)
                break
        else:
            raise RuntimeError(f"no feasible board pose found for pose {k} in {max_tries} tries")
    return poses


def one_way_poses(rig: Rig, n: int, rng: np.random.Generator, direction: str, tilt_deg: float = 30.0,
                  depth_m: tuple[float, float] | None = None, max_tries: int = 20000) -> list[np.ndarray]:
    """``n`` feasible poses over the image, every normal tilted ``tilt_deg`` the same way (``up`` or ``right``
    in the image): the planar method's badly conditioned sets."""
    target = {"up": np.array([0.0, -1.0, 0.0]), "right": np.array([1.0, 0.0, 0.0])}[direction]
    lo, hi = depth_m or (rig.min_distance_m, rig.max_distance_m)
    poses = []
    for _ in range(max_tries * n):
        z = rng.uniform(lo, hi)
        c = np.array([rng.uniform(-0.35, 0.35) * z, rng.uniform(-0.25, 0.25) * z, z])
        ray = c / np.linalg.norm(c)
        axis = np.cross(ray, target)
        R0 = _board_rotation(ray, 0.0, 0.0, rng.uniform(-0.3, 0.3))
        R = R_from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(tilt_deg)) @ R0
        T = T_from_Rt(R, c - R @ rig.board.centre)
        if _pose_fits(rig, T):
            poses.append(T)
            if len(poses) == n:
                return poses
    raise RuntimeError(f"no feasible {direction}-tilted board pose found in {max_tries * n} tries")


LAYOUT_FAMILIES = ("spread", "quadrants", "upward", "rightward", "frontal", "weak", "diamond", "handheld")


def sample_layout(rig: Rig, family: str, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n`` board poses of a named family: ``spread`` (normals round the viewing axis, 15-40 degrees),
    ``quadrants`` (normals 30 degrees into the four image quadrants in turn), ``upward`` / ``rightward`` (all
    30 degrees one way), ``frontal`` (tilts under 8 degrees: the rotation is barely observable), ``weak`` (tilts
    of 3-12 degrees at random azimuths: the planes leave the translation along the boards weak), ``diamond``
    (the weak tilts, each board turned 35-55 degrees either way about its normal, as the shared recordings hold
    theirs: every ring then leaves it by slanted sides), ``handheld``
    (:func:`_handheld_poses`: boards held up in front of the rig, all facing its forward axis)."""
    if family == "spread":
        return sample_board_poses(rig, n, rng)
    if family == "quadrants":
        return _sample_poses(rig, n, rng, lambda k: (np.pi / 4 + np.pi / 2 * (k % 4), np.deg2rad(30.0)))
    if family in ("upward", "rightward"):
        return one_way_poses(rig, n, rng, {"upward": "up", "rightward": "right"}[family])
    if family == "weak":
        return _sample_poses(rig, n, rng, lambda k: (rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(3.0, 12.0))))
    if family == "diamond":
        return _sample_poses(rig, n, rng, lambda k: (rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(3.0, 12.0))),
                             spin=lambda k: np.deg2rad(rng.choice([-1.0, 1.0]) * rng.uniform(35.0, 55.0)))
    if family == "frontal":
        return _sample_poses(rig, n, rng, lambda k: (rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(0, 8.0))))
    if family == "handheld":
        return _handheld_poses(rig, n, rng)
    raise ValueError(f"Expected a layout family in {LAYOUT_FAMILIES}, got {family!r}")


def handheld_rig(rng: np.random.Generator) -> Rig:
    """The default camera and a VLP-16-like LiDAR (2 cm range noise) with a small hand-held board (0.35 x 0.40
    m, 6 x 7 inner corners) held 1.5-4 m away: with :func:`sample_layout`'s ``handheld`` poses, the weak layouts
    of boards held up facing the rig."""
    return replace(default_rig(rng, "vlp16", 0.02), board=BoardModel((7, 8), 0.045, size=(0.35, 0.40)),
                   min_distance_m=1.5, max_distance_m=4.0)


def _handheld_poses(rig: Rig, n: int, rng: np.random.Generator, max_tries: int = 20000) -> list[np.ndarray]:
    """``n`` poses of a board held up in front of the rig: in the middle of the image, its normal within 1-4
    degrees of the camera's optical axis (not of the line of sight), so that the normals spread 0.02-0.05 (the
    smallest singular value of the best triple over sqrt 3) and the planes leave the layout weak."""
    poses = []
    for _ in range(n):
        for _ in range(max_tries):
            uv = np.array([[rng.uniform(0.3, 0.7) * rig.camera.width, rng.uniform(0.35, 0.65) * rig.camera.height]])
            centre = rig.camera.rays(uv)[0] * rng.uniform(rig.min_distance_m, rig.max_distance_m)
            R = _board_rotation(np.array([0.0, 0.0, 1.0]), np.deg2rad(rng.uniform(1.0, 4.0)),
                                rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(-10.0, 10.0)))
            T = T_from_Rt(R, centre - R @ rig.board.centre)
            if _pose_fits(rig, T):
                poses.append(T)
                break
        else:
            raise ValueError("no feasible hand-held board pose found; check the rig")
    return poses


def scene_patches(rig: Rig, T_lidar_board: np.ndarray, static: list[Patch] | None = None,
                  held: bool = False) -> tuple[list[Patch], int]:
    """Scene pieces in the LiDAR frame and the index of the board among them: the board, its stand (or the
    person holding it, ``held``), and the static scene (``static``; default: the ground and four walls)."""
    if rig.stand not in STANDS:
        raise ValueError(f"Expected stand in {STANDS}, got {rig.stand!r}")
    # Built in the level frame (the ground below, stands upright), then turned into the LiDAR's; ``static`` is
    # given in the LiDAR's frame.
    to_lidar = rig.level.T
    T_level_board = T_from_Rt(rig.level, np.zeros(3)) @ T_lidar_board
    if static is not None:
        room = list(static)
    else:  # a held board in the default scene has no room around it (as before the level frame)
        room = [] if held else rotated_patches(default_room(-rig.lidar_height_m), to_lidar)
    return rotated_patches(_board_and_holder(rig, T_level_board, held), to_lidar) + room, 0


def _board_and_holder(rig: Rig, T_lidar_board: np.ndarray, held: bool) -> list[Patch]:
    """The board and its stand (or holder), for a level scanner: the ground ``lidar_height_m`` below."""
    board = rig.board
    R, o = T_lidar_board[:3, :3], T_lidar_board[:3, 3]
    w, h = board.extent
    patches = [rectangle(o, R[:, 0], R[:, 1], w, h, board_reflectance(board), "board")]
    ground_z = -rig.lidar_height_m
    if held:
        return patches + holder(transform_points(T_lidar_board, board.outline()), ground_z)
    outline = transform_points(T_lidar_board, board.outline())
    if rig.stand == "uprights":
        return patches + _uprights(outline, R[:, 2], ground_z)
    if rig.stand == "tripod":
        return patches + _tripod(outline, R[:, 2], ground_z)
    # A thin stand from the board's lowest point to the ground, a little behind the board.
    low = outline[np.argmin(outline[:, 2])]
    to_sensor = -low[:2] / np.linalg.norm(low[:2])
    side = np.array([-to_sensor[1], to_sensor[0], 0.0])
    behind = np.append(-to_sensor, 0.0) * 0.05
    if low[2] > ground_z:
        patches.append(rectangle(np.array([low[0], low[1], ground_z]) + behind - 0.02 * side, side,
                                 [0.0, 0.0, 1.0], 0.04, low[2] - ground_z, 0.3, "stand"))
    return patches


# The stand's uprights: width (m), gap beside the board's ends (m), distance behind the board's plane (m), and how
# far above the board's top they reach (m); each stands on a foot (length along the line of sight, height; m).
UPRIGHT_WIDTH_M, UPRIGHT_GAP_M, UPRIGHT_BEHIND_M, UPRIGHT_ABOVE_M = 0.04, 0.02, 0.06, 0.10
FOOT_LENGTH_M, FOOT_HEIGHT_M = 0.6, 0.05
# A tripod: the head (square side, distance behind the board's plane), the column's width, and the legs' width,
# the hub's height over the ground and how far the feet spread from under it (m).
TRIPOD_HEAD_M, TRIPOD_BEHIND_M, TRIPOD_COLUMN_M = 0.15, 0.04, 0.04
TRIPOD_LEG_M, TRIPOD_HUB_M, TRIPOD_SPREAD_M = 0.03, 0.7, 0.45


def _away_across(outline: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board's normal pointing away from the sensor, and the horizontal direction along the board."""
    away = normal if normal @ outline.mean(0) > 0 else -normal  # from the sensor through the board
    across = np.cross(away, [0.0, 0.0, 1.0])
    return away, across / np.linalg.norm(across)


def _uprights(outline: np.ndarray, normal: np.ndarray, ground_z: float) -> list[Patch]:
    """Two vertical uprights of a stand beside the board's left and right ends, behind its plane, each on a foot
    along the line of sight (LiDAR frame: ``outline`` the board's corners, ``normal`` its normal)."""
    away, across = _away_across(outline, normal)
    ahead = np.array([-away[0], -away[1], 0.0]) / np.linalg.norm(away[:2])  # horizontal, towards the sensor
    along = outline @ across
    top = float(outline[:, 2].max()) + UPRIGHT_ABOVE_M
    posts = []
    for end, side in ((along.min(), -1.0), (along.max(), 1.0)):
        centre = outline[np.argmin(np.abs(along - end))]
        foot = centre + across * (end - centre @ across + side * (UPRIGHT_GAP_M + UPRIGHT_WIDTH_M / 2)) \
            + away * UPRIGHT_BEHIND_M
        foot = np.array([foot[0], foot[1], ground_z]) - across * UPRIGHT_WIDTH_M / 2
        posts.append(rectangle(foot, across, [0.0, 0.0, 1.0], UPRIGHT_WIDTH_M, top - ground_z, 0.35, "stand"))
        # The foot: a bar on the ground under the upright, half in front of it, its side facing across.
        bar = foot + across * UPRIGHT_WIDTH_M / 2 - ahead * FOOT_LENGTH_M / 2
        posts.append(rectangle(bar, ahead, [0.0, 0.0, 1.0], FOOT_LENGTH_M, FOOT_HEIGHT_M, 0.35, "stand"))
    return posts


def _tripod(outline: np.ndarray, normal: np.ndarray, ground_z: float) -> list[Patch]:
    """A tripod: a square head behind the board's centre, a column from it down to the hub, and three legs from
    the hub splayed to the ground (LiDAR frame)."""
    away, across = _away_across(outline, normal)
    up = np.cross(across, away)
    centre = outline.mean(0) + away * TRIPOD_BEHIND_M
    parts = [rectangle(centre - (across + up) * TRIPOD_HEAD_M / 2, across, up, TRIPOD_HEAD_M, TRIPOD_HEAD_M,
                       0.2, "stand")]
    hub = np.array([centre[0], centre[1], ground_z + TRIPOD_HUB_M])
    head_low = centre[2] - TRIPOD_HEAD_M / 2
    if head_low > hub[2]:
        parts.append(rectangle(hub - across * TRIPOD_COLUMN_M / 2, across, [0.0, 0.0, 1.0], TRIPOD_COLUMN_M,
                               head_low - hub[2], 0.2, "stand"))
    for k in range(3):
        a = np.deg2rad(90.0 + 120.0 * k)  # one leg straight back, two towards the sensor's side
        out = np.cos(a) * across + np.sin(a) * np.array([away[0], away[1], 0.0]) / np.linalg.norm(away[:2])
        foot = np.array([hub[0], hub[1], ground_z]) + TRIPOD_SPREAD_M * out
        leg = hub - foot
        side = np.cross(leg, [0.0, 0.0, 1.0])
        parts.append(rectangle(foot - side / np.linalg.norm(side) * TRIPOD_LEG_M / 2, side, leg, TRIPOD_LEG_M,
                               np.linalg.norm(leg), 0.2, "stand"))
    return parts


def default_room(ground_z: float) -> list[Patch]:
    """The default scene's static part: the ground and four walls."""
    return [infinite_plane([0, 0, 1], ground_z, 0.3, "ground"),
            infinite_plane([1, 0, 0], 12.0, 0.55, "wall"),
            infinite_plane([1, 0, 0], -8.0, 0.55, "wall"),
            infinite_plane([0, 1, 0], 8.0, 0.6, "wall"),
            infinite_plane([0, 1, 0], -8.0, 0.6, "wall")]


def cast_sweep(rig: Rig, patches: list[Patch], background: tuple[Background, np.ndarray] | None = None
               ) -> tuple[np.ndarray, ...]:
    """The noise-free sweep: every beam's direction and ring, and its range, patch and reflectance
    (``scene.cast``); no random numbers. ``background``: the static scene's cast of the beams, and the rings."""
    if background is None:
        dirs, ring = rig.beams.directions()
        return (dirs, ring, *cast(np.zeros(3), dirs, patches, rig.beams.max_range_m))
    bg, ring = background
    return (bg.dirs, ring, *cast(np.zeros(3), bg.dirs, patches, rig.beams.max_range_m, bg))


def simulate_scan(rig: Rig, patches: list[Patch], rng: np.random.Generator, board_index: int | None = None,
                  bias: RangeBias | None = None, sweep: tuple[np.ndarray, ...] | None = None
                  ) -> tuple[np.ndarray, ...]:
    """A full sweep: points (N, 3) in the LiDAR frame with Gaussian range noise (and ``bias``: systematic
    range errors, the black-square term on the board's black squares), intensity, ring (and, given
    ``board_index``, the mask of the points that hit the board). ``sweep``: :func:`cast_sweep` of these
    patches when it was cast already."""
    dirs, ring, rng_m, which, refl = cast_sweep(rig, patches) if sweep is None else sweep
    hit = np.isfinite(rng_m)
    r = rng_m[hit] + rng.normal(0.0, rig.beams.sigma_range_m, hit.sum())
    if bias is not None and not bias.is_zero:
        dark = (which[hit] == board_index) & (refl[hit] < 0.5) if board_index is not None else np.zeros(hit.sum(), bool)
        r = r + bias.of(ring[hit], dark)
    out = dirs[hit] * r[:, None], (refl[hit] * 100).astype(np.float32), ring[hit]
    return out if board_index is None else (*out, which[hit] == board_index)


@dataclass(frozen=True, eq=False)
class SimulatedFrame:
    name: str
    image: np.ndarray
    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    T_camera_board: np.ndarray
    board_mask: np.ndarray | None = None  # which points hit the board (ground truth)
    held: bool = False  # the board held by a person (else on its stand)


def simulate_frames(rig: Rig, n_poses: int, rng: np.random.Generator,
                    poses: list[np.ndarray] | None = None, scene: str = "default",
                    bias: RangeBias | None = None, outside_image_share: float = 0.0, workers: int = 2
                    ) -> list[SimulatedFrame]:
    """Rendered images and ray-cast sweeps of ``n_poses`` sampled board poses (or of the given ``poses``).

    ``scene``: ``default`` (the ground, four walls, the board on a stand), ``office`` or ``hall``
    (``simulation.office``: a static scene drawn once, the board held by a person in 70% of the frames, and
    in 3D a quarter of the boards partly above or below the LiDAR's vertical field of view).
    ``outside_image_share``: that share of the sampled poses is cut by the image's edge (ChArUco).
    ``workers``: threads that cast the frames of the default scene (the result does not depend on it)."""
    return list(iter_frames(rig, n_poses, rng, poses, scene, bias, outside_image_share, workers))


def static_scene(rig: Rig, scene: str, rng: np.random.Generator, poses: list[np.ndarray] | None = None
                 ) -> list[Patch]:
    """The static part of ``scene`` in the LiDAR's frame: the default room, an office or a hall
    (``simulation.office``), or a furnished room whose furniture keeps off the lines of sight to the boards of
    ``poses`` (``simulation.rooms``; camera frame)."""
    if scene == "office":
        return rotated_patches(office_layout(-rig.lidar_height_m, rng), rig.level.T)
    if scene == "hall":
        return rotated_patches(hall_layout(-rig.lidar_height_m), rig.level.T)
    if scene == "furnished":
        from .rooms import room_around_rig

        T_level_camera = T_from_Rt(rig.level, np.zeros(3)) @ T_inverse(rig.T_camera_lidar)
        centres = np.array([transform_points(T_level_camera @ T, rig.board.outline()).mean(0) for T in poses])
        return rotated_patches(room_around_rig(-rig.lidar_height_m, rng, centres), rig.level.T)
    return rotated_patches(default_room(-rig.lidar_height_m), rig.level.T)


def iter_frames(rig: Rig, n_poses: int, rng: np.random.Generator, poses: list[np.ndarray] | None = None,
                scene: str = "default", bias: RangeBias | None = None, outside_image_share: float = 0.0,
                workers: int = 2, static: list[Patch] | None = None) -> Iterator[SimulatedFrame]:
    """:func:`simulate_frames` one frame at a time, each as soon as it is made (later frames are cast
    meanwhile), so that a caller can write it while the next ones are cast. ``static``: the scene's static part
    (LiDAR frame) when drawn already (:func:`static_scene`; a rig's further sensors cast the same)."""
    if scene not in SCENES:
        raise ValueError(f"Expected scene in {SCENES}, got {scene!r}")
    T_lidar_camera = T_inverse(rig.T_camera_lidar)
    if static is None and scene in ("office", "hall"):
        static = static_scene(rig, scene, rng)
    if poses is None:
        partial = 0.25 if scene != "default" and not rig.beams.is_2d else 0.0
        poses = sample_board_poses(rig, n_poses, rng, partial_share=partial, outside_image_share=outside_image_share)
    if static is None and scene == "furnished":
        static = static_scene(rig, scene, rng, poses)

    # The default scene draws nothing before a frame is cast: frames are cast in ``workers`` threads (numpy
    # releases the interpreter in its large array operations), ``workers`` of them ahead of the one whose noise
    # is being added, in the original order, so that a seed gives the same dataset for any number of workers
    # (and no more than ``workers + 1`` noise-free images are held at once). The threads also share the
    # camera's pixel rays, for any scene.
    parallel = scene == "default" and workers > 1
    with ThreadPoolExecutor(max_workers=workers) if workers > 1 else contextlib.nullcontext() as pool:
        # The static scene is cast once, for the camera's pixels and the LiDAR's beams; each frame casts only
        # the board and its stand or holder over it (the same images and sweeps as casting the whole scene).
        static = rotated_patches(default_room(-rig.lidar_height_m), rig.level.T) if static is None else static
        image_background = cast_background(T_lidar_camera[:3, 3], pixel_rays(rig.camera, T_lidar_camera, pool),
                                           static)
        dirs, ring = rig.beams.directions()
        sweep_background = cast_background(np.zeros(3), dirs, static, rig.beams.max_range_m)

        def cast_frame(T_cb: np.ndarray, held: bool):
            """Everything of one frame that draws no random numbers: its scene, image and sweep, noise-free."""
            T_lb = T_lidar_camera @ T_cb
            patches, bi = scene_patches(rig, T_lb, static, held)
            clean = render_clean(rig.camera, T_lidar_camera, patches, bi,
                                 transform_points(T_lb, rig.board.outline()), background=image_background)
            return bi, clean, cast_sweep(rig, patches, (sweep_background, ring))

        ahead: deque = deque()
        for k, T_cb in enumerate(poses):
            if parallel:
                while len(ahead) <= workers and k + len(ahead) < len(poses):
                    ahead.append(pool.submit(cast_frame, poses[k + len(ahead)], False))
                held = False
                bi, clean, sweep = ahead.popleft().result()
            else:
                held = scene != "default" and bool(rng.uniform() < 0.7)
                bi, clean, sweep = cast_frame(T_cb, held)
            img = add_pixel_noise(clean, rng, rig.pixel_noise)
            pts, inten, ring_k, on_board = simulate_scan(rig, [], rng, bi, bias, sweep)
            yield SimulatedFrame(f"{k:04d}", img, pts, inten, ring_k, T_cb, on_board, held)


def cropped_to_boards(frames: list[SimulatedFrame], pad_m: float) -> list[SimulatedFrame]:
    """The frames' clouds cropped, as some recorders do, to one box (in the LiDAR frame) around every frame's
    board returns widened by ``pad_m``: the board then fills a large share of each cloud."""
    boards = np.vstack([f.points[f.board_mask] for f in frames])
    lo, hi = boards.min(axis=0) - pad_m, boards.max(axis=0) + pad_m
    out = []
    for f in frames:
        keep = np.all((f.points >= lo) & (f.points <= hi), axis=1)
        out.append(replace(f, points=f.points[keep], intensity=f.intensity[keep],
                           ring=None if f.ring is None else f.ring[keep], board_mask=f.board_mask[keep]))
    return out


INTENSITY_MODES = ("contrast", "flat", "saturated")


def _as_recorded(frames: Iterable[SimulatedFrame], intensity: str, ring_field: bool, rng: np.random.Generator
                 ) -> Iterator[SimulatedFrame]:
    """The frames as a LiDAR whose intensity has no black/white contrast (``flat``: 50 +- 5) or is saturated
    (255), and whose clouds have no ring field, would record them."""
    for f in frames:
        value = f.intensity
        if intensity == "flat":
            value = rng.normal(50.0, 5.0, len(value)).astype(np.float32)
        elif intensity == "saturated":
            value = np.full(len(value), 255.0, dtype=np.float32)
        yield replace(f, intensity=value, ring=f.ring if ring_field else None)


def dataset_yaml(rig: Rig, lidar: str | None = None) -> dict:
    return dataset_spec(lidar or ("2d" if rig.beams.is_2d else "3d"), rig.board, rig.camera)


def write_sweep_2d(path: str | Path, beams, points: np.ndarray) -> None:
    """A 2D scanner's returns (points in its frame) as the scan file it writes: every beam of the sweep, those
    with no return at range 0 (as scanners report them)."""
    az = beams.azimuths()
    ranges = np.zeros(len(az))
    k = np.rint((np.arctan2(points[:, 1], points[:, 0]) - az[0]) / beams.azimuth_step_rad)
    ranges[k.astype(int)] = np.linalg.norm(points[:, :2], axis=1)
    write_scan_2d(path, az, ranges)


def write_dataset(out: str | Path, rig: Rig, frames: Iterable[SimulatedFrame], scan_format: str = "pcd",
                  include_camera: bool = True, overwrite: bool = False, meta: dict | None = None) -> Path:
    """Write the dataset folder atomically (all of it, or nothing). ``frames`` may be an iterator
    (:func:`iter_frames`): each frame's files are written as it comes."""
    spec = dataset_yaml(rig)
    if not include_camera:
        spec.pop("camera")
    with atomic_directory(out, overwrite=overwrite) as tmp:
        write_dataset_yaml(tmp, spec, "simulated by lidarcam; ground_truth.json is for evaluation only")
        poses, masks = {}, {}
        for f in frames:
            poses[f.name] = f.T_camera_board.tolist()
            if f.board_mask is not None:
                masks[f.name] = f.board_mask
            cv2.imwrite(str(tmp / f"{f.name}.png"), f.image)
            if rig.beams.is_2d:
                write_sweep_2d(tmp / f"{f.name}.{scan_format}", rig.beams, f.points)
            else:
                write_scan(tmp / f"{f.name}.{scan_format}", f.points, f.intensity, f.ring)
        truth = {"T_camera_lidar": rig.T_camera_lidar.tolist(), "T_camera_board": poses,
                 "lidar_model": rig.beams.name, "sigma_range_m": rig.beams.sigma_range_m,
                 "pixel_noise": rig.pixel_noise, **(meta or {})}
        (tmp / "ground_truth.json").write_text(json.dumps(truth, indent=1))
        if masks:  # which returns hit the board, in the order of each scan file's valid returns
            np.savez_compressed(tmp / "ground_truth_board_points.npz", **masks)
    return Path(out)


def simulate_dataset(out: str | Path, n_poses: int = 8, seed: int = 0, lidar: str = "hdl64e",
                     sigma_range_m: float | None = None, pixel_noise: float = 2.0, scan_format: str | None = None,
                     include_camera: bool = True, overwrite: bool = False, scene: str = "default",
                     range_bias: tuple[float, float, float] | None = None, rig_config: str = "default",
                     pattern: str = "checkerboard", outside_image_share: float | None = None,
                     range_bias_family: str | None = None, intensity: str = "contrast", ring_field: bool = True
                     ) -> Path:
    """Simulate a rig and write a dataset folder, with ``ground_truth.json``.

    Images are rendered and scans cast from the LiDAR's beam model, so the dataset goes through the same
    measurement as a recording. ``ground_truth_board_points.npz`` holds which returns hit the board.

    Parameters
    ----------
    out : str or Path
        The dataset folder to write (atomically).
    n_poses : int
        Board poses (frames).
    seed : int
        Seed of the rig's and the poses' draws and of the noise.
    lidar : str
        ``hdl64e``, ``vlp16`` or ``os64`` (3D beam models) or ``2d`` (a 270-degree single-line scanner).
    sigma_range_m : float, optional
        Range noise, m (default 0.02 in 3D, 0.01 in 2D).
    pixel_noise : float
        Image noise, grey levels (1 sd).
    scan_format : str, optional
        ``pcd``, ``ply``, ``bin`` or ``npy`` in 3D (default ``pcd``); ``csv``, ``npy`` or ``pcd`` in 2D (default
        ``csv``).
    include_camera : bool
        Write the intrinsics into ``dataset.yaml`` (False: they are calibrated from the images).
    overwrite : bool
        Replace an existing folder.
    scene : str
        ``default``, ``office`` or ``hall``.
    range_bias : tuple of float, optional
        (global offset, sd of the per-ring offsets, black-square offset), m, injected into every return.
    rig_config : str
        2D only: ``default``, ``varied`` (a rig from a second, independent configuration) or ``mounted`` (the
        scanner upside down, tilted or 0.5 m from the camera).
    pattern : str
        ``checkerboard`` or ``charuco`` (the same board with DICT_5X5_100 markers).
    outside_image_share : float, optional
        The share of poses cut by the image's edge (default 0.3 for ChArUco, 0 for a checkerboard).
    range_bias_family : str, optional
        Inject range errors drawn from that sensor family's priors instead of ``range_bias``.
    intensity : str
        ``contrast`` (the board's reflectance), ``flat`` (no black/white contrast) or ``saturated``.
    ring_field : bool
        Write each return's ring (False: clouds without a ``ring`` field).

    Returns
    -------
    Path
        The dataset folder.

    Examples
    --------
    >>> path = lc.simulate("/tmp/sim2d", n_poses=6, lidar="2d", seed=3)   # doctest: +SKIP
    """
    if intensity not in INTENSITY_MODES:
        raise ValueError(f"Expected intensity in {INTENSITY_MODES}, got {intensity!r}")
    check_output_folder(out, overwrite)  # before minutes of rendering
    if sigma_range_m is None:
        sigma_range_m = 0.01 if lidar == "2d" else 0.02
    if scan_format is None:
        scan_format = "csv" if lidar == "2d" else "pcd"
    rng = np.random.default_rng(seed)
    if rig_config not in RIGS_2D or (rig_config != "default" and lidar != "2d"):
        raise ValueError(f"Expected rig_config in {RIGS_2D} (varied and mounted only for 2d), got {rig_config!r}")
    base = rig_2d(rig_config, rng, sigma_range_m) if lidar == "2d" else default_rig(rng, lidar, sigma_range_m)
    if pattern not in PATTERNS:
        raise ValueError(f"Expected pattern in {PATTERNS}, got {pattern!r}")
    rig = replace(base, pixel_noise=pixel_noise, board=as_charuco(base.board) if pattern == CHARUCO else base.board)
    if outside_image_share is None:
        outside_image_share = 0.3 if pattern == CHARUCO else 0.0
    if outside_image_share > 0 and pattern != CHARUCO:
        raise ValueError("Expected outside_image_share 0 for a checkerboard (it must be seen whole)")
    bias = None
    meta = {"seed": seed, "poses": n_poses, "scene": scene, "rig": rig_config, "pattern": pattern,
            "outside_image_share": outside_image_share}
    if range_bias_family is not None:
        acc = range_accuracy_for(range_bias_family)
        draw = np.random.default_rng([seed, 16])
        range_bias = (float(draw.normal(0.0, acc)), RING_PRIOR_SHARE * acc, float(draw.normal(0.0, acc)))
        meta["range_bias_family"] = range_bias_family
    if range_bias is not None:
        # Drawn from a generator of its own, so that the rest of the simulation stays as without a bias.
        bias = RangeBias.drawn(np.random.default_rng([seed, 16]), len(rig.beams.elevations_rad), *range_bias)
        meta["range_bias"] = bias.record()
    # Each frame is written while the next ones are cast.
    frames = iter_frames(rig, n_poses, rng, scene=scene, bias=bias, outside_image_share=outside_image_share)
    if intensity != "contrast" or not ring_field:
        frames = _as_recorded(frames, intensity, ring_field, np.random.default_rng([seed, 17]))
        meta.update({"intensity": intensity, "ring_field": ring_field})
    return write_dataset(out, rig, frames, scan_format, include_camera, overwrite, meta=meta)
