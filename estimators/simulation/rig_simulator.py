"""Simulated rigs: several cameras and a 3D LiDAR sharing the frames, written as a rig folder
(``io.rig_dataset``) with the ground truth of every sensor.

The first camera and the LiDAR are the pair simulator's (``simulator.iter_frames``: its boards, scene and
noise). Further cameras, in this order: two pinhole cameras beside the first, turned 5-15 degrees (their views
overlap the first's); a fisheye looking backwards; a fisheye looking right; a pinhole looking left. A camera
whose view does not overlap the first's gets boards of its own, sampled in its view (and the LiDAR's), so that it
shares frames with the LiDAR only. Every camera is rendered of the same scene from its own pose and sees a frame
only when the whole board lies in its image (else it has no file for that frame). A second LiDAR (``lidars=2``,
VLP-16-like, 0.4-0.6 m to the first's left and 0.1-0.3 m lower, turned 10-30 degrees to the left and tilted a few
degrees) casts its own sweep of every frame's scene; it records every frame, as a running LiDAR does. A 2D
scanner (``scanners=1``, ``scan0``: 270 degrees in 0.25 degree steps, 1 cm range noise) sits level 0.15-0.3 m
below the camera and 0.1-0.3 m to its right, tilted up to 3 degrees: its scan line cuts the boards that reach
down to its height, and a frame whose board it misses is skipped by the calibration with that reason.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, transform_points

from ..io.dataset import dataset_spec, write_dataset_yaml
from ..io.output import atomic_directory
from ..io.pointcloud_io import write_scan
from .range_bias import RangeBias
from .rendering import add_pixel_noise, pixel_rays, render_clean
from .scene import cast, cast_background
from .simulator import (BEAM_MODELS, default_rig, iter_frames, sample_board_poses, scene_patches, static_scene,
                        write_sweep_2d)


def _fisheye(f: float) -> CameraModel:
    return CameraModel(np.array([[f, 0.0, 512.0], [0.0, f, 400.0], [0.0, 0.0, 1.0]]),
                       np.array([0.02, -0.005, 0.001, -0.0005]), 1024, 800, "fisheye")


def _extra_cameras(n: int, rng: np.random.Generator) -> list[tuple[str, CameraModel, np.ndarray, bool]]:
    """Cameras after the first (module docstring): ``(name, model, T_cam0_camk, overlaps the first's view)``."""
    out = []
    base = default_rig(np.random.default_rng(0)).camera
    for k in range(1, n):
        if k <= 2:
            side = 1.0 if k % 2 else -1.0
            t = np.array([side * rng.uniform(0.15, 0.35), rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)])
            yaw = side * np.deg2rad(rng.uniform(5.0, 15.0))
            f = base.K[0, 0] * rng.uniform(0.9, 1.1)
            K = np.array([[f, 0.0, base.width / 2 + rng.uniform(-10, 10)],
                          [0.0, f, base.height / 2 + rng.uniform(-10, 10)], [0.0, 0.0, 1.0]])
            cam, overlaps = CameraModel(K, base.dist.copy(), base.width, base.height, base.model), True
        else:  # backwards, right, left: the first's view not shared
            yaw = {3: np.pi, 4: np.pi / 2, 5: -np.pi / 2}[(k - 3) % 3 + 3] + np.deg2rad(rng.uniform(-5.0, 5.0))
            t = np.array([np.sin(yaw), 0.0, np.cos(yaw)]) * 0.15 + rng.uniform(-0.03, 0.03, 3)
            cam = _fisheye(rng.uniform(330.0, 370.0)) if k in (3, 4) else base
            overlaps = False
        R = R_from_rotvec(np.array([0.0, yaw, 0.0]))
        out.append((f"cam{k}", cam, T_from_Rt(R, t), overlaps))
    return out


def _second_lidar(rng: np.random.Generator) -> np.ndarray:
    """``T_lidar0_lidar1`` of the second LiDAR (module docstring)."""
    yaw = np.deg2rad(rng.uniform(10.0, 30.0))
    R = R_from_rotvec(np.array([0.0, 0.0, yaw])) @ R_from_rotvec(rng.normal(0.0, np.deg2rad(3.0), 3))
    return T_from_Rt(R, np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.4, 0.6), -rng.uniform(0.1, 0.3)]))


def _scanner(rng: np.random.Generator, T_lidar_cam0: np.ndarray, R_level_lidar: np.ndarray) -> np.ndarray:
    """``T_lidar0_scan0`` of the 2D scanner (module docstring): level in the world, below and right of the
    camera."""
    cam = T_lidar_cam0[:3, 3]
    down, right = R_level_lidar.T @ np.array([0.0, 0.0, -1.0]), T_lidar_cam0[:3, :3] @ np.array([1.0, 0.0, 0.0])
    t = cam + rng.uniform(0.15, 0.3) * down + rng.uniform(0.1, 0.3) * right
    R = R_level_lidar.T @ R_from_rotvec(np.r_[rng.normal(0.0, np.deg2rad(1.5), 2), rng.uniform(-0.2, 0.2)])
    return T_from_Rt(R, t)


