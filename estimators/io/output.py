"""Writing results atomically: a file or a whole folder appears complete, or not at all."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..errors import LidarcamError

_UMASK = os.umask(0)
os.umask(_UMASK)


def write_atomic(path: str | os.PathLike, write, mode: str = "w") -> Path:
    """Write ``path`` through ``write(file)`` into a temporary file beside it, then rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            write(fh)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; results are ordinary files
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def write_json_atomic(path: str | os.PathLike, data: object) -> Path:
    def write(fh):
        json.dump(data, fh, indent=1)
        fh.write("\n")
    return write_atomic(path, write)


def write_npz_atomic(path: str | os.PathLike, **arrays) -> Path:
    """A compressed ``.npz`` (loadable with ``allow_pickle=False``)."""
    return write_atomic(path, lambda fh: np.savez_compressed(fh, **arrays), mode="wb")


def check_output_folder(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """``out`` as a folder that may be written (absent, empty, or ``overwrite``); checked before any work."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LidarcamError("exists and is not a folder", path=out, hint="choose another --out")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise LidarcamError("output folder exists and is not empty", path=out,
                            hint="choose another --out or pass --overwrite")
    return out


@contextlib.contextmanager
def atomic_directory(out: str | os.PathLike, overwrite: bool = False):
    """Yield a temporary folder beside ``out``; on success it becomes ``out``, on failure it vanishes."""
    out = check_output_folder(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        yield tmp
        if out.is_dir():
            old = out.with_name(f".{out.name}.old.{os.getpid()}")
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
