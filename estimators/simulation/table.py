"""A second 3D generator, unlike the default rig: a small board standing on a plate on an optical table, seen by a
dense LiDAR with a non-repetitive scan pattern (``lidar_models.Rosette``: a Livox-like sensor, no beam index),
in the whole lab around it (the cloud is not cropped).

The rig looks down the table from its end (both sensors pitched down, the LiDAR 0.3 m above the table top); the
board (a 6 x 8 pattern of 30 mm squares, 18 x 24 cm, its size not declared) stands on a small base plate at 0.7-1.3
m, turned about the vertical, leaning back or forward and rolled, at a few places of the table (a user moves the
plate a little between poses). Each sweep draws its own pattern, so the background is returned at different
places every frame. Built in the level frame (z up, the LiDAR at the origin) and turned into the LiDAR's.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, transform_points

from ..lidar.lidar_models import BeamModel, Rosette
from .office import _box
from .rendering import add_pixel_noise, pixel_rays, render_clean
from .scene import Patch, cast, cast_background, infinite_plane, rectangle
from .simulator import R_CAMERA_LIDAR_NOMINAL, SimulatedFrame, board_reflectance, default_camera, rotated_patches

TABLE_TOP_M = -0.30          # the table's top below the LiDAR (level frame)
FLOOR_M = -1.20              # the floor below the LiDAR
PLATE_M = 0.012              # the base plate's thickness: the board's lowest corner this far above the table
PITCH_DEG = 14.0             # both sensors look this far down


@dataclass(frozen=True, eq=False)
class TableRig:
    """The table rig: the camera, the LiDAR's pattern, the board (its physical size; the dataset declares only
    the pattern), ``T_camera_lidar`` and the LiDAR's mounting ``R_level_lidar``."""

    camera: CameraModel
    beams: Rosette | BeamModel
    board: BoardModel
    T_camera_lidar: np.ndarray
    R_level_lidar: np.ndarray
    pixel_noise: float = 2.0


def table_board() -> BoardModel:
    """The 6 x 8 pattern of 30 mm squares on an 18 x 24 cm board with a 5 mm white border."""
    return BoardModel(squares=(6, 8), square_size=0.03, size=(0.19, 0.25))


TABLE_LIDARS = ("rosette", "sector")


def sector_laser(sigma_range_m: float = 0.01) -> BeamModel:
    """A dense spinning laser that sweeps a sector: a vertical line of 201 beams (+-25 degrees, 0.25 degree
    apart) turned through +-25 degrees in 0.3 degree steps, about 34 thousand returns a sweep, each with its beam
    index."""
    return BeamModel("dense sector laser", np.deg2rad(np.arange(25.0, -25.01, -0.25)), np.deg2rad(0.3),
                     sigma_range_m, 30.0, (-np.deg2rad(25.0), np.deg2rad(25.0)))


def table_rig(rng: np.random.Generator, sigma_range_m: float = 0.01, lidar: str = "rosette") -> TableRig:
    """The rig with a small random deviation of its mounting: the camera 8 cm left of and 5 cm below the LiDAR.
    ``lidar``: ``rosette`` (:class:`Rosette`, no beam index) or ``sector`` (:func:`sector_laser`)."""
    if lidar not in TABLE_LIDARS:
        raise ValueError(f"Expected lidar in {TABLE_LIDARS}, got {lidar!r}")
    R_level_lidar = R_from_rotvec([0.0, np.deg2rad(PITCH_DEG), 0.0])
    R_level_camera = R_from_rotvec(rng.normal(0.0, np.deg2rad(1.5), 3)) @ R_level_lidar @ R_CAMERA_LIDAR_NOMINAL.T
    camera_in_level = np.array([0.02, 0.08, -0.05]) + rng.normal(0.0, 0.01, 3)
    R = R_level_camera.T @ R_level_lidar
    t = -R_level_camera.T @ camera_in_level
    beams = Rosette(sigma_range_m=sigma_range_m) if lidar == "rosette" else sector_laser(sigma_range_m)
    return TableRig(default_camera(), beams, table_board(), T_from_Rt(R, t), R_level_lidar)


def in_view(beams: Rosette | BeamModel, points: np.ndarray, margin_rad: float = 0.0) -> np.ndarray:
    """Which points (LiDAR frame) the LiDAR's field of view holds, ``margin_rad`` inside its edges."""
    if isinstance(beams, Rosette):
        return beams.in_view(points, margin_rad)
    el = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    az = np.arctan2(points[:, 1], points[:, 0])
    lo, hi = beams.azimuth_limits_rad or (-np.pi, np.pi)
    return ((el >= beams.elevations_rad.min() + margin_rad) & (el <= beams.elevations_rad.max() - margin_rad)
            & (az >= lo + margin_rad) & (az <= hi - margin_rad))


