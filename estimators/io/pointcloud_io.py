"""Reading and writing LiDAR scans: PCD (ascii, binary, binary_compressed), PLY, KITTI .bin, .npy.

Every reader returns an (N, 3) float64 array of finite points with the no-return (0, 0, 0) points
of organised clouds removed.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ScanReadError
from .input_files import regular_file

SCAN_SUFFIXES = (".pcd", ".ply", ".bin", ".npy")
SCAN_2D_SUFFIXES = (".csv", ".npy", ".pcd")
# Returns outside these ranges are invalid in a 2D scan (no-return codes, the sensor's own housing).
MIN_RANGE_2D_M, MAX_RANGE_2D_M = 0.02, 80.0
# A beam index (a ring field, an organised cloud's rows) is read only if it indexes beams: the returns this far from
# the spin axis (m) or more lie, ring by ring, in narrow bands of elevation. Where most of them (``MAX_WIDE_SHARE``)
# lie in rings whose central half spans more than ``MAX_RING_IQR_DEG`` (a converter that writes 0 for every return,
# an organised cloud stored by columns), the index is set aside and the sweep read as one without it. A true ring's
# central half spans under 0.1 degree on the recorded sets (0.9 degree at 2 m for an Ouster, whose beams leave 36 mm
# above its points' origin); the 16-128 beams' spacing is 0.1-2 degrees, a sweep's whole span 20-45 degrees.
RING_CHECK_RHO_M, MAX_RING_IQR_DEG, MAX_WIDE_SHARE, MIN_RING_CHECK = 2.0, 2.0, 0.5, 200
# A sweep whose median return lies farther than this (m) is not in metres in its LiDAR's frame: the longest-reaching
# LiDARs range to 200-500 m, and a sweep's median return lies far nearer (2-30 m on the recorded sets). Millimetres
# (or centimetres) put an office's returns thousands of metres away, and so does a map's frame.
MAX_MEDIAN_RANGE_M = 300.0
# A scan whose every return lies within this (m) of z = 0 is a 2D scanner's line (a z = 0 PCD as ROS tools save it).
SCAN_LINE_Z_M = 1e-3


def read_scan(path: str | os.PathLike) -> np.ndarray:
    """Load a scan as (N, 3) metres in the LiDAR frame, dropping NaN/inf and (0, 0, 0) returns."""
    return read_sweep(path).points


@dataclass(frozen=True, eq=False)
class Sweep:
    """A 3D scan's valid points and, when the file tells it, each point's beam (laser) index: the ``ring``
    field, or the row of an organised cloud. ``ring`` is None for an unorganised cloud without one;
    ``intensity`` None for a file without an intensity (reflectivity) field. ``ring_note``: why the file's beam
    index was set aside (it does not index beams, :func:`ring_field_problem`), or None."""

    points: np.ndarray
    ring: np.ndarray | None = None
    intensity: np.ndarray | None = None
    ring_note: str | None = None

    def kept(self, keep: np.ndarray) -> "Sweep":
        """The sweep's returns where ``keep`` (a mask or indices), with their beams and intensities."""
        return Sweep(self.points[keep], None if self.ring is None else self.ring[keep],
                     None if self.intensity is None else self.intensity[keep], self.ring_note)


def _sorted_percentiles(values: np.ndarray, starts: np.ndarray, counts: np.ndarray, q: float) -> np.ndarray:
    """``np.percentile(group, q)`` of each group ``values[start:start + count]`` (each sorted ascending) at once:
    numpy's linear interpolation, in its own arithmetic (the same bits)."""
    v = (counts - 1) * (q / 100)
    lo = np.floor(v)
    t = v - lo
    i = starts + lo.astype(int)
    a, b = values[i], values[np.minimum(i + 1, starts + counts - 1)]
    d = b - a
    return np.where(t >= 0.5, b - d * (1 - t), a + d * t)


