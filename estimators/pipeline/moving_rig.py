"""A rig's moving-board recording calibrated: each LiDAR's extrinsic and clock offset against the first camera.

``lidarcam extract`` of a rig bag whose board moves throughout writes, for each 3D LiDAR, the board followed in the
first camera's images with that LiDAR's sweeps (``lidarN/motion.npz``). The LiDARs are solved against that camera
in one joint solve (``moving_board.solve_moving_many``): each one's ``T_cam0_lidarN`` and offset ``t_cam0_stamp -
t_lidarN_stamp``, and the joint covariance over them all (the LiDARs share the camera's board poses and its
pointing, so their estimates correlate); a transform between two LiDARs is composed through the camera with that
correlation (sample by sample with the posterior).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import block_diag

from geometry.rotations import between_batch, local_batch, retract_batch

from .. import __version__
from ..errors import DatasetError
from ..io.motion_track import FILE, FOLLOWED_CAMERA
from ..io.rig_dataset import load_rig
from ..solvers.rig_graph import pair_transform
from .moving_board import TIME_OFFSET_CONVENTION, solve_moving_many
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
    covariance_joint: np.ndarray | None = None  # 7 per LiDAR in the order of ``lidars``: [rot; trans; offset]
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
                                                      "distance_scale", "timings_s", "posterior", "posterior_note")}})
            transforms[f"T_{cam}_{n}"] = _keys(r.pair)
        names = list(self.lidars)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                transforms[f"T_{a}_{b}"] = _keys(self.between(a, b))
        held = {n: r.time_offset_std_s is None for n, r in self.lidars.items()}
        return {
            "verdict": self.verdict.to_dict(), "rig": True, "tool": "lidarcam", "version": __version__,
            "dataset": self.dataset, "recording": "moving board", "reference": cam, "convention": CONVENTION,
            "covariance_convention": COVARIANCE_CONVENTION,
            "covariance_source": first.to_dict()["covariance_source"] + "; the LiDARs solved against the camera in "
                                 "one joint solve (they share its board poses and pointing), a transform between "
                                 "two LiDARs composed through the camera with their correlation",
            "covariance_joint_with_time_offsets": None if self.covariance_joint is None else
            self.covariance_joint.tolist(),
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
        """``T_a_b`` of two LiDARs through the camera, with their correlation: the joint covariance's blocks of the
        two (first order), or with the posterior each joint sample's pair composed."""
        Ta, Tb = self.lidars[a].pair, self.lidars[b].pair
        names = list(self.lidars)
        if self.covariance_joint is None:
            cov12 = block_diag(Ta.covariance, Tb.covariance)
        else:
            at = np.r_[7 * names.index(a) + np.arange(6), 7 * names.index(b) + np.arange(6)]
            cov12 = self.covariance_joint[np.ix_(at, at)]
        T, cov = pair_transform(Ta.T, Tb.T, cov12)
        samples = None
        if Ta.samples is not None and Tb.samples is not None and len(Ta.samples) == len(Tb.samples):
            samples = local_batch(T, *between_batch(*retract_batch(Ta.T, Ta.samples), *retract_batch(Tb.T, Tb.samples)))
            cov = np.cov(samples, rowvar=False)
        return PairEstimate(a, b, T, cov, samples, min(Ta.frames, Tb.frames))


def _keys(p: PairEstimate) -> dict:
    """A transform's entry in calibration.json: as a still rig's, with its posterior's summary when sampled."""
    summary = p.summary()
    return p.transform_keys() | ({} if summary is None else {"posterior": summary})


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
    names = [s.name for s in rig.sensors if not s.is_camera]
    for name in names:
        if not (root / name / FILE).is_file():
            raise DatasetError(f"{name}/{FILE} not found: the LiDAR's record of the moving board",
                               path=root / name, hint="extract the bag again with lidarcam extract")
    if not names:
        raise DatasetError("the rig has no LiDAR", path=root / "dataset.yaml", hint="extract it with --cloud-topic")
    results, joint = solve_moving_many([root / n for n in names], rig.board, cams[0].camera, rng, time_offset_s,
                                       cams[0].name, names, samples)
    return MovingRigResult(str(root), cams[0].name, dict(zip(names, results)), joint)
