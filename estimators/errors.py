"""lidarcam's exceptions. Each message is one line: the file, the problem, and what to do."""
from __future__ import annotations

from contextlib import contextmanager


class LidarcamError(Exception):
    """Base of every error lidarcam raises on purpose; the CLI prints it as one line and exits 2."""

    def __init__(self, problem: str, *, path: object | None = None, hint: str | None = None):
        self.path = None if path is None else str(path)
        self.problem = problem
        self.hint = hint
        super().__init__(self.message)

    @property
    def message(self) -> str:
        text = f"{self.path}: {self.problem}" if self.path else self.problem
        return f"{text}; {self.hint}" if self.hint else text


def in_pair(exc: LidarcamError, pair: str, path: object | None = None) -> LidarcamError:
    """``exc`` said of one camera-LiDAR pair of a rig (``pair``, "cam0-lidar0"): the same kind, its problem prefixed
    with the pair, its file (else ``path``) and hint kept."""
    return type(exc)(f"{pair}: {exc.problem}", path=exc.path or path, hint=exc.hint)


@contextmanager
def about(path: object):
    """Name ``path`` in any :class:`LidarcamError` raised inside that names no file (a solver knows its arrays, not
    the folder they came from), so that the one-line error says which dataset it is about."""
    try:
        yield
    except LidarcamError as exc:
        if exc.path is None:
            exc.path = str(path)
            exc.args = (exc.message,)
        raise


class DatasetError(LidarcamError):
    """A dataset folder, its ``dataset.yaml`` or one of its files is missing, corrupt or inconsistent."""


class ScanReadError(DatasetError):
    """A LiDAR scan file cannot be read or holds no valid points."""


class ImageReadError(DatasetError):
    """An image file cannot be read."""


class MeasurementError(LidarcamError):
    """A board could not be measured in one frame (the frame is skipped, with this reason)."""


class AmbiguousBoardError(MeasurementError):
    """Several scan pieces could be the board; ``candidates`` holds their observations for a later choice
    (by agreement with an extrinsic estimated from the unambiguous frames)."""

    def __init__(self, problem: str, candidates: list):
        super().__init__(problem)
        self.candidates = candidates


class AmbiguousOrientationError(MeasurementError):
    """The board's corners fit two tilts of it alike; ``observations`` holds the camera observation of each
    (best first, each with its corner chi-square above the best), for a choice by the laser (2D)."""

    def __init__(self, problem: str, observations: tuple, hint: str | None = None):
        super().__init__(problem, hint=hint)
        self.observations = observations


class DegenerateLayoutError(LidarcamError):
    """The usable frames cannot determine the transform (too few, or normals that do not span 3D)."""


class NoHypothesisError(DegenerateLayoutError):
    """The frames' joint choice of their boards has no extrinsic to test them by (too few frames with a candidate,
    none three of whose normals span 3D, or no minimal solution): a property of the layout, which says nothing
    against the candidates (unlike a choice whose extrinsics no frames agree on)."""


class BagError(LidarcamError):
    """A ROS bag, one of its topics or messages cannot be used (missing topic, unknown encoding, no overlap)."""


class PosteriorSkippedError(LidarcamError):
    """The posterior cannot be sampled (a nearly degenerate problem: directions the data do not determine);
    the calibration goes on with the Laplace covariance and says why."""