def ring_field_problem(points: np.ndarray, ring: np.ndarray) -> str | None:
    """Why ``ring`` (each return's beam index, as its file gives it) does not index the beams of a spinning LiDAR
    (the constants above), or None where it does or too few far returns tell."""
    rho = np.hypot(points[:, 0], points[:, 1])
    far = rho >= RING_CHECK_RHO_M
    if np.count_nonzero(far) < MIN_RING_CHECK:
        return None
    el = np.degrees(np.arctan2(points[far, 2], rho[far]))
    values, inverse, counts = np.unique(ring[far], return_inverse=True, return_counts=True)
    # each ring's elevations, ascending: sorted by elevation, then stably by ring (a radix sort on small integers;
    # five times faster than lexsort on a sweep, with the same values in the same places)
    order = np.argsort(el)
    by_ring = el[order[np.argsort(inverse[order].astype(np.uint16 if len(values) < 2**16 else np.int64),
                                  kind="stable")]]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    iqr = _sorted_percentiles(by_ring, starts, counts, 75.0) - _sorted_percentiles(by_ring, starts, counts, 25.0)
    wide = int(counts[iqr > MAX_RING_IQR_DEG].sum())
    if wide <= MAX_WIDE_SHARE * len(el):
        return None
    return (f"its beam index (ring field or organised rows) is not one: {wide / len(el):.0%} of the returns beyond "
            f"{RING_CHECK_RHO_M:g} m lie in rings spanning more than {MAX_RING_IQR_DEG:g} degrees of elevation "
            f"({len(values)} ring value{'s' if len(values) > 1 else ''} in all)")


def read_sweep(path: str | os.PathLike) -> Sweep:
    """Load a scan's valid points (NaN/inf and (0, 0, 0) returns dropped) with their beam index if known."""
    path = regular_file(path, "scan file", ScanReadError, "check the dataset folder")
    suffix = path.suffix.lower()
    readers = {".pcd": _read_pcd, ".ply": _read_ply, ".bin": _read_kitti_bin, ".npy": _read_npy}
    if suffix not in readers:
        raise ScanReadError(f"unknown scan format {suffix!r}", path=path,
                            hint=f"use one of {', '.join(SCAN_SUFFIXES)}")
    try:
        xyz, ring, intensity = readers[suffix](path, rings=True)
    except ScanReadError:
        raise
    except Exception as exc:  # the readers raise many kinds on corrupt input; name the file instead
        raise ScanReadError(f"corrupt or unreadable {suffix[1:].upper()} file ({type(exc).__name__}: "
                            f"{_first_line(exc)})", path=path, hint="re-export the scan") from exc
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    keep = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0.0, axis=1)
    xyz = xyz[keep]
    if len(xyz) == 0:
        raise ScanReadError("scan holds no valid points (all NaN, inf or zero)", path=path,
                            hint="check the recording")
    with np.errstate(over="ignore"):  # a corrupt file's 1e308 is infinitely far, and refused as far
        _in_metres(np.linalg.norm(xyz, axis=1), MAX_MEDIAN_RANGE_M, path)
    if ring is not None:
        ring = np.asarray(ring).reshape(-1)
        ring = ring[keep].astype(np.int64) if len(ring) == len(keep) and np.all(np.isfinite(ring)) else None
    note = None if ring is None else ring_field_problem(xyz, ring)
    if note is not None:
        ring = None
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=float).reshape(-1)
        intensity = intensity[keep] if len(intensity) == len(keep) else None
        if intensity is not None and not np.all(np.isfinite(intensity)):
            intensity = None
    return Sweep(xyz, ring, intensity, note)


