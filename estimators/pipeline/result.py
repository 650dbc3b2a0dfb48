"""A calibration's result: the record (``CalibrationResult``), the planes' residuals under it, and calibration.json."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from geometry.camera import CameraModel

from .. import __version__
from ..io.output import write_json_atomic
from ..measurements import FrameMeasurement
from ..solvers.closed_form import describe_direction
from ..solvers.edges_in_graph import conflict_words
from ..solvers.refinement import Refinement
from .pair_estimate import PairEstimate
from .verdict import Verdict, pair_verdict

if TYPE_CHECKING:  # the 2D solvers are imported where they are used (they load scipy.optimize)
    from ..solvers.solution_selection import MinimalSelection


# 2D: a second minimum holding at least this share of the posterior mass makes the result ambiguous: the printed
# result begins with it and ``lidarcam calibrate --strict`` exits with EXIT_AMBIGUOUS.
AMBIGUOUS_MASS = 0.05
CONVENTION = ("T_camera_lidar maps LiDAR points into the camera frame: p_camera = R p_lidar + t. "
              "LiDAR x forward, y left, z up; camera x right, y down, z forward (OpenCV).")
COVARIANCE_CONVENTION = ("6x6 covariance of xi = [rotation (rad); translation (m)] in GTSAM's Pose3 tangent: "
                         "T_true = T_hat * Exp(xi), so both parts are along the LiDAR's axes")


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """The estimate and everything a reader needs to judge it; frames keep their measurements.

    ``covariance`` (the factor graph's Laplace one: the pair's own solve draws no posterior, the engine does),
    ``std_rotation_deg``, ``std_translation_mm`` and ``diagnostics`` are derived from these; ``to_dict()`` gives
    ``calibration.json``'s content.

    Attributes
    ----------
    T_camera_lidar : numpy.ndarray
        4x4, maps LiDAR points into the camera frame (``p_camera = R p_lidar + t``).
    init, refine : str
        The initial solver and the refinement used.
    frames : tuple of FrameMeasurement
        Every frame, used or skipped (with its reason).
    camera : CameraModel
        The camera model used (given, or calibrated from the images).
    normal_singular_values : numpy.ndarray
        Singular values of the used frames' stacked camera normals (their spread).
    weakest_direction_camera : numpy.ndarray
        The direction those normals constrain least, in the camera frame.
    dataset : str
        The dataset's name.
    warnings : tuple of str
        Everything that limits trust in the result, most important first.
    timings_s : dict
        Stage times (s).
    plane_residuals : dict
        Per frame: the normal angle (rad) and distance (m) between the camera's and the LiDAR's plane.
    refinement : Refinement or None
        The factor graph's solution and Laplace covariance.
    selection : MinimalSelection or None
        2D: how the minimal solutions were chosen.
    modes : tuple
        2D: the refined minima that hold posterior mass, the chosen one first.
    measurements_source : str
        ``measured``, ``cache`` or a measurements file.
    """

    T_camera_lidar: np.ndarray
    init: str
    refine: str
    frames: tuple[FrameMeasurement, ...]
    camera: CameraModel
    normal_singular_values: np.ndarray
    weakest_direction_camera: np.ndarray
    dataset: str
    warnings: tuple[str, ...] = ()
    timings_s: dict = field(default_factory=dict)
    plane_residuals: dict = field(default_factory=dict)  # name -> (normal angle rad, distance m)
    refinement: Refinement | None = None
    selection: MinimalSelection | None = None  # 2D LiDAR: how the minimal solutions were chosen
    # 2D LiDAR: the refined minima that hold posterior mass (``solution_selection.Mode``), the chosen one first;
    # more than one means the data do not decide between them.
    modes: tuple = ()
    # Where the measurements came from: "measured" (images and scans read now), "cache" or a measurements file.
    measurements_source: str = "measured"
    # When the planes disagree beyond their noise (3D): whether freeing the intrinsics explains it
    # (``intrinsics_refinement.intrinsics_drop``), else None.
    intrinsics_check: dict | None = None

    @property
    def covariance(self) -> np.ndarray | None:
        """6x6 covariance in GTSAM's right tangent (``T_true = T_hat Exp(xi)``, ``xi = [rot; trans]``): the
        factor graph's Laplace one (its marginal); None without the refinement."""
        return None if self.refinement is None else self.refinement.covariance

    @property
    def diagnostics(self) -> dict:
        """Noise levels, consistency test and timings, as written to calibration.json."""
        d = self.to_dict()
        return {k: d[k] for k in ("noise", "consistency", "timings_s", "warnings") if k in d}

    @property
    def std_rotation_deg(self) -> np.ndarray | None:
        """Standard deviations of the rotation about the LiDAR's x, y, z axes (degrees): :meth:`pair`'s."""
        return self.pair().std_rotation_deg

    @property
    def std_translation_mm(self) -> np.ndarray | None:
        """Standard deviations of the translation along the LiDAR's x, y, z axes (millimetres): :meth:`pair`'s."""
        return self.pair().std_translation_mm

    @property
    def std_translation_camera_mm(self) -> np.ndarray | None:
        """Standard deviations of the entries of ``t`` in ``T_camera_lidar`` (camera axes, millimetres)."""
        return self.pair().std_translation_camera_mm

    def pair(self, a: str = "cam0", b: str = "lidar0") -> PairEstimate:
        """The pair as a rig's result gives it (``RigResult.pair``): a single pair's sensors are ``cam0`` and
        ``lidar0``, the names its folder takes as a rig; ``pair("lidar0", "cam0")`` gives ``T_lidar_camera``."""
        est = PairEstimate("cam0", "lidar0", self.T_camera_lidar, self.covariance, None, self.frames_used)
        if (a, b) == ("cam0", "lidar0"):
            return est
        if (a, b) == ("lidar0", "cam0"):
            return est.inverse()
        raise KeyError(f"{a!r}, {b!r}: a single pair's sensors are 'cam0' and 'lidar0'")

    @property
    def frames_used(self) -> int:
        dropped = {f.name for f in self.refinement.frames if f.dropped} if self.refinement else set()
        return sum(f.usable and f.name not in dropped for f in self.frames)

    @property
    def condition_number(self) -> float:
        s = self.normal_singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    def _uncertainty_dict(self) -> dict:
        ref = self.refinement
        if ref is None:
            return {"covariance": None,
                    "covariance_note": "no covariance without refinement (refine: none)"}
        return {
            "covariance": self.covariance.tolist(),
            "covariance_convention": COVARIANCE_CONVENTION,
            "covariance_note": "Laplace approximation (the pair's own solve draws no posterior samples)",
            "std": self.pair().camera_lidar_keys()["std"],
            "noise": {"corner_noise_px": ref.corner_noise_px, "corner_residual_px": ref.corner_residual_px,
                      "range_noise_m": ref.range_noise_m, "plane_floor_m": ref.plane_floor_m},
            "consistency": {"variance_factor": ref.variance_factor, "dof": ref.consistency_dof,
                            "p_value": ref.consistency_p},
            "iterations": ref.iterations,
            "lidar_range_model": (ref.range_model.to_dict() if ref.range_model is not None else
                                  {"requested": "none", "chosen": "none", "reason": "not requested", "terms": []}),
            "board_edges": ref.edges if ref.edges is not None else {"used": False},
            "contradicted": self.contradicted,
        }

    @property
    def alternatives(self) -> tuple:
        """2D LiDAR: the other minima that hold posterior mass (empty when the answer is unambiguous)."""
        return tuple(self.modes[1:])

    @property
    def contradicted(self) -> str | None:
        """How the boards' planes and their edges conflict beyond their noise (``edges_in_graph.conflict_words``; the
        covariance then holds both answers), or None. The verdict says it (``CHECK``, or ``UNTRUSTED`` beyond what
        a frame may disagree by)."""
        return conflict_words(self.refinement.edges) if self.refinement is not None else None

    @property
    def ambiguous(self) -> bool:
        """A second minimum holds at least ``AMBIGUOUS_MASS`` of the posterior mass: the printed result starts
        with it, and ``--strict`` exits non-zero."""
        return any(m.mass >= AMBIGUOUS_MASS for m in self.modes[1:])

    @property
    def verdict(self) -> Verdict:
        """``OK``, ``CHECK: ...`` or ``UNTRUSTED: ...`` (``pipeline.verdict``): the first line of the printout, the
        report and calibration.json; ``--strict`` exits non-zero on ``UNTRUSTED`` or an ambiguous answer."""
        return pair_verdict(self)

    def minimal_dict(self) -> dict:
        """2D: how the minimal solutions were chosen and the minima that hold mass (calibration.json's
        ``minimal_solutions`` and ``modes``); empty for a 3D LiDAR's."""
        sel = self.selection
        if sel is None:
            return {}
        return {"minimal_solutions": {
            "method": sel.method, "triples": sel.n_triples, "solutions": sel.n_solutions,
            "inside_board_extent": sel.n_inside_extent, "clusters": sel.n_clusters,
            "candidates_refined": len(sel.candidates), "cost_threshold": sel.threshold,
            "candidate_costs": [c.cost for c in sel.candidates], "degenerate_triples": list(sel.degenerate_triples),
            "weak_triples": list(sel.weak_triples), "multistart_fallback": sel.fallback, "seconds": sel.seconds,
            "max_sensor_separation_m": sel.max_separation_m, "unphysical_solutions": sel.n_unphysical},
            "modes": [{"T_camera_lidar": m.T_camera_lidar.tolist(), "posterior_mass": m.mass,
                       "covariance": m.refinement.covariance.tolist(), "refined_cost": m.cost,
                       "outline_cost": m.outline_cost, "evidence": m.evidence} for m in self.modes],
            "ambiguous": len(self.modes) > 1, "ambiguous_5_percent": self.ambiguous}

    def to_dict(self) -> dict:
        fits = {f.name: f for f in self.refinement.frames} if self.refinement else {}
        axis, advice = describe_direction(self.weakest_direction_camera)
        return {
            "verdict": self.verdict.to_dict(),
            "tool": "lidarcam", "version": __version__, "dataset": self.dataset,
            "convention": CONVENTION,
            **{k: v for k, v in self.pair().camera_lidar_keys().items() if k not in ("covariance", "std")},
            "init": self.init, "refine": self.refine,
            "frames_used": self.frames_used, "frames_total": len(self.frames),
            **self._uncertainty_dict(),
            "frames": [frame_dict(f, self.plane_residuals.get(f.name), fits.get(f.name)) for f in self.frames],
            "layout": {
                "normal_singular_values": self.normal_singular_values.tolist(),
                "condition_number": self.condition_number,
                "weakest_direction_camera": self.weakest_direction_camera.tolist(),
                "weakest_direction_words": f"{axis}: to constrain it further, {advice}",
            },
            **self.minimal_dict(),
            "intrinsics": self.camera.as_dict(),
            "intrinsics_check": self.intrinsics_check,
            "warnings": list(self.warnings),
            "measurements_source": self.measurements_source,
            "timings_s": self.timings_s,
        }


