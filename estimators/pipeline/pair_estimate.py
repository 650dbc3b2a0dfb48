"""One pair of sensors' estimate, as every result gives it (``result.pair(a, b)``, a single pair's and a rig's
alike): the transform, its covariance and samples, and what is read from them (standard deviations, intervals,
credible regions). The printout and the reports show a pair from this record alone."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import T_log, quat_xyzw_from_R, skew

from ..solvers.closed_form import describe_direction
from ..solvers.posterior import INTERVAL_LEVELS, equal_tailed, mahalanobis_d2, mode_distance, region_d2, regions
from ..solvers.rig_graph import translation_sd_in_first


@dataclass(frozen=True, eq=False)
class PairEstimate:
    """Two sensors' estimate: ``T_a_b`` with its covariance and samples (``result.pair(a, b)``).

    Attributes
    ----------
    a, b : str
        The sensors' names (a single pair's are ``cam0`` and ``lidar0``).
    T : numpy.ndarray
        4x4 ``T_a_b``: maps b's points into a's frame (for a camera and a LiDAR, ``T_camera_lidar``).
    covariance : numpy.ndarray or None
        6x6 in the right tangent (``T_true = T Exp(xi)``, about and along b's axes): the posterior samples' when
        sampled, else the graph's Laplace one; None without a refinement.
    samples : numpy.ndarray or None
        The posterior's tangent samples (M x 6), or None.
    frames : int
        The frames the two share with the board found in both.
    mode_index, mode_centers, mode_weights
        Where the samples mix several minima (a 2D scanner's few boards): each sample's minimum, each minimum as a
        tangent offset of ``T`` (K, 6) and its mass; else None, None and ().
    """

    a: str
    b: str
    T: np.ndarray
    covariance: np.ndarray | None
    samples: np.ndarray | None
    frames: int
    mode_index: np.ndarray | None = None
    mode_centers: np.ndarray | None = None
    mode_weights: tuple = ()

    def region_d2(self, level: float) -> float:
        """The credible region at ``level`` (``posterior.region_d2``): ``T Exp(xi)`` with
        :meth:`region_distance` of ``xi`` at most this; with several minima, the union of each one's own ellipsoid."""
        return region_d2(self.samples, level, self.mode_index, self.mode_centers)

    def region_distance(self, xi: np.ndarray) -> np.ndarray:
        """The distance the credible region bounds, of tangent offsets ``xi`` (rows) of ``T``: the squared
        Mahalanobis distance under the samples' covariance, or with several minima from the nearest one under its
        own samples' covariance (``posterior.mode_distance``)."""
        if self.mode_index is None:
            return mahalanobis_d2(self.samples, np.atleast_2d(xi))
        return mode_distance(self.samples, self.mode_index, self.mode_centers, xi)

    def regions(self) -> dict:
        """The sampled credible regions at 99% and 99.9% (``posterior.regions``; with several minima, each one's
        transform, mass and covariance) as calibration.json gives them."""
        return regions(self.samples, self.mode_index, self.mode_centers, self.T, self.mode_weights)

    def contains(self, T: np.ndarray, level: float) -> bool:
        """Whether the transform ``T`` lies in the sampled credible region at ``level``."""
        return bool(self.region_distance(T_log(np.linalg.inv(self.T) @ T))[0] <= self.region_d2(level))

    @property
    def T_camera_lidar(self) -> np.ndarray:
        return self.T

    @property
    def std_rotation_deg(self) -> np.ndarray | None:
        """About b's axes (degrees)."""
        c = self.covariance
        return None if c is None else np.degrees(np.sqrt(np.maximum(np.diag(c)[:3], 0.0)))

    @property
    def std_translation_mm(self) -> np.ndarray | None:
        """Along b's axes (millimetres): the right tangent's."""
        c = self.covariance
        return None if c is None else 1000 * np.sqrt(np.maximum(np.diag(c)[3:], 0.0))

    @property
    def std_translation_camera_mm(self) -> np.ndarray | None:
        """Of the entries of ``T``'s translation, in a's frame (millimetres)."""
        return None if self.covariance is None else 1000 * translation_sd_in_first(self.T, self.covariance)

    def weakest_translation(self) -> dict | None:
        """Where the translation is least certain: its largest standard deviation (mm), that direction in a's frame
        (the covariance is along b's axes) and its words and advice (``closed_form.describe_direction``); None
        without a covariance. A single pair's printout and a rig's layout say it alike."""
        if self.covariance is None:
            return None
        ev, V = np.linalg.eigh(self.covariance[3:, 3:])
        weak = self.T[:3, :3] @ V[:, -1]
        axis, advice = describe_direction(weak)
        return {"max_translation_sd_mm": float(1000 * np.sqrt(max(ev[-1], 0.0))),
                "weakest_direction_camera": weak.tolist(), "axis": axis, "advice": advice}

    def camera_lidar_keys(self) -> dict:
        """The keys a single camera-LiDAR pair's calibration.json gives its transform (``T_camera_lidar``,
        ``quaternion_xyzw``, ``translation_m``; with a covariance, ``covariance`` and ``std``): a pair's file and a
        two-sensor rig's carry them alike (docs/reference/calibration_json.md)."""
        R, t = self.T[:3, :3], self.T[:3, 3]
        out = {"T_camera_lidar": self.T.tolist(), "quaternion_xyzw": quat_xyzw_from_R(R).tolist(),
               "translation_m": t.tolist()}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
            out["std"] = {"rotation_deg_about_lidar_xyz": self.std_rotation_deg.tolist(),
                          "translation_mm_along_lidar_xyz": self.std_translation_mm.tolist(),
                          "translation_mm_of_t_camera_xyz": self.std_translation_camera_mm.tolist()}
        return out

    def transform_keys(self) -> dict:
        """A rig's calibration.json entry of this transform: ``T``, ``covariance``, ``std_rotation_deg``,
        ``std_translation_mm`` (about and along b's axes) and ``std_translation_of_t_mm`` (in a's frame)."""
        return {"T": self.T.tolist(), "covariance": self.covariance.tolist(),
                "std_rotation_deg": self.std_rotation_deg.tolist(),
                "std_translation_mm": self.std_translation_mm.tolist(),
                "std_translation_of_t_mm": self.std_translation_camera_mm.tolist()}

    def intervals(self, level: float) -> np.ndarray | None:
        """The samples' equal-tailed intervals (6, 2) of each tangent axis at ``level``, or None unsampled."""
        return None if self.samples is None else equal_tailed(self.samples, level)

    def summary(self) -> dict | None:
        """The samples' standard deviations, equal-tailed intervals at ``INTERVAL_LEVELS`` (degrees about, and
        millimetres along, b's axes: the right tangent) and credible regions (``posterior.regions``: the
        covariance's ellipsoid about the estimate holding 99% and 99.9% of the samples); None unsampled."""
        if self.samples is None:
            return None
        sd = np.std(self.samples, axis=0, ddof=1)
        out = {"std_rotation_deg": np.degrees(sd[:3]).tolist(), "std_translation_mm": (1000 * sd[3:]).tolist()}
        for level in INTERVAL_LEVELS:
            iv = self.intervals(level)
            out[f"{round(100 * level)}%"] = {"rotation_deg": np.degrees(iv[:3]).tolist(),
                                            "translation_mm": (1000 * iv[3:]).tolist()}
        out["credible_regions"] = self.regions()
        return out

    def inverse(self) -> "PairEstimate":
        """``T_b_a``: exactly, ``(T Exp(xi))^-1 = T^-1 Exp(-Ad_T xi)``, so the tangent maps by ``-Ad_T``."""
        R, t = self.T[:3, :3], self.T[:3, 3]
        ad = np.zeros((6, 6))
        ad[:3, :3] = ad[3:, 3:] = R
        ad[3:, :3] = skew(t) @ R
        cov = None if self.covariance is None else ad @ self.covariance @ ad.T
        samples = None if self.samples is None else -self.samples @ ad.T
        centers = None if self.mode_centers is None else -self.mode_centers @ ad.T
        return PairEstimate(self.b, self.a, np.linalg.inv(self.T), cov, samples, self.frames, self.mode_index, centers,
                            self.mode_weights)
