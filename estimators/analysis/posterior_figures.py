"""The posterior's two figures, the corner plot with the Laplace ellipses and the MCMC traces, drawn from plain
arrays. They are the report's slowest figures and need nothing but the samples, so the report draws them in a
child process (:func:`start_posterior_figures`) while it draws the rest; this module imports only numpy,
matplotlib and corner, which is all that process loads. Arrays go to the child and PNGs come back as ``.npz``
files (never pickles); the child is a fresh interpreter, so no caller's main module is imported again and no
threads are forked."""
from __future__ import annotations

import io
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.figure import Figure

from .figures import new_figure, png_bytes

LABELS = ["rot x [deg]", "rot y [deg]", "rot z [deg]", "trans x [mm]", "trans y [mm]", "trans z [mm]"]
UNITS = np.array([np.degrees(1.0)] * 3 + [1000.0] * 3)  # tangent (rad, m) to the figures' deg and mm
DPI = 90


def corner_png(xi: np.ndarray, covariance_laplace: np.ndarray) -> bytes:
    """Posterior samples ``xi`` (N, 6; GTSAM tangent, LiDAR axes) shown in deg and mm with the Laplace
    covariance's 1- and 2-sigma ellipses."""
    import corner

    # corner's own size for 6 axes (2 in per panel, margins), on a figure outside pyplot. Density shading and
    # contours, without corner's marker per sample outside the outer contour: those tens of thousands of
    # markers were a quarter of the whole report's drawing time and add nothing the contours do not show.
    fig = corner.corner(xi * UNITS, fig=Figure(figsize=(13.9, 13.9)), labels=LABELS, quantiles=[0.025, 0.5, 0.975],
                        show_titles=True, title_fmt=".3f", title_kwargs={"fontsize": 8}, label_kwargs={"fontsize": 8},
                        plot_datapoints=False)
    C = covariance_laplace * np.outer(UNITS, UNITS)
    axes = np.array(fig.axes).reshape(6, 6)
    angles = np.linspace(0, 2 * np.pi, 100)
    circle = np.stack([np.cos(angles), np.sin(angles)])
    for i in range(6):
        for j in range(i):
            vals, vecs = np.linalg.eigh(C[np.ix_([j, i], [j, i])])
            for k in (1, 2):
                e = vecs @ (np.sqrt(np.maximum(vals, 0))[:, None] * circle) * k
                axes[i, j].plot(e[0], e[1], color="tab:red", lw=0.8)
    fig.suptitle("posterior (black) and Laplace 1/2-sigma ellipses (red); offsets from the estimate", fontsize=9)
    return png_bytes(fig, dpi=DPI, tight=False)  # corner sets the margins for its labels: no second layout pass


def traces_png(chain: np.ndarray, burn: int) -> bytes:
    """The sampler's chain (steps, walkers, 7: the tangent and the log camera-noise scale), a twelfth of the
    walkers drawn, with the end of burn-in dashed."""
    labels = LABELS + ["log s (camera noise scale)"]
    units = np.append(UNITS, 1.0)
    fig, ax = new_figure(7, 1, figsize=(10, 11), sharex=True)
    step = max(1, chain.shape[1] // 12)
    for k in range(7):
        ax[k].plot(chain[:, ::step, k] * units[k], lw=0.4, alpha=0.6)
        ax[k].axvline(burn, color="k", lw=0.8, ls="--")
        ax[k].set_ylabel(labels[k], fontsize=7)
    ax[-1].set_xlabel("step (dashed: end of burn-in)")
    # fixed margins instead of tight_layout and a tight crop: the same page, a third of the drawing time
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.05, top=0.98, hspace=0.12)
    return png_bytes(fig, dpi=DPI, tight=False)


def posterior_pngs(xi: np.ndarray, covariance_laplace: np.ndarray, chain: np.ndarray, burn: int
                   ) -> tuple[bytes, bytes]:
    """``(corner plot, traces)`` as PNG bytes."""
    return corner_png(xi, covariance_laplace), traces_png(chain, burn)


