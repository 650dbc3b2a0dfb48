"""Opening files that other people's rigs, bags and tarballs produced: regular files only, read within a size
bound, and YAML and JSON parsed with every failure turned into one :class:`LidarcamError` naming the file.

Readers of particular formats (``pointcloud_io``, ``image_io``, ``dataset``, ``export``...) go through these, so
that a directory, a FIFO or a symlink to a device in place of a file, a text file that is not UTF-8, a document
nested thousands deep or a YAML alias bomb is refused in the same words everywhere.
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np

from ..errors import DatasetError, LidarcamError

# Text documents (dataset.yaml, plans, study specs, calibration.json) are small; these bounds are far above
# any real one and far below what would take memory or time to parse.
MAX_TEXT_BYTES = 64 * 1024 * 1024
MAX_YAML_BYTES = 4 * 1024 * 1024
# The number of values a YAML document may expand to once its aliases are followed.
MAX_YAML_NODES = 200_000


def regular_file(path: str | os.PathLike, what: str = "file", error: type[LidarcamError] = DatasetError,
                 hint: str | None = None) -> Path:
    """``path`` when it is (or links to) a regular file; else ``error`` saying what it is instead."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise error(f"{what} not found", path=path, hint=hint or "check the path") from None
    except OSError as exc:
        raise error(f"{what} cannot be opened ({exc.strerror or exc})", path=path,
                    hint=hint or "check its permissions") from None
    if stat.S_ISDIR(mode):
        raise error(f"{what} is a directory", path=path, hint=hint or "give the file itself")
    if not stat.S_ISREG(mode):
        kind = ("a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
        raise error(f"{what} is {kind}, not a regular file", path=path, hint=hint or "give a regular file")
    return path


def read_bytes(path: str | os.PathLike, what: str = "file", max_bytes: int = MAX_TEXT_BYTES,
               error: type[LidarcamError] = DatasetError) -> bytes:
    """The bytes of a regular file no larger than ``max_bytes``."""
    path = regular_file(path, what, error)
    size = path.stat().st_size
    if size > max_bytes:
        raise error(f"{what} is {size} bytes, more than the {max_bytes} bytes such a file can need", path=path,
                    hint="check that this is the right file")
    try:
        with open(path, "rb") as fh:
            # As many bytes as the file had (and one more, so that a file still growing stays bounded):
            # read(n) allocates n bytes first, so n is not the bound of hundreds of MB.
            return fh.read(min(size, max_bytes) + 1)[:max_bytes]
    except OSError as exc:
        raise error(f"{what} cannot be read ({exc.strerror or exc})", path=path, hint="check the file") from None


def read_text(path: str | os.PathLike, what: str = "file", max_bytes: int = MAX_TEXT_BYTES,
              error: type[LidarcamError] = DatasetError) -> str:
    """The UTF-8 text of a regular file no larger than ``max_bytes``."""
    data = read_bytes(path, what, max_bytes, error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} is not UTF-8 text (byte {exc.start})", path=path,
                    hint="save it as UTF-8 text") from None


def _count_nodes(value, limit: int) -> int:
    """Values in ``value`` with aliases expanded, counted without recursion; stops past ``limit``."""
    count, stack = 0, [value]
    while stack and count <= limit:
        v = stack.pop()
        count += 1
        if isinstance(v, dict):
            stack.extend(v.keys())
            stack.extend(v.values())
        elif isinstance(v, (list, tuple, set)):
            stack.extend(v)
    return count


def load_yaml(path: str | os.PathLike, what: str = "YAML file", hint: str = "fix the syntax",
              error: type[LidarcamError] = DatasetError, opencv: bool = False):
    """``yaml.safe_load`` of a regular file (never another loader: no tags that build Python objects), with
    its size, nesting and alias expansion bounded. ``opencv``: OpenCV ``FileStorage``'s YAML read too (its
    ``%YAML:1.0`` line dropped, its ``!!opencv-matrix`` mappings read as plain mappings), in Python rather than by
    OpenCV's parser, which a damaged file can crash."""
    import yaml

    text = read_text(path, what, MAX_YAML_BYTES, error)
    loader = yaml.SafeLoader
    if opencv:
        if text.startswith("%YAML"):
            text = text.split("\n", 1)[1] if "\n" in text else ""
        loader = _OpenCVSafeLoader.get()
    try:
        data = yaml.load(text, Loader=loader)  # noqa: S506 (a SafeLoader, or its subclass with one plain tag)
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()
        raise error(f"invalid YAML ({first[0] if first else type(exc).__name__})", path=path, hint=hint) from None
    except RecursionError:
        raise error("YAML nested too deeply", path=path, hint=hint) from None
    if _count_nodes(data, MAX_YAML_NODES) > MAX_YAML_NODES:
        raise error(f"YAML expands to more than {MAX_YAML_NODES} values (aliases followed)", path=path,
                    hint="write the values out instead of through anchors and aliases") from None
    return data


class _OpenCVSafeLoader:
    """A ``yaml.SafeLoader`` that also reads OpenCV's ``!!opencv-matrix`` as a plain mapping (made on first use)."""

    _loader = None

    @classmethod
    def get(cls):
        if cls._loader is None:
            import yaml

            class Loader(yaml.SafeLoader):
                pass

            Loader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                                   lambda loader, node: loader.construct_mapping(node, deep=True))
            cls._loader = Loader
        return cls._loader


def load_json(path: str | os.PathLike, what: str = "JSON file", hint: str = "check the file",
              error: type[LidarcamError] = DatasetError):
    """``json.loads`` of a regular file, with its size and nesting bounded."""
    text = read_text(path, what, MAX_TEXT_BYTES, error)
    try:
        return json.loads(text)
    except ValueError as exc:
        raise error(f"not valid JSON ({exc})", path=path, hint=hint) from None
    except RecursionError:
        raise error("JSON nested too deeply", path=path, hint=hint) from None


def load_npz(npz: Path) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` (never pickles), each member's declared shape checked against the member's
    size before it is read, and the members' total against the archive's length: a lying header allocates
    nothing."""
    import zipfile

    size = npz.stat().st_size
    with zipfile.ZipFile(npz) as zf:
        infos = zf.infolist()
        if sum(i.file_size for i in infos) > 100 * max(size, 1):
            raise ValueError("its members claim far more data than the archive holds")
        for info in infos:
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                shape, _, dtype = (np.lib.format.read_array_header_1_0(fh) if version == (1, 0) else
                                   np.lib.format.read_array_header_2_0(fh))
                if dtype.hasobject or int(np.prod(shape, dtype=object)) * dtype.itemsize > info.file_size:
                    raise ValueError(f"member {info.filename} declares {shape} {dtype}, more than it holds")
    with np.load(npz, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
