"""A rig folder (``io.rig_dataset``) from a ROS 1 or ROS 2 bag with several cameras and LiDARs.

Streaming passes over the bag:

1. **Still poses, per camera.** Each image topic is examined on its own grid and grouped into still segments as
   for a single pair (``bag_extract``: its steadiest interior image, one per still pose, a pose already kept not
   kept again), its kept image staged on disk at once. Segments of different cameras that overlap in time are one
   board pose, one frame: a camera whose segment does not overlap any other's gives a frame of its own (a camera
   looking backwards at boards of its own). Frames are numbered in time order.
2. **Scans.** Each LiDAR topic's scan nearest to the frame's moment (the first camera's kept image), within the
   time the board stood still in every camera of the frame (plus ``max_dt_s``), is written for that frame. Only
   the best scan so far of the one frame in reach is held in memory.
3. **The motion between the poses**, where the first camera saw the board move (``bag_extract.MOVED_TO_TIME``):
   for each 3D LiDAR, the board followed in that camera's images and the LiDAR's sweeps (``bag_motion``) into the
   LiDAR's folder (``lidar0/motion.npz``): ``calibrate`` times each LiDAR's clock against the camera's with it.

A board that moves throughout (between ``bag_extract.MOVING_SHARE`` of the first camera's examined images) makes
the bag a moving board's rig: no frames; pass 3 follows the whole recording, for each 3D LiDAR, and ``calibrate``
solves each LiDAR's extrinsic and clock offset against that camera (``pipeline.moving_rig``). It takes one camera
(the others' poses need still boards) and 3D LiDARs only.

A camera without a kept image in a frame did not see the board then (it has no file for that stem), and a LiDAR
without a scan within reach has none either; ``extract.json`` says which sensor has which frame and why not.
Sensors are named ``cam0..``, ``lidar0..`` (clouds) and ``scan0..`` (2D scans) in the order their topics are
given, the reference ``cam0``; each camera's intrinsics from the CameraInfo beside its image topic when there is
one.
"""
from __future__ import annotations

import bisect
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2

from geometry.board import BoardModel

from ..errors import BagError
from .bag_extract import (CLOUD_TYPE, IMAGE_TYPES, INFO_TYPE, MOVING, MOVING_SHARE, SCAN_TYPE, STILL, ExtractOptions,
                          Detections, _between_poses, _Check, _follow, _ImageGrid, _messages, _open_reader,
                          _StillSegments, _camera_info_topic, _topic)
from .dataset import dataset_spec, write_dataset_yaml
from .image_io import to_gray8
from .motion_track import FOLLOWED_CAMERA, save_motion_track
from .output import atomic_directory
from .pointcloud_io import write_scan, write_scan_2d
from .ros_messages import camera_from_info, decode_image, decode_laser_scan, decode_point_cloud, stamp_ns


@dataclass(frozen=True)
class RigExtractSummary:
    """What a rig extraction wrote: the frames, each sensor's topic and its files, and each camera's image
    counts by reason (``bag_extract.REASONS``)."""

    out: Path
    frames: int
    topics: dict
    files: dict
    counts: dict = field(default_factory=dict)
    # Each LiDAR's board motion between the poses (followed with the first camera, or why not; none where the board
    # did not move in view); a moving board's: throughout.
    motion: dict = field(default_factory=dict)
    recording: str = STILL

    def lines(self) -> list[str]:
        if self.recording == MOVING:
            out = [f"a moving board (read as one, every image of {FOLLOWED_CAMERA} and every sweep of each LiDAR)"]
            out += [f"  {name:8s} {topic}: " + (self.motion[name] if name in self.motion else
                                                 f"{sum(self.counts.get(name, {}).values())} images examined")
                    for name, topic in self.topics.items()]
            return out
        out = [f"{self.frames} frames (one per still board pose, seen by any camera)"]
        for name, topic in self.topics.items():
            line = f"  {name:8s} {topic}: {self.files[name]} files"
            if name in self.counts:
                c = self.counts[name]
                line += f" ({c.get('kept', 0)} still poses of {sum(c.values())} images)"
            if name in self.motion:
                line += f"; motion between the poses {self.motion[name]}"
            out.append(line)
        return out


