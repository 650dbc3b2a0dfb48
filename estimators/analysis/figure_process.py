"""A child interpreter that draws the report's matplotlib figures (``report_figures``) while this process does
other work: the posterior sampling, the report's OpenCV figures and its page.

The child is a fresh interpreter (no fork: no caller's main module imported again, no threads copied). It
loads matplotlib and corner as soon as it starts, then takes jobs in order from its input, one line each: a
job number, a figure's name in ``report_figures.DRAWERS`` and two ``.npz`` paths, the arrays in and the PNGs
out (never pickles). It answers each with a line, ``<number> ok`` or ``<number> failed``. A job is submitted
once per content: asking again for the same figure of the same arrays returns the same job, so a figure can
be started ahead (``report.draw_ahead``) and asked for later by the report as if it were new. Between jobs,
while none waits, it builds the corner plot's and traces' empty axes (much of their cost).

Where the child cannot be started, fails, or runs past ``CHILD_TIMEOUT_S``, the figures are drawn in this
process instead: the same figures, only later.
"""
from __future__ import annotations

import gc
import hashlib
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

# Seconds a job may take in the child before the figure is drawn here instead.
CHILD_TIMEOUT_S = 300.0


def _child_env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(Path(__file__).resolve().parents[2])] + [p for p in [os.environ.get("PYTHONPATH")] if p]))


def _digest(kind: str, arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256(kind.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"|{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _draw_here(kind: str, arrays: dict[str, np.ndarray]) -> dict[str, bytes]:
    from .report_figures import DRAWERS

    return DRAWERS[kind](**arrays)


class FigureProcess:
    """The drawing child, started at construction (where it cannot be, every figure is drawn here). Use it as
    a context manager; closing it ends the child."""

    def __init__(self) -> None:
        self.child: subprocess.Popen | None = None
        self._tmp = tempfile.TemporaryDirectory(prefix="lidarcam-figures-")
        self._jobs: dict[str, Callable[[], dict[str, bytes]]] = {}
        self._answers: dict[int, bool] = {}
        self._sent = 0
        try:
            self.child = subprocess.Popen([sys.executable, "-m", __name__, "--serve"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, bufsize=0,
                                          env=_child_env())
        except OSError:
            self.child = None

    @property
    def running(self) -> bool:
        return self.child is not None and self.child.poll() is None

    def draw(self, kind: str, **arrays: np.ndarray) -> Callable[[], dict[str, bytes]]:
        """Start drawing ``report_figures.DRAWERS[kind](**arrays)``; the returned function waits for its PNGs
        (by file name). The same figure of the same arrays is drawn once."""
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        key = _digest(kind, arrays)
        if key not in self._jobs:
            self._jobs[key] = self._submit(kind, arrays)
        return self._jobs[key]

    def _submit(self, kind: str, arrays: dict[str, np.ndarray]) -> Callable[[], dict[str, bytes]]:
        job = self._sent
        src, dst = Path(self._tmp.name) / f"in{job}.npz", Path(self._tmp.name) / f"out{job}.npz"
        sent = False
        if self.running:
            try:
                np.savez(src, **arrays)
                self.child.stdin.write(f"{job}\t{kind}\t{src}\t{dst}\n".encode())
                self.child.stdin.flush()
                self._sent += 1
                sent = True
            except OSError:
                self._stop()
        done: list[dict[str, bytes]] = []

        def wait() -> dict[str, bytes]:
            if not done:
                pngs = self._collect(job, dst) if sent else None
                done.append(pngs if pngs is not None else _draw_here(kind, arrays))
            return done[0]

        return wait

    def _collect(self, job: int, dst: Path) -> dict[str, bytes] | None:
        """The child's PNGs of ``job``, or None (it failed, ended or ran out of time; it is then stopped)."""
        deadline = time.monotonic() + CHILD_TIMEOUT_S
        try:
            while job not in self._answers:
                if self.child is None:
                    return None
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self.child.stdout], [], [], left)[0]:
                    raise TimeoutError
                line = self.child.stdout.readline()  # unbuffered: nothing is read past the line
                if not line:
                    raise EOFError
                number, status = line.split()
                self._answers[int(number)] = status == b"ok"
            if not self._answers[job]:
                return None
            with np.load(dst, allow_pickle=False) as z:
                return {name: z[name].tobytes() for name in z.files}
        except (TimeoutError, EOFError, OSError, ValueError):
            self._stop()
            return None

    def _stop(self) -> None:
        child, self.child = self.child, None
        if child is not None:
            if child.poll() is None:
                child.kill()
            child.wait()
            for pipe in (child.stdin, child.stdout):
                try:
                    pipe.close()
                except OSError:
                    pass

    def close(self) -> None:
        """End the child: nothing more is asked of it, and its interpreter's orderly exit (matplotlib's) would
        only be waited for. Figures not collected yet are drawn here if asked for after all."""
        self._stop()
        self._tmp.cleanup()

    def __enter__(self) -> "FigureProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve() -> None:
    """The child: load the drawing modules, then draw each job of the input until it closes; whenever no job
    waits after the first (the calibration has reached its refinement, and the caller samples the posterior),
    collect its garbage and build the next figures' empty axes (``report_figures.prepare``). Its answers go
    to the original standard output, which nothing else may write to: anything a library prints there goes
    to standard error instead."""
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    jobs = os.fdopen(os.dup(0), "rb", buffering=0)  # unbuffered: a line waiting is a line the fd still holds
    from .report_figures import DRAWERS, prepare, warm_up

    warm_up()
    # The cyclic garbage collector runs only while no job waits: during a figure its passes over the
    # figure's tens of thousands of fresh objects cost a sixth of the drawing time, for nothing freed.
    gc.disable()
    started = False
    while True:
        if started and not select.select([jobs], [], [], 0)[0]:
            gc.collect()
            prepare()
        started = True
        line = jobs.readline()
        if not line:
            return
        number, kind, src, dst = line.decode().rstrip("\n").split("\t")
        status = "failed"
        try:
            with np.load(src, allow_pickle=False) as z:
                pngs = DRAWERS[kind](**{k: z[k] for k in z.files})
            tmp = dst + ".part.npz"
            np.savez(tmp, **{name: np.frombuffer(png, np.uint8) for name, png in pngs.items()})
            os.replace(tmp, dst)
            status = "ok"
        except Exception:  # noqa: BLE001 (the parent draws the figure itself and meets the error there)
            pass
        answers.write(f"{number} {status}\n")
        answers.flush()


if __name__ == "__main__" and sys.argv[1:] == ["--serve"]:
    _serve()