def sweep_directions(beams: Rosette | BeamModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
    """One sweep's unit beam directions and beam indices (None for the rosette): a spinning laser's firings
    fall at a new phase within its step each sweep."""
    if isinstance(beams, Rosette):
        return beams.directions(rng), None
    return replace(beams, azimuth_phase_rad=float(rng.uniform(0.0, beams.azimuth_step_rad))).directions()


def table_layout(rng: np.random.Generator) -> list[Patch]:
    """The lab (level frame): floor, walls and ceiling, the optical table (top and sides) from just behind the rig
    to 2.2 m ahead, equipment on the table's far end and sides, a cabinet and a door on the far wall."""
    g, top = FLOOR_M, TABLE_TOP_M
    far = rng.uniform(3.0, 4.0)
    patches = [infinite_plane([0, 0, 1], g, 0.3, "ground"), infinite_plane([0, 0, 1], g + 2.8, 0.5, "ceiling"),
               infinite_plane([1, 0, 0], far, 0.55, "wall"), infinite_plane([1, 0, 0], -2.5, 0.55, "wall"),
               infinite_plane([0, 1, 0], 2.5, 0.6, "wall"), infinite_plane([0, 1, 0], -2.5, 0.6, "wall")]
    x0, x1, half = -0.3, 2.2, 0.75
    zv = np.array([0.0, 0.0, 1.0])
    patches += [rectangle([x0, -half, top], [1, 0, 0], [0, 1, 0], x1 - x0, 2 * half, 0.25, "table"),
                rectangle([x1, -half, g], [0, 1, 0], zv, 2 * half, top - g, 0.2, "table"),
                rectangle([x0, half, g], [1, 0, 0], zv, x1 - x0, top - g, 0.2, "table"),
                rectangle([x0, -half, g], [1, 0, 0], zv, x1 - x0, top - g, 0.2, "table")]
    # Equipment: boxes and posts on the table's far end and along its sides, clear of the board's workspace.
    for _ in range(int(rng.integers(2, 5))):
        x = rng.uniform(1.6, 2.0)
        y = rng.uniform(-0.6, 0.6)
        patches += _box([x, y, top], (rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.3), rng.uniform(0.05, 0.35)),
                        rng.uniform(0, np.pi), rng.uniform(0.2, 0.7), "equipment")
    for side in (-1.0, 1.0):
        patches += _box([rng.uniform(0.3, 1.4), side * rng.uniform(0.55, 0.65), top],
                        (0.12, 0.12, rng.uniform(0.1, 0.3)), 0.0, 0.5, "equipment")
    patches += _box([far - 0.3, rng.uniform(-1.5, 1.5), g], (1.0, 0.5, 1.8), 0.0, 0.45, "cabinet")
    patches.append(rectangle([far - 0.05, rng.uniform(-2.0, 1.0), g], [0, 1, 0], zv, 0.9, 2.05, 0.4, "door"))
    return patches


def plate(outline: np.ndarray, normal: np.ndarray) -> list[Patch]:
    """The small plate the board stands on (level frame): a base 12 x 10 cm on the table under the board's lowest
    point, and a bracket 5 cm wide behind the board's plane from the base up to a third of the board's height."""
    low = outline[np.argmin(outline[:, 2])]
    away = normal if normal @ outline.mean(0) > 0 else -normal
    along = np.cross(away, [0.0, 0.0, 1.0])
    along /= np.linalg.norm(along)
    flat_away = np.array([away[0], away[1], 0.0]) / np.linalg.norm(away[:2])
    base_z = TABLE_TOP_M + PLATE_M
    centre = np.array([low[0], low[1], base_z]) + 0.02 * flat_away
    base = rectangle(centre - 0.06 * along - 0.05 * flat_away, along, flat_away, 0.12, 0.10, 0.35, "plate")
    height = (outline[:, 2].max() - base_z) / 3
    foot = np.array([low[0], low[1], base_z]) + 0.015 * flat_away - 0.025 * along
    bracket = rectangle(foot, along, [0.0, 0.0, 1.0], 0.05, height, 0.35, "plate")
    return [base, bracket]