@dataclass
class _Frame:
    """One board pose: the kept image of each camera that held it still (stamp, staged file), the moment its scans
    are taken nearest to, and the window in which the board stood still in all of those cameras."""

    t_ref: int
    lo: int
    hi: int
    images: dict = field(default_factory=dict)


def extract_rig_bag(bag: str | os.PathLike, out: str | os.PathLike, board: BoardModel, image_topics: list[str],
                    cloud_topics: list[str] = (), scan_topics: list[str] = (), use_camera_info: bool = True,
                    options: ExtractOptions = ExtractOptions(), progress: bool = False,
                    overwrite: bool = False) -> RigExtractSummary:
    """Write a rig folder from a bag with several cameras and LiDARs (module docstring), atomically.

    Parameters
    ----------
    bag : str or os.PathLike
        A ROS 1 ``.bag`` file, a ROS 2 bag folder, or its ``.db3`` or ``.mcap`` file.
    out : str or os.PathLike
        The rig folder to write.
    board : BoardModel
        The board.
    image_topics : list of str
        ``sensor_msgs/Image`` or ``CompressedImage`` topics: ``cam0``, ``cam1``, ... in this order.
    cloud_topics, scan_topics : list of str
        ``PointCloud2`` topics (``lidar0``, ...) and ``LaserScan`` topics (``scan0``, ...); one or more in all.
    use_camera_info : bool
        False: write no intrinsics (``calibrate`` estimates each camera's from its board views).
    options : ExtractOptions
        Stillness settings; ``max_dt_s`` widens each frame's window for its scans.
    progress : bool
        Show a progress bar.
    overwrite : bool
        Replace an existing folder.

    Returns
    -------
    RigExtractSummary

    Raises
    ------
    BagError
        A missing or repeated topic, a topic without messages, or no still board pose in any camera.
    """
    from tqdm.auto import tqdm

    bag = Path(bag)
    topics = list(image_topics) + list(cloud_topics) + list(scan_topics)
    if not image_topics or not (cloud_topics or scan_topics):
        raise BagError("a rig needs at least one image topic and one cloud or scan topic", path=bag,
                       hint="pass --image-topic T for each camera and --cloud-topic T / --scan-topic T for each LiDAR")
    if len(set(topics)) != len(topics):
        raise BagError("a topic is given twice", path=bag, hint="give each sensor's topic once")
    cams = {f"cam{k}": t for k, t in enumerate(image_topics)}
    lidars = {f"lidar{k}": (t, "3d") for k, t in enumerate(cloud_topics)}
    lidars.update({f"scan{k}": (t, "2d") for k, t in enumerate(scan_topics)})
    scan_format = {"3d": options.scan_format or "pcd", "2d": options.scan_format or "csv"}
    reader = _open_reader(bag)
    try:
        img_conns = {n: _topic(reader, bag, t, IMAGE_TYPES, "--image-topic") for n, t in cams.items()}
        lidar_conns = {n: _topic(reader, bag, t, (CLOUD_TYPE,) if kind == "3d" else (SCAN_TYPE,),
                                 "--cloud-topic" if kind == "3d" else "--scan-topic")
                       for n, (t, kind) in lidars.items()}
        info = {n: _camera_info_topic(reader, t) if use_camera_info else None for n, t in cams.items()}
        info_conns = {n: _topic(reader, bag, t, (INFO_TYPE,), "--image-topic") for n, t in info.items() if t}
        with atomic_directory(out, overwrite=overwrite) as tmp:
            stage = tmp / ".staged"
            stage.mkdir()
            for name in list(cams) + list(lidars):
                (tmp / name).mkdir()
            detect = Detections(board)  # each image searched once, by the still poses' pass and the following
            kept, cameras, counts, segments = _still_poses(reader, bag, board, cams, img_conns, info, info_conns,
                                                           options, stage, progress, tqdm, detect)
            seen = segments[FOLLOWED_CAMERA]
            if options.follow_motion and seen.with_board >= 10 and seen.moved >= MOVING_SHARE * seen.with_board:
                shutil.rmtree(stage)
                motion = _moving_rig(reader, bag, tmp, board, cameras, cams, lidars, img_conns, lidar_conns, seen,
                                     progress, detect)
                _write_rig_records(tmp, bag, board, cams, cameras, lidars, info, {
                    "recording": MOVING, "image_counts": counts, "motion": motion})
                return RigExtractSummary(Path(out), 0, {**cams, **{n: t for n, (t, _) in lidars.items()}},
                                         {n: 0 for n in list(cams) + list(lidars)}, counts,
                                         {n: _followed_words(m) for n, m in motion.items()}, MOVING)
            frames = _merge(kept)
            if not frames:
                total = ", ".join(f"{n}: {sum(c.values())} images" for n, c in counts.items())
                raise BagError(f"no still board poses found in any camera ({total})", path=bag,
                               hint="hold the board still for --still-s seconds per pose, or raise --still-px for "
                                    "a hand-held board")
            files = {n: 0 for n in list(cams) + list(lidars)}
            records = [{"name": f"{j:04d}", "stamp_ns": f.t_ref, "cameras": {}, "lidars": {}}
                       for j, f in enumerate(frames)]
            for j, f in enumerate(frames):
                for cam, (stamp, path) in f.images.items():
                    path.rename(tmp / cam / f"{j:04d}.png")
                    records[j]["cameras"][cam] = stamp
                    files[cam] += 1
            for name, (topic, kind) in lidars.items():
                for j, (stamp, msg) in _nearest_scans(reader, bag, lidar_conns[name], frames, options.max_dt_s,
                                                  progress, tqdm):
                    path = tmp / name / f"{j:04d}.{scan_format[kind]}"
                    if kind == "3d":
                        write_scan(path, *decode_point_cloud(msg, topic, rings=True))
                    else:
                        write_scan_2d(path, *decode_laser_scan(msg))
                    records[j]["lidars"][name] = stamp
                    files[name] += 1
                if files[name] == 0:
                    raise BagError(f"topic {topic!r} has no scan while the board stood still in a camera", path=bag,
                                   hint="check that every sensor stamps with the same clock and recorded then")
            stage.rmdir()
            # The board's motion between the poses, followed in the first camera with each LiDAR's sweeps into
            # that LiDAR's folder: calibrate times each LiDAR's clock against the camera's with it.
            motion = {name: _between_poses(reader, bag, tmp / name, board, cameras.get(FOLLOWED_CAMERA),
                                           img_conns[FOLLOWED_CAMERA] + lidar_conns[name], cams[FOLLOWED_CAMERA],
                                           topic, kind, segments[FOLLOWED_CAMERA], options, progress,
                                           f"record CameraInfo beside {cams[FOLLOWED_CAMERA]}", detect)
                      for name, (topic, kind) in lidars.items()}
            motion = {n: w for n, w in motion.items() if w is not None}
            _write_rig_records(tmp, bag, board, cams, cameras, lidars, info, {
                "recording": STILL, "options": {"max_dt_s": options.max_dt_s, "still_s": options.still_s,
                                                "still_px": options.still_px, "check_hz": options.check_hz},
                "image_counts": counts, "files": files, "frames": records,
                "motion_between_poses": {"camera": FOLLOWED_CAMERA, **motion} if motion else None})
    finally:
        reader.close()
    return RigExtractSummary(Path(out), len(frames), {**cams, **{n: t for n, (t, _) in lidars.items()}}, files,
                             counts, motion)


