"""Writing results atomically: a file or a whole folder appears complete, or not at all."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import zipfile
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


def write_npz_atomic(path: str | os.PathLike, arrays: dict, compress: bool = True) -> Path:
    """An ``.npz`` of ``arrays`` (loadable with ``allow_pickle=False``, as ``numpy.savez`` writes it), deflated at
    zlib's fastest level: measurements shrink 2.5 times as at numpy's default level, in a third of the time (a
    six-camera rig's: 5.0 MB against 4.9 MB, 0.3 s against 1.1 s). ``compress=False`` stores them as they are:
    posterior samples, random in every bit below their spread, shrink 4% at any level."""
    def write(fh):
        how = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
        with zipfile.ZipFile(fh, "w", compression=how, compresslevel=1 if compress else None) as z:
            for name, value in arrays.items():
                with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
    return write_atomic(path, write, mode="wb")


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