def read_scan_2d(path: str | os.PathLike, min_range_m: float = MIN_RANGE_2D_M,
                 max_range_m: float = MAX_RANGE_2D_M) -> np.ndarray:
    """Load a single-line scan as (N, 2) metres in its scan plane (the LiDAR's x-y plane).

    Formats: ``.csv`` with a header ``angle,range`` (radians, metres) or ``x,y`` (metres); ``.npy``
    (N x 2, or N x 3 with z = 0); ``.pcd`` with z = 0 (as ROS tools save scans). Non-finite, zero and
    out-of-range returns are dropped.
    """
    path = regular_file(path, "scan file", ScanReadError, "check the dataset folder")
    suffix = path.suffix.lower()
    if suffix not in SCAN_2D_SUFFIXES:
        raise ScanReadError(f"unknown 2D scan format {suffix!r}", path=path,
                            hint=f"use one of {', '.join(SCAN_2D_SUFFIXES)}")
    try:
        if suffix == ".csv":
            xy = _read_csv_2d(path)
        elif suffix == ".npy":
            a = load_npy(path)
            if a.ndim != 2 or a.shape[1] not in (2, 3) or a.dtype.kind not in "fiu":
                raise ScanReadError(f"expected a numeric N x 2 (or N x 3) array, got shape {a.shape} dtype {a.dtype}",
                                    path=path, hint="save the scan's x, y as two columns")
            xy = _planar(a.astype(float), path)
        else:
            xy = _planar(_read_pcd(path), path)
    except ScanReadError:
        raise
    except Exception as exc:
        raise ScanReadError(f"corrupt or unreadable {suffix[1:].upper()} file ({type(exc).__name__}: "
                            f"{_first_line(exc)})", path=path, hint="re-export the scan") from exc
    r = np.linalg.norm(xy, axis=1)
    keep = np.all(np.isfinite(xy), axis=1) & (r >= min_range_m) & (r <= max_range_m)
    if np.count_nonzero(keep) < 0.05 * len(r):  # hardly a return within reach: are they in metres?
        _in_metres(r[np.isfinite(r) & (r > 0)], max_range_m, path)
    if not keep.any():
        raise ScanReadError("scan holds no valid returns (all NaN, zero or out of range)", path=path,
                            hint="check the recording")
    return xy[keep]


def _in_metres(ranges: np.ndarray, farthest_m: float, path: Path) -> None:
    """Refuse a scan whose returns' median range lies beyond ``farthest_m``: not metres in the LiDAR's frame."""
    median = float(np.median(ranges)) if ranges.size else 0.0
    if median > farthest_m:
        raise ScanReadError(f"its returns lie a median {median:,.0f} m from the LiDAR, where a "
                            f"scan's lie within {farthest_m:g} m: points in millimetres, or in another frame than "
                            "the LiDAR's", path=path, hint="write the points in metres in the LiDAR's own frame")


def _planar(xyz: np.ndarray, path: Path) -> np.ndarray:
    if xyz.shape[1] == 3:
        z = np.abs(xyz[:, 2][np.isfinite(xyz[:, 2])])
        if z.size and z.max() > SCAN_LINE_Z_M:
            raise ScanReadError(f"not a 2D scan: z reaches {z.max():.3f} m", path=path,
                                hint="use lidar: 3d for a 3D LiDAR, or save the scan plane's x, y")
    return xyz[:, :2]


def _read_csv_2d(path: Path) -> np.ndarray:
    with open(path, encoding="utf-8") as fh:
        header = [h.strip().lower() for h in fh.readline().split(",")]
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.size == 0:
        return np.zeros((0, 2))
    cols = {name: i for i, name in enumerate(header)}
    if {"angle", "range"} <= cols.keys():
        a, r = data[:, cols["angle"]], data[:, cols["range"]]
        span = np.ptp(a[np.isfinite(a)]) if np.isfinite(a).any() else 0.0
        if span > 2 * np.pi + 0.01:  # a turn at most in radians: a 270-degree scanner's in degrees spans 270
            raise ScanReadError(f"its angles span {span:.4g}, more than a turn in radians: angles in degrees?",
                                path=path, hint="write the angle column in radians")
        with np.errstate(invalid="ignore", over="ignore"):  # an infinite range (no return) is dropped, not warned of
            return np.column_stack([r * np.cos(a), r * np.sin(a)])
    if {"x", "y"} <= cols.keys():
        return data[:, [cols["x"], cols["y"]]]
    raise ScanReadError(f"CSV header {','.join(header)!r} has neither angle,range nor x,y", path=path,
                        hint="write a header line: angle,range (radians, metres) or x,y (metres)")