def _write_rig_records(tmp: Path, bag: Path, board: BoardModel, cams: dict, cameras: dict, lidars: dict, info: dict,
                       record: dict) -> None:
    """The rig folder's dataset.yaml (every sensor, each camera's intrinsics where known) and extract.json (the
    topics and ``record``)."""
    spec = dataset_spec("3d", board, None)
    spec.pop("lidar")
    sensors = []
    for n in cams:
        entry = {"name": n, "type": "camera"}
        if cameras.get(n) is not None:
            entry.update(dataset_spec("3d", board, cameras[n])["camera"])
        sensors.append(entry)
    sensors += [{"name": n, "type": "lidar", "lidar": kind} for n, (_, kind) in lidars.items()]
    spec.update({"sensors": sensors, "reference": "cam0"})
    write_dataset_yaml(tmp, spec, f"extracted by lidarcam from {bag.name}: " + ", ".join(
        f"{n} {t}" for n, t in list(cams.items()) + [(n, t) for n, (t, _) in lidars.items()]))
    (tmp / "extract.json").write_text(json.dumps({
        "bag": str(bag), "topics": {**cams, **{n: t for n, (t, _) in lidars.items()}},
        "camera_info_topics": {n: t for n, t in info.items() if cameras.get(n) is not None}, **record}, indent=1)
        + "\n")


