"""Furnished rooms seen from a rig carried through them, without a board: the scene's check's own simulator.

The board scenes (``simulator``, ``office``) keep the space in front of the camera clear for the boards, so their
views hold few occluding contours. Here a room drawn at random (``rooms.furnished_room``: desks with monitors
whose black screens return nothing to the LiDAR, shelves, cabinets, chairs, sofas, boxes, pillars, plant stands;
textured posters, doors in proud frames, windows whose glass the LiDAR's beams pass, leaving a gap in the ring;
materials from dark to bright, each face shaded by its turn to a light) is seen from many spots.

The rig (``simulator.default_rig``: the camera 15 cm ahead of and 20 cm below the LiDAR) is placed per frame at a
free spot of the room, 1.0-1.8 m high, turned to any heading and tipped by up to 3 degrees, so that the frames of
one dataset see different parts of the room. The image is rendered with a ray through each pixel's centre and
``supersample^2`` rays wherever an edge can pass (a neighbour's centre sees another face or a reflectance step:
the edges anti-aliased, 2-5% of the pixels, half the time of supersampling them all, the images within a few grey
levels of it at a few pixels), the sweep cast from the LiDAR's beams; each return's intensity is its material's
reflectance times the cosine of its incidence, and a return weaker than ``MIN_ECHO`` is lost.

This is a second, independent generator for the scene's check: its claims are not to rest on the board scenes
alone.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse

from ..io.output import atomic_directory, check_output_folder
from ..io.dataset import write_dataset_yaml
from ..io.pointcloud_io import write_scan
from .rendering import SKY_REFLECTANCE, _interp_subpixels, _normalized_grid, _rays_world, add_pixel_noise, edge_pixels
from .rooms import GLASS, Room, _in_lidar, furnished_room
from .scene import Patch, cast
from .simulator import default_rig

MIN_ECHO = 0.03  # reflectance x cos(incidence) below which a return is lost
# A reflectance step between neighbouring pixel centres above which both pixels are supersampled.
REFLECTANCE_STEP = 0.02


def rig_poses(room: Room, n: int, rng: np.random.Generator, max_tries: int = 10000) -> list[np.ndarray]:
    """``n`` LiDAR poses in the room (``T_world_lidar``): 1.0-1.8 m high, 1.2 m from the walls, clear of the
    furniture by 0.8 m, any heading, tipped by up to 3 degrees."""
    poses = []
    for _ in range(max_tries):
        if len(poses) == n:
            break
        xy = np.array([rng.uniform(1.2, room.length - 1.2), rng.uniform(1.2, room.width - 1.2)])
        if any(np.hypot(*(xy - f[:2])) < f[2] + 0.8 for f in room.footprints):
            continue
        tip = np.radians(rng.uniform(-3.0, 3.0, 2))
        R = R_from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)]) @ R_from_rotvec([tip[0], tip[1], 0.0])
        poses.append(T_from_Rt(R, np.array([*xy, rng.uniform(1.0, 1.8)])))
    if len(poses) < n:
        raise ValueError(f"found room for {len(poses)} of {n} rig poses in this room")
    return poses


def render_scene(camera: CameraModel, T_world_camera: np.ndarray, patches: list[Patch], supersample: int = 2,
                 blur_sigma_px: float = 0.5) -> np.ndarray:
    """The noise-free image (grey levels, float) of a scene: one ray per pixel centre, ``supersample^2`` rays
    averaged where a neighbour's centre sees another patch or a reflectance more than ``REFLECTANCE_STEP`` apart
    (and the pixels next to those), then optical blur."""
    grid = _normalized_grid(camera)
    H, W = camera.height, camera.width
    pv, pu = np.divmod(np.arange(H * W), W)
    origin = T_world_camera[:3, 3]
    centre = _rays_world(_interp_subpixels(grid, pu, pv, np.array([0.0])), T_world_camera)
    _, which, refl = cast(origin, centre, patches)
    refl = np.where(np.isnan(refl), SKY_REFLECTANCE, refl).reshape(H, W)
    edge = np.flatnonzero(edge_pixels(which.reshape(H, W), refl, 1, REFLECTANCE_STEP))
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    out = refl.ravel().copy()
    for part in np.array_split(edge, 16):
        dirs = _rays_world(_interp_subpixels(grid, pu[part], pv[part], offs), T_world_camera)
        r = cast(origin, dirs, patches)[2]
        out[part] = np.where(np.isnan(r), SKY_REFLECTANCE, r).reshape(-1, supersample * supersample).mean(1)
    img = 20.0 + 210.0 * out.reshape(H, W)
    return cv2.GaussianBlur(img, (0, 0), blur_sigma_px) if blur_sigma_px > 0 else img


def cast_room_sweep(beams, patches: list[Patch], rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """A sweep of the room (LiDAR frame): points with range noise, intensity (reflectance x cos incidence x
    100), ring. Beams through glass and echoes weaker than ``MIN_ECHO`` return nothing."""
    dirs, ring = beams.directions()
    solid = [p for p in patches if p.label != GLASS]
    glass = [p for p in patches if p.label == GLASS]
    r, which, refl = cast(np.zeros(3), dirs, solid, beams.max_range_m)
    if glass:  # a pane in front of what a beam hits: the echo is lost
        r_glass = cast(np.zeros(3), dirs, glass, beams.max_range_m)[0]
        r = np.where(r_glass < r, np.inf, r)
    normals = np.array([p.normal for p in solid])
    cos = np.abs(np.einsum("ij,ij->i", dirs, normals[np.clip(which, 0, None)]))
    echo = np.where(np.isnan(refl), 0.0, refl) * cos
    hit = np.isfinite(r) & (echo >= MIN_ECHO)
    rr = r[hit] + rng.normal(0.0, beams.sigma_range_m, hit.sum())
    return dirs[hit] * rr[:, None], (100 * echo[hit]).astype(np.float32), ring[hit]


def simulate_scene_dataset(out: str | Path, n_frames: int = 10, seed: int = 0, lidar: str = "vlp16",
                           sigma_range_m: float = 0.02, pixel_noise: float = 2.0, supersample: int = 2,
                           overwrite: bool = False) -> Path:
    """A folder of frames of one furnished room (module docstring) with no board, written atomically.

    Parameters
    ----------
    out : str or Path
        The folder to write: ``dataset.yaml`` (``lidar: 3d`` and the camera's intrinsics), ``NNNN.png`` and
        ``NNNN.pcd`` (x, y, z, intensity, ring), and ``ground_truth.json`` (``T_camera_lidar``, each frame's
        ``T_world_lidar``, the seed).
    n_frames : int
        Frames, each from another spot and heading of the rig in the room.
    seed : int
        Seed of the rig's mounting, the room, the rig's poses and the noise.
    lidar : str
        ``vlp16``, ``os64`` or ``hdl64e``.
    sigma_range_m : float
        Range noise (m, 1 sd).
    pixel_noise : float
        Image noise (grey levels, 1 sd).
    supersample : int
        Rays per pixel along each side where an edge can pass (anti-aliasing; one ray elsewhere).
    overwrite : bool
        Replace an existing folder.

    Returns
    -------
    Path
        The folder.

    Examples
    --------
    >>> lc.simulate_scene("/tmp/room", n_frames=10, seed=3, lidar="os64")   # doctest: +SKIP
    """
    check_output_folder(out, overwrite)
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, lidar, sigma_range_m)
    room = furnished_room(rng)
    poses = rig_poses(room, n_frames, rng)
    cam = rig.camera
    T_lidar_camera = T_inverse(rig.T_camera_lidar)
    spec = {"lidar": "3d", "camera": {"model": cam.model, "width": cam.width, "height": cam.height,
                                      "K": cam.K.tolist(), "dist": cam.dist.tolist()}}
    with atomic_directory(out, overwrite=overwrite) as tmp:
        write_dataset_yaml(tmp, spec, "simulated by lidarcam (a furnished room, no board); ground_truth.json is for "
                                      "evaluation only")
        for k, T_wl in enumerate(poses):
            patches = _in_lidar(room.patches, T_wl)
            clean = render_scene(cam, T_lidar_camera, patches, supersample)
            cv2.imwrite(str(tmp / f"{k:04d}.png"), add_pixel_noise(clean, rng, pixel_noise))
            pts, inten, ring = cast_room_sweep(rig.beams, patches, rng)
            write_scan(tmp / f"{k:04d}.pcd", pts, inten, ring)
        truth = {"T_camera_lidar": rig.T_camera_lidar.tolist(), "T_world_lidar": [T.tolist() for T in poses],
                 "lidar_model": rig.beams.name, "seed": seed, "scene": "furnished room"}
        (tmp / "ground_truth.json").write_text(json.dumps(truth, indent=1))
    return Path(out)
