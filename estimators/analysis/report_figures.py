"""The report's matplotlib figures, drawn from plain arrays: the posterior's corner plot with the Laplace
ellipses and its MCMC traces, the per-frame residuals, and the LiDAR range residuals. They are the report's
slowest figures, so ``figure_process.FigureProcess`` draws them in a child interpreter while the calibration
samples its posterior and the report draws the rest. This module imports only numpy, matplotlib and corner:
all that child loads. Each figure is one entry of :data:`DRAWERS`, a function of named arrays (what the child
reads from an ``.npz``, never a pickle) to named PNGs."""
from __future__ import annotations

from typing import Callable

import numpy as np
from matplotlib.figure import Figure

from .figures import new_figure, png_bytes

LABELS = ["rot x [deg]", "rot y [deg]", "rot z [deg]", "trans x [mm]", "trans y [mm]", "trans z [mm]"]
UNITS = np.array([np.degrees(1.0)] * 3 + [1000.0] * 3)  # tangent (rad, m) to the figures' deg and mm
DPI = 90
CORNER_INCHES = 13.9  # corner's own size for 6 axes: 2 in per panel and its margins

# Empty figures built ahead by :func:`prepare` (a drawing process builds them while it waits for samples): a
# figure's axes and ticks are most of the corner plot's cost, and they do not depend on the data.
_SPARE: dict[str, tuple] = {}


def _corner_figure() -> Figure:
    fig = Figure(figsize=(CORNER_INCHES, CORNER_INCHES))
    fig.subplots(6, 6)  # as corner would make them
    return fig


def _traces_figure() -> tuple:
    fig, ax = new_figure(7, 1, figsize=(10, 11), sharex=True)
    for a in ax:  # tick objects for the ticks drawn later (a tick's making is half of this figure's drawing)
        a.xaxis.get_major_ticks(12)
        a.yaxis.get_major_ticks(12)
    return fig, ax


def prepare() -> None:
    """Build the next corner plot's and traces' empty figures now, while nothing waits for them; the figures
    drawn on them are the same, byte for byte."""
    if "corner" not in _SPARE:
        _SPARE["corner"] = (_corner_figure(),)
    if "traces" not in _SPARE:
        _SPARE["traces"] = _traces_figure()


def corner_png(xi: np.ndarray, covariance_laplace: np.ndarray) -> bytes:
    """Posterior samples ``xi`` (N, 6; GTSAM tangent, LiDAR axes) shown in deg and mm with the Laplace
    covariance's 1- and 2-sigma ellipses."""
    import corner

    # A figure outside pyplot. Density shading and contours, without corner's marker per sample outside the
    # outer contour: those tens of thousands of markers were a quarter of the whole report's drawing time and
    # add nothing the contours do not show. On a figure with its axes made already, corner keeps their
    # limits unless given the ranges: the samples' extent, which is corner's own default.
    data = xi * UNITS
    lo, hi = data.min(0), data.max(0)
    fig = _SPARE.pop("corner", (None,))[0] if np.all(hi > lo) else None
    fig = corner.corner(data, fig=fig if fig is not None else Figure(figsize=(CORNER_INCHES, CORNER_INCHES)),
                        range=list(zip(lo, hi)) if fig is not None else None, labels=LABELS,
                        quantiles=[0.025, 0.5, 0.975], label_kwargs={"fontsize": 8}, plot_datapoints=False)
    C = covariance_laplace * np.outer(UNITS, UNITS)
    axes = np.array(fig.axes).reshape(6, 6)
    # Each panel's median and 95% interval as plain text: corner's own titles are TeX-like math, which
    # matplotlib parses at about 35 ms a title (a quarter of the plot's drawing time).
    q = np.quantile(data, [0.025, 0.5, 0.975], axis=0)
    for i in range(6):
        axes[i, i].set_title(f"{LABELS[i]} = {q[1, i]:.3f}  -{q[1, i] - q[0, i]:.3f} / +{q[2, i] - q[1, i]:.3f}",
                             fontsize=8)
    angles = np.linspace(0, 2 * np.pi, 100)
    circle = np.stack([np.cos(angles), np.sin(angles)])
    for i in range(6):
        for j in range(i):
            vals, vecs = np.linalg.eigh(C[np.ix_([j, i], [j, i])])
            for k in (1, 2):
                e = vecs @ (np.sqrt(np.maximum(vals, 0))[:, None] * circle) * k
                axes[i, j].plot(e[0], e[1], color="tab:red", lw=0.8)
    fig.suptitle("posterior (black) and Laplace 1/2-sigma ellipses (red); offsets from the estimate; titles: "
                 "median and 95% interval", fontsize=9)
    return png_bytes(fig, dpi=DPI, tight=False)  # corner sets the margins for its labels: no second layout pass


def traces_png(chain: np.ndarray, burn: int) -> bytes:
    """The sampler's chain (steps, walkers, 7 or more: the tangent and the log camera-noise scale, then for a 2D
    scan's ends the outline's nuisances, not drawn), a twelfth of the walkers drawn, with the end of burn-in
    dashed."""
    labels = LABELS + ["log s (camera noise scale)"]
    units = np.append(UNITS, 1.0)
    fig, ax = _SPARE.pop("traces", None) or _traces_figure()
    step = max(1, chain.shape[1] // 12)
    for k in range(7):
        ax[k].plot(chain[:, ::step, k] * units[k], lw=0.4, alpha=0.6)
        ax[k].axvline(burn, color="k", lw=0.8, ls="--")
        ax[k].set_ylabel(labels[k], fontsize=7)
    ax[-1].set_xlabel("step (dashed: end of burn-in)")
    # fixed margins instead of tight_layout and a tight crop: the same page, a third of the drawing time
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.05, top=0.98, hspace=0.12)
    return png_bytes(fig, dpi=DPI, tight=False)