def _moving_rig(reader, bag: Path, tmp: Path, board: BoardModel, cameras: dict, cams: dict, lidars: dict,
                img_conns: dict, lidar_conns: dict, seen, progress: bool, detect: Detections) -> dict:
    """A board that moves throughout: for each 3D LiDAR, every image of the first camera and every sweep read into
    the LiDAR's folder (``motion.npz``); what was read per LiDAR. A :class:`BagError` for a second camera, a 2D
    scanner or the first camera's intrinsics unknown."""
    cam = FOLLOWED_CAMERA
    share = f"it moved between {seen.moved} of the {seen.with_board} examined images of {cams[cam]} that show it"
    if len(cams) > 1:
        raise BagError(f"the board moves throughout ({share}), and a moving board's rig is read with one camera",
                       path=bag, hint="give the first camera's --image-topic alone with the LiDARs' topics (the "
                                      "other cameras need the board held still per pose)")
    scanners = [t for t, kind in lidars.values() if kind != "3d"]
    if scanners:
        raise BagError(f"the board moves throughout ({share}), and a moving board needs a 3D LiDAR's sweeps: "
                       f"{', '.join(scanners)} is a 2D scanner", path=bag,
                       hint="with a 2D scanner hold the board still for --still-s seconds per pose")
    if cameras.get(cam) is None:
        raise BagError(f"the board moves throughout ({share}), and following it needs the camera's intrinsics: the "
                       f"bag has no CameraInfo beside {cams[cam]}", path=bag,
                       hint="record the camera's CameraInfo, or hold the board still per pose")
    motion = {}
    for name, (topic, _) in lidars.items():
        track, counts, images = _follow(reader, bag, tmp / name, board, cameras[cam], img_conns[cam] +
                                        lidar_conns[name], cams[cam], topic, progress, detect)
        save_motion_track(tmp / name, track)
        motion[name] = {"images": images, "counts": counts, "images_kept": len(track.view_stamps_s),
                        "sweeps_kept": len(track.sweep_stamps_s), "point_times": track.point_times,
                        "origin_ns": track.origin_ns}
    return motion


def _followed_words(m: dict) -> str:
    return (f"{m['sweeps_kept']} sweeps and {m['images_kept']} of {m['images']} images that show the board kept "
            f"(motion.npz; returns timed by {m['point_times'] or 'their sweep'})")