def frame_dict(f: FrameMeasurement, residual: tuple[float, float] | None = None, fit=None) -> dict:
    """One frame as calibration.json's ``frames`` give it: used or not and why, its measurements' sizes and planes,
    its planes' ``residual`` under the estimate and its ``fit`` (``refinement.FrameFit``), where given."""
    used = f.usable and not (fit is not None and fit.dropped)
    reason = f.reason if fit is None or not fit.dropped else f"dropped as an outlier: {fit.outlier}"
    d = {"name": f.name, "used": used, "reason": reason,
         "board_points": f.lidar.n_points if f.lidar else 0,
         "plane_rms_m": f.lidar.plane_rms_m if f.lidar else None,
         "corner_rms_px": f.camera.reprojection_rms_px if f.camera else None,
         "corner_detector": f.camera.detector if f.camera else None}
    if residual is not None:
        d["normal_residual_deg"] = float(np.degrees(residual[0]))
        d["distance_residual_m"] = residual[1]
    if fit is not None:
        d["plane_chi2"] = fit.plane_chi2
        d["consistency_chi2"] = fit.consistency_chi2
        d["plane_dof"] = fit.plane_dof
        d["robust_weight"] = fit.weight
        d["outlier"] = fit.outlier
    if f.camera is not None:
        d["camera_plane"] = {"normal": f.camera.plane.normal.tolist(), "distance_m": f.camera.plane.distance}
    if f.lidar is not None:
        d["lidar_plane"] = {"normal": f.lidar.plane.normal.tolist(), "distance_m": f.lidar.plane.distance}
    if f.decision is not None:
        d["lidar_board_choice"] = f.decision.to_dict()
    return d


def write_calibration(result: CalibrationResult, out_dir: str | Path) -> Path:
    """The pair's own solve's ``OUT/calibration.json``, atomically; returns its path (``estimators.write_calibration``
    writes either record)."""
    return write_json_atomic(Path(out_dir) / "calibration.json", result.to_dict())