# Seconds the child may take before the figures are drawn here instead.
CHILD_TIMEOUT_S = 300.0


def _child_env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(Path(__file__).resolve().parents[2])] + [p for p in [os.environ.get("PYTHONPATH")] if p]))


class FigureProcess:
    """A child interpreter started ahead of the report: it loads numpy, matplotlib and corner while the
    calibration runs (the sampler uses one core), then waits for the posterior's arrays. Closing it unused
    ends it (its input closes). Use as a context manager, or :func:`start_posterior_figures` takes it over."""

    def __init__(self) -> None:
        self.child: subprocess.Popen | None = None
        try:
            self.child = subprocess.Popen([sys.executable, "-m", __name__, "--wait"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=_child_env())
        except OSError:
            self.child = None

    def take(self) -> subprocess.Popen | None:
        """The waiting child (None if it could not start or has ended), handed over once."""
        child, self.child = self.child, None
        if child is not None and child.poll() is not None:
            child.wait()
            return None
        return child

    def close(self) -> None:
        child, self.child = self.child, None
        if child is not None:
            try:
                child.stdin.close()
                child.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                child.kill()
                child.wait()
            child.stdout.close()

    def __enter__(self) -> "FigureProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def start_posterior_figures(xi: np.ndarray, covariance_laplace: np.ndarray, chain: np.ndarray, burn: int,
                            process: FigureProcess | None = None) -> Callable[[], tuple[bytes, bytes]]:
    """Start drawing :func:`posterior_pngs` in a child process (``process``'s waiting one, or a new one); the
    returned function waits for the PNGs.

    Where the child cannot be started, fails or runs past ``CHILD_TIMEOUT_S``, the figures are drawn in this
    process instead: the same figures, only later."""
    args = (xi, covariance_laplace, chain, burn)
    tmp = tempfile.TemporaryDirectory(prefix="lidarcam-figures-")
    child = process.take() if process is not None else None
    try:
        src = Path(tmp.name) / "posterior.npz"
        np.savez(src, xi=xi, covariance_laplace=covariance_laplace, chain=chain, burn=burn)
        if child is not None:
            child.stdin.write(str(src).encode() + b"\n")
            child.stdin.flush()  # (communicate() below closes it)
        else:
            child = subprocess.Popen([sys.executable, "-m", __name__, str(src)], stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, env=_child_env())
    except OSError:
        if child is not None:
            child.kill()
            child.wait()
        tmp.cleanup()
        return lambda: posterior_pngs(*args)

    def wait() -> tuple[bytes, bytes]:
        try:
            out, _ = child.communicate(timeout=CHILD_TIMEOUT_S)
            if child.returncode == 0:
                with np.load(io.BytesIO(out), allow_pickle=False) as z:
                    return z["corner"].tobytes(), z["traces"].tobytes()
        except (subprocess.TimeoutExpired, OSError, ValueError, KeyError):
            child.kill()
            child.wait()
        finally:
            tmp.cleanup()
        return posterior_pngs(*args)

    return wait


def _main(path: str) -> None:
    """The child: the arrays from ``path`` in, the two PNGs as an ``.npz`` on stdout. With ``--wait``, it
    loads the drawing modules first and then reads the path from its input (none: it ends)."""
    if path == "--wait":
        import corner as _  # noqa: F401  (loaded now, and a first figure drawn, while nothing waits for them)

        png_bytes(new_figure(figsize=(1, 1))[0], dpi=DPI, tight=False)
        path = sys.stdin.readline().strip()
        if not path:
            return
    with np.load(path, allow_pickle=False) as z:
        corner, traces = posterior_pngs(z["xi"], z["covariance_laplace"], z["chain"], int(z["burn"]))
    buf = io.BytesIO()
    np.savez(buf, corner=np.frombuffer(corner, np.uint8), traces=np.frombuffer(traces, np.uint8))
    sys.stdout.buffer.write(buf.getvalue())


if __name__ == "__main__":
    _main(sys.argv[1])