def table_poses(rig: TableRig, n: int, rng: np.random.Generator, places: int = 3, spread_deg: float = 20.0,
                max_tries: int = 20000) -> list[np.ndarray]:
    """``n`` poses (``T_camera_board``) of the board standing on its plate: the plate at one of ``places`` spots
    of the table moved by up to 5 cm, the board turned by up to 45
    degrees about the vertical, leaning back up to 30 or forward up to 15 degrees and rolled by up to 20; seen
    whole by the camera and inside the LiDAR's field of view (2 degrees inside its edge). The spots lie 0.7-1.3 m
    ahead in bearings spread over ``spread_deg`` (one in each share), as a user moves the plate across the view
    (or hardly: a few degrees, every board in line with the others)."""
    ahead = rng.uniform(0.7, 1.3, places)
    bearing = np.deg2rad(spread_deg * ((np.arange(places) + rng.uniform(0.2, 0.8, places)) / places - 0.5))
    spots = np.column_stack([ahead, ahead * np.tan(bearing)])
    T_level_camera = T_from_Rt(rig.R_level_lidar, np.zeros(3)) @ T_inverse(rig.T_camera_lidar)
    T_camera_level = T_inverse(T_level_camera)
    w, h = rig.board.extent
    corners = rig.board.outline()
    poses = []
    for k in range(n):
        for _ in range(max_tries):
            x, y = spots[k % places] + rng.uniform(-0.05, 0.05, 2)
            yaw = np.deg2rad(rng.uniform(-45.0, 45.0))
            lean = np.deg2rad(rng.uniform(-15.0, 30.0))
            roll = np.deg2rad(rng.uniform(-20.0, 20.0))
            # Board axes (level frame) facing the rig: x to the right, y down, z away from the rig.
            R0 = np.column_stack([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
            R = R_from_rotvec([0.0, 0.0, yaw]) @ R0 @ R_from_rotvec([lean, 0.0, 0.0]) @ R_from_rotvec([0.0, 0.0, roll])
            c = np.array([w / 2, h / 2, 0.0])
            o = transform_points(T_from_Rt(R, np.zeros(3)), corners - c)
            centre = np.array([x, y, TABLE_TOP_M + PLATE_M - o[:, 2].min()])
            T_level_board = T_from_Rt(R, centre - R @ c)
            T_cb = T_camera_level @ T_level_board
            uv = rig.camera.project(transform_points(T_cb, corners))
            if not np.all(rig.camera.in_image(uv, margin_px=15.0)):
                continue
            in_lidar = transform_points(T_inverse(rig.T_camera_lidar) @ T_cb, corners)
            if not np.all(in_view(rig.beams, in_lidar, margin_rad=np.deg2rad(2.0))):
                continue
            poses.append(T_cb)
            break
        else:
            raise RuntimeError(f"no feasible pose on the table for pose {k} in {max_tries} tries")
    return poses


def simulate_table_frames(rig: TableRig, n_poses: int, rng: np.random.Generator, places: int = 3,
                          spread_deg: float = 20.0) -> tuple[list[SimulatedFrame], list[Patch]]:
    """The frames (images and sweeps with ground truth) of ``n_poses`` table poses (:func:`table_poses`), and the
    static lab in the LiDAR's frame."""
    to_lidar = rig.R_level_lidar.T
    static = rotated_patches(table_layout(rng), to_lidar)
    poses = table_poses(rig, n_poses, rng, places, spread_deg)
    T_lidar_camera = T_inverse(rig.T_camera_lidar)
    image_background = cast_background(T_lidar_camera[:3, 3], pixel_rays(rig.camera, T_lidar_camera), static)
    frames = []
    for k, T_cb in enumerate(poses):
        T_lb = T_lidar_camera @ T_cb
        T_level_board = T_from_Rt(rig.R_level_lidar, np.zeros(3)) @ T_lb
        w, h = rig.board.extent
        outline_level = transform_points(T_level_board, rig.board.outline())
        board = rectangle(T_level_board[:3, 3], T_level_board[:3, 0], T_level_board[:3, 1], w, h,
                          board_reflectance(rig.board), "board")
        own = rotated_patches([board] + plate(outline_level, T_level_board[:3, 2]), to_lidar)
        patches = own + static
        clean = render_clean(rig.camera, T_lidar_camera, patches, 0, transform_points(T_lb, rig.board.outline()),
                             background=image_background)
        image = add_pixel_noise(clean, rng, rig.pixel_noise)
        dirs, ring = sweep_directions(rig.beams, rng)
        r, which, refl = cast(np.zeros(3), dirs, patches, rig.beams.max_range_m)
        hit = np.isfinite(r)
        ranges = r[hit] + rng.normal(0.0, rig.beams.sigma_range_m, hit.sum())
        frames.append(SimulatedFrame(f"{k:04d}", image, dirs[hit] * ranges[:, None],
                                     (refl[hit] * 100).astype(np.float32), None if ring is None else ring[hit], T_cb,
                                     which[hit] == 0))
    return frames, static


def declared(rig: TableRig) -> TableRig:
    """The rig as its dataset declares it: the pattern alone, no board size."""
    return replace(rig, board=replace(rig.board, size=None))