def write_scan_2d(path: str | os.PathLike, angles: np.ndarray, ranges: np.ndarray) -> None:
    """Write a 2D scan as ``angle,range`` CSV (invalid returns as range 0), ``.npy`` or z = 0 ``.pcd``."""
    path = Path(path)
    a, r = np.asarray(angles, dtype=float), np.asarray(ranges, dtype=float)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        np.savetxt(path, np.column_stack([a, r]), delimiter=",", header="angle,range", comments="", fmt="%.6f")
    elif suffix in (".npy", ".pcd"):
        xy = np.column_stack([r * np.cos(a), r * np.sin(a)])
        if suffix == ".npy":
            np.save(path, xy)
        else:
            write_scan(path, np.column_stack([xy, np.zeros(len(xy))]))
    else:
        raise ValueError(f"Expected a 2D scan suffix in {SCAN_2D_SUFFIXES}, got {suffix!r}")


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:160] if text else "no detail"


# Far above any LiDAR sweep (a 128-beam sensor gives about 260,000 points), far below what exhausts memory.
MAX_SCAN_POINTS = 20_000_000
_PCD_TYPES = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}


def _pcd_header(path: Path) -> tuple[str, int, int, int]:
    """The PCD header checked against itself and against the file: ``(data, points, point_bytes,
    data_offset)``. Nothing is allocated from a count before it is checked against the file's length."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(min(size, 65536))
    keys, offset = {}, 0
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        line = raw.decode("ascii", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        key, _, value = line.partition(" ")
        keys[key.upper()] = value.split()
        if key.upper() == "DATA":
            break
    else:
        raise ScanReadError("not a PCD file (no DATA line in its header)", path=path, hint="re-export the scan")
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA") if k not in keys]
    if missing:
        raise ScanReadError(f"PCD header lacks {', '.join(missing)}", path=path, hint="re-export the scan")
    fields, n = keys["FIELDS"], len(keys["FIELDS"])
    try:
        sizes = [int(v) for v in keys["SIZE"]]
        counts = [int(v) for v in keys.get("COUNT", ["1"] * n)]
        width, height = int(keys["WIDTH"][0]), int(keys["HEIGHT"][0])
        points = int(keys["POINTS"][0]) if "POINTS" in keys else width * height
    except (ValueError, IndexError):
        raise ScanReadError("PCD header has a non-integer SIZE, COUNT, WIDTH, HEIGHT or POINTS", path=path,
                            hint="re-export the scan") from None
    types = [t.upper() for t in keys["TYPE"]]
    if not (len(sizes) == len(types) == len(counts) == n) or n == 0:
        raise ScanReadError(f"PCD header lists {n} FIELDS but {len(sizes)} SIZE, {len(types)} TYPE and "
                            f"{len(counts)} COUNT values", path=path, hint="re-export the scan")
    if any((t, z) not in _PCD_TYPES for t, z in zip(types, sizes)) or any(c < 1 or c > 4096 for c in counts):
        raise ScanReadError(f"PCD header has an unknown TYPE/SIZE/COUNT ({' '.join(types)} / "
                            f"{' '.join(map(str, sizes))} / {' '.join(map(str, counts))})", path=path,
                            hint="re-export the scan")
    if width < 0 or height < 0 or points < 0 or points != width * height:
        raise ScanReadError(f"PCD header says POINTS {points} but WIDTH x HEIGHT = {width} x {height}", path=path,
                            hint="the header is damaged; re-export the scan")
    if points > MAX_SCAN_POINTS:
        raise ScanReadError(f"PCD header declares {points} points (at most {MAX_SCAN_POINTS} are read)", path=path,
                            hint="the header is damaged or this is not one sweep")
    data = keys["DATA"][0].lower() if keys["DATA"] else ""
    point_bytes = sum(z * c for z, c in zip(sizes, counts))
    remaining = size - offset
    if data == "binary":
        if remaining < points * point_bytes:
            raise ScanReadError(f"PCD header declares {points} points ({points * point_bytes} bytes) but the file "
                                f"holds {max(remaining, 0)} bytes of data", path=path,
                                hint="the file is truncated; re-export the scan")
    elif data == "binary_compressed":
        with open(path, "rb") as fh:
            fh.seek(offset)
            sizes8 = fh.read(8)
        if len(sizes8) < 8:
            raise ScanReadError("PCD binary_compressed data is cut off before its sizes", path=path,
                                hint="the file is truncated; re-export the scan")
        compressed, uncompressed = np.frombuffer(sizes8, "<u4").tolist()
        if uncompressed != points * point_bytes or compressed > remaining - 8:
            raise ScanReadError(f"PCD binary_compressed sizes ({compressed} compressed, {uncompressed} "
                                f"uncompressed) disagree with the header ({points} points of {point_bytes} "
                                f"bytes) or the file ({remaining - 8} bytes of data)", path=path,
                                hint="the file is truncated or damaged; re-export the scan")
    elif data == "ascii":
        if remaining < 2 * points:  # every point takes at least one digit and a line end
            raise ScanReadError(f"PCD header declares {points} points but the file holds {max(remaining, 0)} "
                                "bytes of ASCII data", path=path, hint="the file is truncated; re-export the scan")
    else:
        raise ScanReadError(f"PCD DATA {data!r} is not ascii, binary or binary_compressed", path=path,
                            hint="re-export the scan")
    if not {"x", "y", "z"} <= set(fields):
        missing_xyz = [f for f in ("x", "y", "z") if f not in fields]
        raise ScanReadError(f"PCD has no field(s) {', '.join(missing_xyz)} (fields: {' '.join(fields)})",
                            path=path, hint="save x, y and z")
    return data, points, point_bytes, offset


def _read_pcd(path: Path, rings: bool = False):
    from pypcd4 import PointCloud

    data, points, _, _ = _pcd_header(path)
    pc = PointCloud.from_path(path)
    xyz = pc.numpy(("x", "y", "z"))
    if len(xyz) != points:
        raise ScanReadError(f"PCD header declares {points} points but its {data} data holds {len(xyz)}",
                            path=path, hint="the header and the data disagree; re-export the scan")
    if not rings:
        return xyz
    intensity = pc.numpy(("intensity",))[:, 0] if "intensity" in pc.fields else None
    if "ring" in pc.fields:
        return xyz, pc.numpy(("ring",))[:, 0], intensity
    height = int(pc.metadata.height)
    if height > 1 and height * int(pc.metadata.width) == len(xyz):  # organised: one row per beam
        return xyz, np.repeat(np.arange(height), int(pc.metadata.width)), intensity
    return xyz, None, intensity


_PLY_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_ply_header(path: Path) -> None:
    """The PLY header's element counts checked against the file's length before anything is read (the
    reader would allocate what the header claims)."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(min(size, 65536))
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ScanReadError("not a PLY file (no 'ply' ... 'end_header' header)", path=path, hint="re-export the scan")
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    data_start = end + len(b"end_header") + 1
    fmt, elements = "", []
    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append([words[1], int(words[2]), 0])
            except ValueError:
                raise ScanReadError(f"PLY element {words[1]!r} has a non-integer count", path=path,
                                    hint="the header is damaged; re-export the scan") from None
        elif words[0] == "property" and elements and len(words) >= 3:
            # a list property takes at least its count's bytes
            elements[-1][2] += _PLY_BYTES.get(words[2] if words[1] == "list" else words[1], 1)
    total = 0
    for name, count, row in elements:
        if count < 0 or count > MAX_SCAN_POINTS:
            raise ScanReadError(f"PLY header declares {count} {name} elements (at most {MAX_SCAN_POINTS} are read)",
                                path=path, hint="the header is damaged or this is not one sweep")
        total += count * (max(row, 1) if fmt.startswith("binary") else 2)
    if total > size - data_start:
        raise ScanReadError(f"PLY header declares {sum(e[1] for e in elements)} elements (at least {total} bytes) "
                            f"but the file holds {max(size - data_start, 0)} bytes of data", path=path,
                            hint="the file is truncated or its header is damaged; re-export the scan")