def posterior_pngs(xi: np.ndarray, covariance_laplace: np.ndarray, chain: np.ndarray, burn
                   ) -> dict[str, bytes]:
    """``corner.png`` and ``traces.png``."""
    return {"corner.png": corner_png(xi, covariance_laplace), "traces.png": traces_png(chain, int(burn))}


def residuals_pngs(names: np.ndarray, chi2: np.ndarray, outlier: np.ndarray, corner_rms_px: np.ndarray,
                   angle_deg: np.ndarray, distance_mm: np.ndarray) -> dict[str, bytes]:
    """``residuals.png``: per used frame, the plane consistency chi-square, the corner reprojection RMS and the
    camera-vs-LiDAR plane angle and distance (outliers red)."""
    fig, ax = new_figure(2, 2, figsize=(11, 6))
    colors = ["tab:red" if o else "tab:blue" for o in outlier]
    x = np.arange(len(names))
    ax[0, 0].bar(x, chi2, color=colors)
    ax[0, 0].axhline(3, color="k", lw=0.8, ls="--")
    ax[0, 0].set_title("plane consistency chi-square per frame (3 dof; red: outlier)", fontsize=9)
    ax[0, 1].bar(x, corner_rms_px, color=colors)
    ax[0, 1].set_title("corner reprojection RMS [px]", fontsize=9)
    ax[1, 0].bar(x, angle_deg, color=colors)
    ax[1, 0].set_title("camera vs LiDAR plane: normal angle [deg]", fontsize=9)
    ax[1, 1].bar(x, distance_mm, color=colors)
    ax[1, 1].set_title("camera vs LiDAR plane: distance [mm]", fontsize=9)
    for a in ax.ravel():
        a.set_xticks(x, [str(n) for n in names], rotation=90, fontsize=7)
    fig.tight_layout()
    return {"residuals.png": png_bytes(fig, dpi=DPI, tight=False)}  # tight_layout fitted the labels already


def range_residuals_pngs(range_m: np.ndarray, ring: np.ndarray, dark: np.ndarray, before_m: np.ndarray,
                         after_m: np.ndarray, chosen: np.ndarray) -> dict[str, bytes]:
    """``range_residuals.png``: board points' range residuals against range, ring (-1: none) and square colour,
    without the range terms (``before_m``) and with the chosen ones (``after_m``, model ``chosen``)."""
    a = {"range": range_m, "ring": ring, "dark": dark.astype(bool), "before": before_m, "after": after_m}
    fig, ax = new_figure(1, 3, figsize=(13, 3.6))
    edges = np.linspace(a["range"].min(), a["range"].max() + 1e-9, 11)
    centre = 0.5 * (edges[1:] + edges[:-1])
    which = np.digitize(a["range"], edges) - 1
    for key, style in (("before", "o--"), ("after", "s-")):
        mean = [1000 * np.mean(a[key][which == j]) if np.any(which == j) else np.nan for j in range(10)]
        ax[0].plot(centre, mean, style, label=key)
    ax[0].set_xlabel("range [m]")
    ax[0].set_ylabel("mean range residual [mm]")
    rings = np.unique(a["ring"][a["ring"] >= 0])
    for key, style in (("before", "o--"), ("after", "s-")):
        ax[1].plot(rings, [1000 * np.mean(a[key][a["ring"] == r]) for r in rings], style, label=key)
    ax[1].set_xlabel("ring")
    x = np.arange(2)
    for j, key in enumerate(("before", "after")):
        means = [1000 * np.mean(a[key][~a["dark"]]) if np.any(~a["dark"]) else np.nan,
                 1000 * np.mean(a[key][a["dark"]]) if np.any(a["dark"]) else np.nan]
        ax[2].bar(x + 0.35 * j, means, 0.35, label=key)
    ax[2].set_xticks(x + 0.175, ["white", "black"])
    ax[2].set_xlabel("square colour (black: most of the return placed on black)")
    for axis in ax:
        axis.axhline(0, color="k", lw=0.6)
        axis.legend(fontsize=8)
    fig.suptitle("board points' range residuals: without the range terms (before) and with the chosen ones "
                 f"(after: {chosen})", fontsize=9)
    fig.tight_layout()
    return {"range_residuals.png": png_bytes(fig, dpi=DPI, tight=False)}


# Each figure by name: a function of named arrays to named PNGs.
def corner_pngs(xi: np.ndarray, covariance_laplace: np.ndarray) -> dict[str, bytes]:
    """``corner.png`` alone: a rig pair's samples, composed from the rig's chain (whose traces are the sensors')."""
    return {"corner.png": corner_png(xi, covariance_laplace)}


DRAWERS: dict[str, Callable[..., dict[str, bytes]]] = {
    "posterior": posterior_pngs, "corner": corner_pngs, "residuals": residuals_pngs,
    "range_residuals": range_residuals_pngs}


def warm_up() -> None:
    """Load what drawing needs (corner, and matplotlib's first-figure setup) before anything waits for it."""
    import corner as _  # noqa: F401

    png_bytes(new_figure(figsize=(1, 1))[0], dpi=DPI, tight=False)