def _sweep(beams, T_l0_l1: np.ndarray, patches, background, rng: np.random.Generator):
    """The second LiDAR's noisy sweep of the scene ``patches`` (in the first LiDAR's frame): points in its own
    frame, intensity, ring."""
    dirs, ring = beams.directions()
    ranges, _, refl = cast(T_l0_l1[:3, 3], background.dirs, patches, beams.max_range_m, background)
    hit = np.isfinite(ranges)
    r = ranges[hit] + rng.normal(0.0, beams.sigma_range_m, hit.sum())
    return dirs[hit] * r[:, None], (refl[hit] * 100).astype(np.float32), ring[hit]


def _sees_board(camera: CameraModel, T_camera_board: np.ndarray, board) -> bool:
    pts = transform_points(T_camera_board, board.inner_corners())
    if np.any(pts[:, 2] <= 0.1):
        return False
    uv = camera.project(pts)
    margin = 10.0
    return bool(np.all((uv[:, 0] > margin) & (uv[:, 0] < camera.width - margin) & (uv[:, 1] > margin)
                       & (uv[:, 1] < camera.height - margin)))


def simulate_rig(out: str | Path, n_poses: int = 10, seed: int = 0, cameras: int = 2, lidar: str = "hdl64e",
                 overwrite: bool = False, lidars: int = 1, scanners: int = 0, range_offset_m: float = 0.0,
                 range_bias: tuple[float, float, float] | None = None, scene: str = "default") -> Path:
    """Simulate a rig of pinhole cameras and one 3D LiDAR and write its folder atomically (module docstring).

    Parameters
    ----------
    out : str or Path
        The rig folder to write: sensors ``cam0..camN-1`` and ``lidar0``, reference ``cam0``.
    n_poses : int
        Board poses (frames), sampled in the first camera's view.
    seed : int
        Seed of the rig, the poses and the noise.
    cameras : int
        Cameras (2 or more).
    lidar : str
        The first LiDAR: ``hdl64e``, ``vlp16`` or ``os64``.
    overwrite : bool
        Replace an existing folder.
    lidars : int
        1, or 2 for a second LiDAR ``lidar1`` (VLP-16-like, module docstring).
    scanners : int
        0, or 1 for a 2D scanner ``scan0`` (module docstring).
    range_offset_m : float
        A range offset (m) added to every return of ``lidar0`` (a systematic range error; ground_truth.json
        records it as ``range_offset_m``).
    range_bias : tuple of float, optional
        ``(global offset, sd of the per-ring offsets, black-square offset)`` (m) injected into ``lidar0``'s returns
        as the single pair's simulation does (``range_bias.RangeBias``, the rings' offsets drawn from a generator
        of their own); ground_truth.json records the terms as ``range_bias``.
    scene : str
        The scene every sensor sees (``simulator.static_scene``: ``default``, ``office``, ``hall`` or
        ``furnished``); in all but the default room a person holds the board in 70% of the frames.

    Returns
    -------
    Path
        The folder; its ``ground_truth.json`` holds every sensor's ``T_cam0_<sensor>``, the frames each camera
        saw and every frame's board pose ``T_cam0_board``.
    """
    if lidars not in (1, 2):
        raise ValueError(f"Expected 1 or 2 LiDARs, got {lidars}")
    if scanners not in (0, 1):
        raise ValueError(f"Expected 0 or 1 2D scanners, got {scanners}")
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, lidar, 0.02)
    extra = _extra_cameras(cameras, rng)
    T_l0_l1 = _second_lidar(rng) if lidars == 2 else None
    poses = sample_board_poses(rig, n_poses, rng)
    for _, cam, T_c0_ck, overlaps in extra:
        if not overlaps:  # boards of its own, in its view and the LiDAR's
            own = replace(rig, camera=cam, T_camera_lidar=T_inverse(T_c0_ck) @ rig.T_camera_lidar)
            poses += [T_c0_ck @ T for T in sample_board_poses(own, max(3, n_poses // 2), rng)]
    T_lidar_cam0 = T_inverse(rig.T_camera_lidar)
    static = static_scene(rig, scene, rng, poses)
    T_l0_s = _scanner(rng, T_lidar_cam0, rig.level) if scanners else None
    backgrounds = {}
    for name, cam, T_c0_ck, _ in extra:
        T_lidar_ck = T_lidar_cam0 @ T_c0_ck
        backgrounds[name] = cast_background(T_lidar_ck[:3, 3], pixel_rays(cam, T_lidar_ck), static)
    spec = dataset_spec("3d", rig.board, rig.camera)
    sensors = [{"name": "cam0", "type": "camera", **spec["camera"]}]
    sensors += [{"name": n, "type": "camera", "model": c.model, "width": c.width, "height": c.height,
                 "K": c.K.tolist(), "dist": c.dist.tolist()} for n, c, _, _ in extra]
    sensors.append({"name": "lidar0", "type": "lidar", "lidar": "3d"})
    if T_l0_l1 is not None:
        sensors.append({"name": "lidar1", "type": "lidar", "lidar": "3d"})
        beams1 = BEAM_MODELS["vlp16"](0.02)
        dirs1, _ = beams1.directions()
        background1 = cast_background(T_l0_l1[:3, 3], dirs1 @ T_l0_l1[:3, :3].T, static, beams1.max_range_m)
    if T_l0_s is not None:
        sensors.append({"name": "scan0", "type": "lidar", "lidar": "2d"})
        beams_s = BEAM_MODELS["2d"](0.01)
        dirs_s, _ = beams_s.directions()
        background_s = cast_background(T_l0_s[:3, 3], dirs_s @ T_l0_s[:3, :3].T, static, beams_s.max_range_m)
    truth = {"reference": "cam0", "T_cam0_cam0": np.eye(4).tolist(), "T_cam0_lidar0": rig.T_camera_lidar.tolist(),
             "range_offset_m": {"lidar0": float(range_offset_m)}}
    bias = None
    if range_bias is not None:
        bias = RangeBias.drawn(np.random.default_rng([seed, 16]), len(rig.beams.elevations_rad), *range_bias)
        truth["range_bias"] = {"lidar0": bias.record()}
    truth.update({f"T_cam0_{n}": T.tolist() for n, _, T, _ in extra})
    if T_l0_l1 is not None:
        truth["T_cam0_lidar1"] = (rig.T_camera_lidar @ T_l0_l1).tolist()
    if T_l0_s is not None:
        truth["T_cam0_scan0"] = (rig.T_camera_lidar @ T_l0_s).tolist()
    with atomic_directory(out, overwrite=overwrite) as tmp:
        write_dataset_yaml(tmp, {"board": spec["board"], "sensors": sensors, "reference": "cam0"},
                           "simulated rig by lidarcam; ground_truth.json is for evaluation only")
        for name in ["cam0", "lidar0"] + (["lidar1"] if T_l0_l1 is not None else []) + \
                (["scan0"] if T_l0_s is not None else []) + [n for n, _, _, _ in extra]:
            (tmp / name).mkdir()
        seen = {n: [] for n in ["cam0"] + [n for n, _, _, _ in extra]}
        boards = {}
        for f in iter_frames(rig, len(poses), rng, poses, scene, bias=bias, workers=1, static=static):
            boards[f.name] = f.T_camera_board.tolist()
            if _sees_board(rig.camera, f.T_camera_board, rig.board):
                cv2.imwrite(str(tmp / "cam0" / f"{f.name}.png"), f.image)
                seen["cam0"].append(f.name)
            points = f.points
            if range_offset_m:
                points = points * (1.0 + range_offset_m / np.linalg.norm(points, axis=1, keepdims=True))
            write_scan(tmp / "lidar0" / f"{f.name}.pcd", points, f.intensity, f.ring)
            T_lidar_board = T_lidar_cam0 @ f.T_camera_board
            patches, bi = scene_patches(rig, T_lidar_board, static, f.held)
            if T_l0_l1 is not None:
                write_scan(tmp / "lidar1" / f"{f.name}.pcd", *_sweep(beams1, T_l0_l1, patches, background1, rng))
            if T_l0_s is not None:
                write_sweep_2d(tmp / "scan0" / f"{f.name}.csv", beams_s,
                               _sweep(beams_s, T_l0_s, patches, background_s, rng)[0])
            for name, cam, T_c0_ck, _ in extra:
                T_ck_board = T_inverse(T_c0_ck) @ f.T_camera_board
                if not _sees_board(cam, T_ck_board, rig.board):
                    continue
                T_lidar_ck = T_lidar_cam0 @ T_c0_ck
                clean = render_clean(cam, T_lidar_ck, patches, bi, transform_points(T_lidar_board,
                                                                                    rig.board.outline()),
                                     background=backgrounds[name])
                cv2.imwrite(str(tmp / name / f"{f.name}.png"), add_pixel_noise(clean, rng, rig.pixel_noise))
                seen[name].append(f.name)
        truth["frames_seen"] = seen
        truth["T_cam0_board"] = boards
        (tmp / "ground_truth.json").write_text(json.dumps(truth, indent=1))
    return Path(out)



def miscalibrate_camera(folder: str | Path, name: str, focal_factor: float = 1.01, k1_factor: float = 0.5) -> Path:
    """A simulated rig folder whose camera ``name`` is given wrong intrinsics in dataset.yaml: its focal lengths
    times ``focal_factor`` and its k1 times ``k1_factor`` (the images are as simulated). Returns the folder."""
    import yaml

    path = Path(folder) / "dataset.yaml"
    spec = yaml.safe_load(path.read_text())
    cam = next(s for s in spec["sensors"] if s["name"] == name)
    cam["K"][0][0] *= focal_factor
    cam["K"][1][1] *= focal_factor
    cam["dist"][0] *= k1_factor
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return Path(folder)