def _read_ply(path: Path, rings: bool = False):
    from plyfile import PlyData

    _check_ply_header(path)
    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise ScanReadError("PLY has no vertex element", path=path, hint="save the points as vertices")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    missing = [f for f in ("x", "y", "z") if f not in names]
    if missing:
        raise ScanReadError(f"PLY vertices have no {', '.join(missing)}", path=path, hint="save x, y and z")
    xyz = np.column_stack([v["x"], v["y"], v["z"]])
    if not rings:
        return xyz
    return (xyz, np.asarray(v["ring"]) if "ring" in names else None,
            np.asarray(v["intensity"]) if "intensity" in names else None)


def _read_kitti_bin(path: Path, rings: bool = False):
    size = path.stat().st_size
    if size == 0 or size % 16:
        raise ScanReadError(f"KITTI .bin size {size} bytes is not a multiple of 16 (float32 x, y, z, i)",
                            path=path, hint="the file is truncated or not a KITTI scan")
    data = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    return (data[:, :3], None, data[:, 3]) if rings else data[:, :3]


def load_npy(path: Path) -> np.ndarray:
    """A ``.npy`` array, never a pickle, its declared size checked against the file's length first (memory
    mapped, then copied: what is allocated is what the file holds)."""
    try:
        a = np.load(path, allow_pickle=False, mmap_mode="r")
    except ValueError as exc:
        raise ScanReadError(f"not a plain numeric .npy array ({_first_line(exc)})", path=path,
                            hint="save it with numpy.save, without pickling") from None
    if a.size > 4 * MAX_SCAN_POINTS:
        raise ScanReadError(f".npy array of shape {a.shape} is too large for a scan", path=path,
                            hint="save one sweep per file")
    return np.array(a)


