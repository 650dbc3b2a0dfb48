"""A rig's moving-board recording calibrated: each LiDAR's extrinsic and clock offset against the first camera.

``lidarcam extract`` of a rig bag whose board moves throughout writes, for each 3D LiDAR, the board followed in the
first camera's images with that LiDAR's sweeps (``lidarN/motion.npz``). Each LiDAR is solved against that camera
as a pair's moving board is (``moving_board.solve_moving``): its ``T_cam0_lidarN``, its offset ``t_cam0_stamp -
t_lidarN_stamp`` and their 7x7 covariance. The LiDARs share the camera's board poses, so their estimates are
somewhat correlated; each is given with its own covariance (the joint one is not formed), and a transform between
two LiDARs is composed through the camera with their covariances added as if independent (said in the file).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import block_diag

from .. import __version__
from ..errors import DatasetError
from ..io.motion_track import FILE, FOLLOWED_CAMERA
from ..io.rig_dataset import load_rig
from ..solvers.rig_graph import pair_transform
from .moving_board import TIME_OFFSET_CONVENTION, solve_moving
from .pair_estimate import PairEstimate
from .result import CONVENTION, COVARIANCE_CONVENTION
from .verdict import Verdict, verdict_of


@dataclass(frozen=True, eq=False)
class MovingRigResult:
    """Each LiDAR's moving-board calibration against ``camera`` (``lidars``: name -> :class:`MovingBoardResult`,
    whose ``pair`` is ``T_camera_lidar`` of that camera and LiDAR)."""

    dataset: str
    camera: str
    lidars: dict  # name -> MovingBoardResult
    ambiguous = False

    @property
    def verdict(self) -> Verdict:
        """The gravest of the LiDARs' verdicts, each reason named by its LiDAR."""
        return verdict_of([(r.verdict.level, f"{n}: {why}") for n, r in self.lidars.items()
                           for why in r.verdict.reasons])

    def to_dict(self) -> dict:
        """calibration.json of a rig (``rig``, ``reference``, ``sensors``, ``transforms``, ``cameras``) with each
        LiDAR's clock offset (``time_offsets_s``, as a still rig's) and its moving-board record."""
        cam = self.camera
        first = next(iter(self.lidars.values()))
        zero = np.zeros((6, 6))
        sensors = [{"name": cam, "type": "camera", f"T_{cam}_{cam}": np.eye(4).tolist(), "covariance": zero.tolist()}]
        transforms = {}
        for n, r in self.lidars.items():
            e = r.pair.transform_keys()
            sensors.append({"name": n, "type": "lidar", f"T_{cam}_{n}": e.pop("T"), **e,
                            "moving_board": {k: v for k, v in r.to_dict().items()
                                             if k in ("verdict", "time_offset_s", "time_offset_std_s",
                                                      "covariance_with_time_offset", "images_used", "sweeps_used",
                                                      "sweeps_with_board", "range_rms_m",
                                                      "range_scatter_own_planes_m", "point_times", "normal_spread",
                                                      "timings_s", "posterior", "posterior_note")}})
            transforms[f"T_{cam}_{n}"] = r.pair.transform_keys()
        names = list(self.lidars)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                transforms[f"T_{a}_{b}"] = self.between(a, b).transform_keys()
        held = {n: r.time_offset_std_s is None for n, r in self.lidars.items()}
        return {
            "verdict": self.verdict.to_dict(), "rig": True, "tool": "lidarcam", "version": __version__,
            "dataset": self.dataset, "recording": "moving board", "reference": cam, "convention": CONVENTION,
            "covariance_convention": COVARIANCE_CONVENTION,
            "covariance_source": first.to_dict()["covariance_source"] + "; each LiDAR solved against the camera on "
                                 "its own, a transform between two LiDARs composed through the camera with their "
                                 "covariances added as if independent (their shared camera poses correlate them)",
            "sensors": sensors, "transforms": transforms,
            "cameras": {cam: first.camera.as_dict()},
            "time_offsets_s": {n: r.time_offset_s for n, r in self.lidars.items()},
            "time_offsets_std_s": {n: r.time_offset_std_s for n, r in self.lidars.items()},
            "time_offsets_held": held, "time_offsets_source": {n: "the moving board" for n in self.lidars},
            "time_offsets_reference": cam,
            "time_offsets_convention": TIME_OFFSET_CONVENTION.replace("t_camera_stamp", f"t_{cam}_stamp")
            .replace("t_lidar_stamp", "t_<lidar>_stamp"),
        }

    def between(self, a: str, b: str) -> PairEstimate:
        """``T_a_b`` of two LiDARs through the camera, their covariances taken as independent."""
        Ta, Tb = self.lidars[a].pair, self.lidars[b].pair
        T, cov = pair_transform(Ta.T, Tb.T, block_diag(Ta.covariance, Tb.covariance))
        return PairEstimate(a, b, T, cov, None, min(Ta.frames, Tb.frames))


def calibrate_moving_rig(folder: str | os.PathLike, rng: np.random.Generator, time_offset_s: float | None = None,
                         samples: int = 0) -> MovingRigResult:
    """Each LiDAR of a moving board's rig folder against its first camera.

    Parameters
    ----------
    folder : str or os.PathLike
        A rig folder ``lidarcam extract`` wrote from a bag whose board moves throughout (each LiDAR's
        ``lidarN/motion.npz``, ``cam0``'s intrinsics in dataset.yaml).
    rng : numpy.random.Generator
        Drives the solves' random draws.
    time_offset_s : float, optional
        Hold every LiDAR's offset ``t_cam0_stamp - t_lidarN_stamp`` at this value (s) instead of solving it.
    samples : int
        Effective posterior samples of each LiDAR's extrinsic and offset (``solvers.moving_posterior``); 0 skips.

    Returns
    -------
    MovingRigResult
        Each LiDAR's :class:`~estimators.pipeline.moving_board.MovingBoardResult` (``lidars``), the rig's verdict;
        ``to_dict`` is calibration.json.

    Raises
    ------
    DatasetError
        No intrinsics for ``cam0``, or a LiDAR without its record.
    """
    rig = load_rig(folder, files=False)
    cams = [s for s in rig.sensors if s.is_camera]
    root = Path(rig.root)
    if cams[0].name != FOLLOWED_CAMERA or cams[0].camera is None:
        raise DatasetError(f"a moving board's rig follows the board in {FOLLOWED_CAMERA} with its intrinsics",
                           path=root / "dataset.yaml", hint="extract the bag again with lidarcam extract")
    lidars = {}
    for s in rig.sensors:
        if s.is_camera:
            continue
        if not (root / s.name / FILE).is_file():
            raise DatasetError(f"{s.name}/{FILE} not found: the LiDAR's record of the moving board",
                               path=root / s.name, hint="extract the bag again with lidarcam extract")
        lidars[s.name] = solve_moving(root / s.name, rig.board, cams[0].camera, rng, time_offset_s,
                                      (cams[0].name, s.name), samples)
    if not lidars:
        raise DatasetError("the rig has no LiDAR", path=root / "dataset.yaml", hint="extract it with --cloud-topic")
    return MovingRigResult(str(root), cams[0].name, lidars)
