"""The factor graph's options (``RefinementOptions``: robust loss, outliers, noise levels, range model, edges,
intrinsics) and the detector's corner-error correlation that the corner noise defaults to.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import chi_square as chi2
from .range_model import RANGE_MODELS

ROBUST_LOSSES = ("none", "huber", "cauchy")
OUTLIER_POLICIES = ("drop", "downweight")
# Effective per-corner noise over each board's own corner residual (its per-axis PnP residual, shrunk towards the
# camera's pooled one: ``noise_levels.board_corner_residuals_px``). Measured by `make bench`: bench_rig_corners.py
# (702 boards of 60 cameras against the truth: d2 mean 5.54 at 1.0) and bench_noise_models.py (100 one-camera
# one-LiDAR datasets, five generators: the extrinsic's mean d2 5.82 with each board's residual at 1.0, 5.18 with
# the camera's pooled residual at 1.28).
CORNER_ERROR_CORRELATION = 1.0
# A per-board plane error (m) beyond which the boards' disagreement is not a plane error (a bent or held board,
# intrinsics: millimetres to a centimetre or two): the model test scales by what remains.
MAX_PLANE_ERROR_M = 0.05
# Prior standard deviation (m) that holds a pinned range term at 0 in the graph.
PINNED_SD_M = 1e-7


@dataclass(frozen=True)
class RefinementOptions:
    """Settings of the factor-graph refinement.

    Attributes
    ----------
    robust : str
        The robust loss on each frame's plane residual: ``huber``, ``cauchy`` or ``none``.
    robust_threshold : float
        The loss's threshold on the whitened residual's norm (default: the square root of chi-square(3) at 99%).
    corner_noise_px : float or None
        Effective per-corner pixel noise; None: estimated from the corner residuals.
    corner_error_correlation : float
        The factor by which the pooled corner residual is scaled to the effective noise (detected corners err
        together within a board).
    range_noise_m : float or None
        LiDAR range noise (m); None: estimated from the board points' scatter.
    outliers : str
        ``drop`` or ``downweight`` a frame whose residual is a gross outlier.
    outlier_p : float
        The tail probability below which a frame is a gross outlier.
    plane_floor_m : float or None
        A per-board plane error (m); None: estimated when the planes disagree beyond the noise.
    estimate_plane_floor : bool
        Estimate that plane error from the data.
    max_iterations : int
        The optimiser's iterations at most.
    corner_scale_sd : float
        A per-board relative scale error of the detected pattern, for a camera known to have one.
    range_model : str
        The LiDAR range model: ``none``, ``offset``, ``per-ring``, ``offset+dark``, ``full``, or ``auto`` (chosen by
        test).
    range_accuracy_m : float or None
        The sensor's range accuracy (m, 1 sd of a systematic error) that sets the range terms' priors; None: a
        conservative default.
    edges : bool or None
        Use the board's edges where the rings (a 2D scan's line) leave it; None: where the board's size is known
        (True: also warn where they cannot be used; False: the planes alone, the ends a check).
    max_sensor_separation_m : float or None
        2D: a solution with the sensors farther apart than this (m) is not a solution; None: no bound.
    refine_intrinsics : bool
        Refine the camera's intrinsics with the extrinsic (``solvers.intrinsics_refinement``; :func:`calibrate` and
        :func:`solve` do it, :func:`refine` does not).
    """

    robust: str = "huber"
    # On the whitened norm of a frame's plane residual; sqrt of chi-square(3) at 99%.
    robust_threshold: float = float(np.sqrt(chi2.ppf(0.99, 3)))
    corner_noise_px: float | None = None
    corner_error_correlation: float = CORNER_ERROR_CORRELATION
    range_noise_m: float | None = None
    outliers: str = "drop"
    # Gross outliers only (a wrong segment or a moved board is off by thousands): detected corners have
    # heavy-tailed errors, and dropping a good frame for a 1-in-1000 residual costs more than it saves.
    outlier_p: float = 1e-6
    # Per-board plane error (m): given, or estimated when the planes disagree beyond the noise.
    plane_floor_m: float | None = None
    estimate_plane_floor: bool = True
    max_iterations: int = 100
    # A per-board relative scale error of the detected corner pattern (it moves the board's distance by that
    # fraction), beyond the effective corner noise, for a camera known to have one; the rendered boards' scale
    # error (1e-4) is already part of CORNER_ERROR_CORRELATION.
    corner_scale_sd: float = 0.0
    # The LiDAR range model (``solvers.range_model``): none, offset, per-ring, offset+dark, full, or auto (chosen
    # by test), and the sensor's range accuracy (m, 1 sd of a systematic error) that sets the terms' priors.
    range_model: str = "auto"
    range_accuracy_m: float | None = None  # None: the conservative default (DEFAULT_RANGE_ACCURACY_M)
    # Check a 3D estimate by its ring ends, without the edges (``solvers.outline_check``), and by its camera's
    # intrinsics (``intrinsics_refinement.intrinsics_drop``): off where the estimate only starts another solve, as
    # a rig's pairwise solves, whose joint graph has its own checks.
    checks: bool = True
    # The board's edges where the rings (a 2D scan's line) leave it (``solvers.board_edges``), when the board's
    # size is known. None: used where it is (the default); True: asked for (a warning where they cannot be used);
    # False: the planes alone.
    edges: bool | None = None
    # Under ``auto``, a 3D LiDAR's global offset not supported by its planes is tested again with the ring ends on
    # the board's outline in the graph, where the board's size is known (``range_terms_choice``): on boards facing
    # the rig the planes alone cannot tell an offset from the translation along their normals. None: where
    # ``edges`` is not False; True: also where the estimate's own edges are off for a later solve to add them (a
    # rig's pairwise solves); False: never.
    offset_with_ends: bool | None = None
    # 2D: a minimal solution or refined minimum whose sensors are farther apart than this (m) is not a solution
    # (``solution_selection.physical``); None: no bound. ``calibrate`` uses its segmentation parameters' bound.
    max_sensor_separation_m: float | None = 1.0
    refine_intrinsics: bool = False

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise ValueError(f"Expected robust in {ROBUST_LOSSES}, got {self.robust!r}")
        if self.outliers not in OUTLIER_POLICIES:
            raise ValueError(f"Expected outliers in {OUTLIER_POLICIES}, got {self.outliers!r}")
        if self.range_model not in RANGE_MODELS:
            raise ValueError(f"Expected range_model in {RANGE_MODELS}, got {self.range_model!r}")
        for name in ("corner_noise_px", "range_noise_m", "plane_floor_m", "range_accuracy_m",
                     "max_sensor_separation_m"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"Expected {name} to be positive, got {v}")


def intrinsics_step_scale(options: RefinementOptions, camera) -> float:
    """What the intrinsics' standard deviations are scaled by where they are propagated: intrinsics estimated from
    the images carry OpenCV's, which take the corners as independent, so they are scaled like the corner noise
    (``corner_error_correlation``, unless the corner noise is given); stated ones (dataset.yaml) as they are."""
    return options.corner_error_correlation if options.corner_noise_px is None and camera.source != "dataset.yaml" \
        else 1.0


def measurement_model_options(**changes) -> RefinementOptions:
    """Options for frames simulated at the measurement level (``observation_model.simulate_measurements``):
    corners independent at the given noise, no detector scale error."""
    return RefinementOptions(**{"corner_error_correlation": 1.0, "corner_scale_sd": 0.0, **changes})