def _read_npy(path: Path, rings: bool = False):
    a = load_npy(path)
    if a.ndim != 2 or a.shape[1] < 3 or a.dtype.kind not in "fiu":
        raise ScanReadError(f"expected a numeric N x >=3 array, got shape {a.shape} dtype {a.dtype}",
                            path=path, hint="save x, y, z as the first three columns")
    return (a[:, :3], None, a[:, 3] if a.shape[1] >= 4 else None) if rings else a[:, :3]


def write_scan(path: str | os.PathLike, points: np.ndarray, intensity: np.ndarray | None = None,
               ring: np.ndarray | None = None, pcd_encoding: str = "binary") -> None:
    """Write (N, 3) points in the format named by the suffix, with their intensities and beams (``ring``: kept by
    PCD and PLY) where given (the simulator, the bags' extraction, tests)."""
    path = Path(path)
    P = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    inten = np.zeros(len(P), np.float32) if intensity is None else np.asarray(intensity, np.float32)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        from pypcd4 import Encoding, PointCloud

        cols = [P[:, 0], P[:, 1], P[:, 2], inten]
        fields, types = ["x", "y", "z", "intensity"], [np.float32] * 4
        if ring is not None:
            cols.append(np.asarray(ring, np.uint16))
            fields.append("ring")
            types.append(np.uint16)
        pc = PointCloud.from_points(cols, fields, types)
        pc.save(path, encoding=Encoding(pcd_encoding))
    elif suffix == ".ply":
        from plyfile import PlyData, PlyElement

        v = np.empty(len(P), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")]
                     + ([] if ring is None else [("ring", "u2")]))
        v["x"], v["y"], v["z"], v["intensity"] = P[:, 0], P[:, 1], P[:, 2], inten
        if ring is not None:
            v["ring"] = ring
        PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    elif suffix == ".bin":
        np.column_stack([P, inten]).astype("<f4").tofile(path)
    elif suffix == ".npy":
        np.save(path, P.astype(np.float64))
    else:
        raise ValueError(f"Expected a scan suffix in {SCAN_SUFFIXES}, got {suffix!r}")