def _still_poses(reader, bag, board, cams, img_conns, info, info_conns, options, stage, progress, tqdm, detect):
    """Pass 1: each camera's kept still poses ``(first stamp, last stamp, kept stamp, staged file)``, its
    intrinsics from CameraInfo (or None), its images' counts by reason and its still segments' record (the board
    found by ``detect``, ``bag_extract.Detections``, which keeps what it found for the following)."""
    kept = {n: [] for n in cams}
    segments, grids = {}, {}
    for n in cams:
        def emit(c: _Check, n=n) -> None:
            seg = segments[n]  # emit runs before the segment is reset: its first and last images are known
            path = stage / f"{n}_{len(kept[n]):04d}.png"
            cv2.imwrite(str(path), c.image)
            kept[n].append((seg.first.stamp, seg.prev.stamp, c.stamp, path))

        segments[n] = _StillSegments(options, emit)
        grids[n] = _ImageGrid(options, segments[n])
    by_topic = {cams[n]: n for n in cams}
    info_of = {t: n for n, t in info.items() if t}
    cameras = {}
    conns = [c for cs in img_conns.values() for c in cs] + [c for cs in info_conns.values() for c in cs]
    bar = tqdm(total=sum(c.msgcount for c in conns), desc=f"images in {bag.name}", unit="msg", disable=not progress)
    for conn, t_bag, msg in _messages(reader, bag, conns):
        bar.update(1)
        if conn.topic in info_of:
            n = info_of[conn.topic]
            if cameras.get(n) is None:
                cameras[n] = camera_from_info(msg, conn.topic)
            continue
        n = by_topic[conn.topic]
        stamp = stamp_ns(msg, t_bag)
        if not grids[n].examine(stamp):
            continue
        image = decode_image(msg, conn.topic)
        # Still segments pair nothing here (each LiDAR's scan is taken in the second pass): every image may be kept.
        segments[n].add(_Check(stamp, image, detect(to_gray8(image)), scan=True))
    bar.close()
    for n in cams:
        segments[n].close()
        if grids[n].n == 0:
            raise BagError(f"topic {cams[n]!r} has no messages", path=bag, hint="check the recording")
    counts = {n: {k: int(v) for k, v in segments[n].counts.items() if v} for n in cams}
    return kept, cameras, counts, segments


def _merge(kept: dict) -> list[_Frame]:
    """Frames from every camera's still poses: poses of different cameras that overlap in time are one frame
    (a camera's second pose in the same overlap starts a frame of its own)."""
    poses = sorted((first, last, stamp, n, path) for n, ks in kept.items() for first, last, stamp, path in ks)
    frames: list[_Frame] = []
    for first, last, stamp, n, path in poses:
        f = frames[-1] if frames else None
        if f is not None and first <= f.hi and last >= f.lo and n not in f.images:
            f.lo, f.hi = max(f.lo, first), min(f.hi, last)
            f.images[n] = (stamp, path)
        else:
            frames.append(_Frame(stamp, first, last, {n: (stamp, path)}))
    for f in frames:  # the scans' moment: the first camera's kept image, within the window all cameras share
        f.t_ref = min(max(f.t_ref, f.lo), f.hi)
    return frames


def _nearest_scans(reader, bag, conns, frames: list[_Frame], max_dt_s: float, progress, tqdm):
    """Pass 2 for one LiDAR: ``(frame index, (stamp, message))`` of the scan nearest each frame's moment within
    its still window widened by ``max_dt_s``, streaming; frames without one are left out."""
    slack = int(max_dt_s * 1e9)
    lo = [f.lo for f in frames]
    best: tuple | None = None  # (frame index, |dt|, stamp, message)
    bar = tqdm(total=sum(c.msgcount for c in conns), desc="scans", unit="msg", disable=not progress)
    for _, t_bag, msg in _messages(reader, bag, conns):
        bar.update(1)
        stamp = stamp_ns(msg, t_bag)
        if best is not None and stamp > frames[best[0]].hi + slack:
            yield best[0], (best[2], best[3])
            best = None
        j = bisect.bisect_right(lo, stamp + slack) - 1
        if j < 0 or stamp > frames[j].hi + slack:
            continue
        dt = abs(stamp - frames[j].t_ref)
        if best is None or best[0] != j or dt < best[1]:
            if best is not None and best[0] != j:
                yield best[0], (best[2], best[3])
            best = (j, dt, stamp, msg)
    bar.close()
    if best is not None:
        yield best[0], (best[2], best[3])
