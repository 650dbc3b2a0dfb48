"""Scan readers: every format round-trips; invalid points are dropped; corrupt files give a named error."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.errors import ScanReadError
from estimators.io.pointcloud_io import read_scan, read_scan_2d, write_scan, write_scan_2d


@pytest.fixture
def points():
    return np.random.default_rng(0).uniform(-20, 20, (500, 3)).astype(np.float32).astype(float)


@pytest.mark.parametrize("name,kw", [("a.pcd", {"pcd_encoding": "ascii"}), ("b.pcd", {"pcd_encoding": "binary"}),
                                     ("c.pcd", {"pcd_encoding": "binary_compressed"}), ("d.ply", {}),
                                     ("e.bin", {}), ("f.npy", {})])
def test_round_trip(tmp_path, points, name, kw):
    path = tmp_path / name
    write_scan(path, points, ring=np.arange(len(points)) % 16 if name.endswith(".pcd") else None, **kw)
    np.testing.assert_allclose(read_scan(path), points, atol=1e-4)


def test_pcd_with_extra_fields_nan_and_no_return_points(tmp_path, points):
    from pypcd4 import Encoding, PointCloud

    P = points.astype(np.float32).copy()
    P[:10] = np.nan
    P[10:20] = 0.0
    P[20, 1] = np.inf
    cols = [P[:, 0], P[:, 1], P[:, 2], np.ones(len(P), np.float32), np.arange(len(P), dtype=np.uint16),
            np.zeros(len(P), np.float64)]
    pc = PointCloud.from_points(cols, ["x", "y", "z", "intensity", "ring", "time"],
                                [np.float32, np.float32, np.float32, np.float32, np.uint16, np.float64])
    pc.save(tmp_path / "org.pcd", encoding=Encoding.BINARY_COMPRESSED)
    got = read_scan(tmp_path / "org.pcd")
    assert len(got) == len(P) - 21
    np.testing.assert_allclose(got, P[21:], atol=1e-6)


def test_recorded_pcd_header_is_read(tmp_path):
    text = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity ring\nSIZE 4 4 4 4 2\nTYPE F F F F U\n"
            "COUNT 1 1 1 1 1\nWIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n"
            "1.5 -2.0 0.25 4 0\n0 0 0 0 1\nnan nan nan 0 2\n")
    (tmp_path / "r.pcd").write_text(text)
    np.testing.assert_allclose(read_scan(tmp_path / "r.pcd"), [[1.5, -2.0, 0.25]])


@pytest.mark.parametrize("name,content,match", [
    ("bad.pcd", b"this is not a point cloud", "not a PCD file"),
    ("trunc.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100\nHEIGHT 1\n"
                  b"POINTS 100\nDATA binary\n\x00\x01", "declares 100 points .1200 bytes. but the file holds 2 bytes"),
    ("bad.ply", b"ply\nformat nonsense\n", "not a PLY file"),
    ("bad.bin", b"\x00" * 17, "not a multiple of 16"),
    ("bad.npy", b"\x93NUMPY garbage", "not a plain numeric .npy array"),
    ("scan.xyz", b"1 2 3", "unknown scan format"),
])
def test_corrupt_files_name_the_file(tmp_path, name, content, match):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ScanReadError, match=match) as info:
        read_scan(path)
    assert str(path) in info.value.message and "\n" not in info.value.message


def test_npy_pickles_are_refused_and_shapes_checked(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ScanReadError, match="obj.npy"):
        read_scan(tmp_path / "obj.npy")
    np.save(tmp_path / "flat.npy", np.zeros((5, 2)))
    with pytest.raises(ScanReadError, match="N x >=3"):
        read_scan(tmp_path / "flat.npy")


def test_all_invalid_and_missing(tmp_path):
    np.save(tmp_path / "z.npy", np.zeros((5, 3)))
    with pytest.raises(ScanReadError, match="no valid points"):
        read_scan(tmp_path / "z.npy")
    with pytest.raises(ScanReadError, match="not found"):
        read_scan(tmp_path / "missing.pcd")


def _spinning_sweep(rng: np.random.Generator, beams: int = 16, fov_deg: float = 30.0, height_m: float = 0.0,
                    near_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A spinning LiDAR's returns and their beams: ``beams`` lasers over ``fov_deg`` leaving ``height_m`` above the
    points' origin (an Ouster's 36 mm), every 0.4 degree of azimuth, ranges ``near_m``-25 m."""
    el = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, beams))
    az = np.radians(np.arange(0.0, 360.0, 0.4))
    ring, a = np.repeat(np.arange(beams), len(az)), np.tile(az, beams)
    r = rng.uniform(near_m, 25.0, len(a))
    e = el[ring]
    P = np.column_stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e) + height_m])
    return P, ring


@pytest.mark.parametrize("height_m", [0.0, 0.036])
def test_a_ring_field_that_indexes_beams_is_read(tmp_path, height_m):
    # An Ouster's beams leave 36 mm above its points' origin: from there a near return's elevation drifts by up to
    # a degree along its ring; its ring field still indexes beams.
    from estimators.io.pointcloud_io import read_sweep

    P, ring = _spinning_sweep(np.random.default_rng(1), 64, 33.2, height_m)
    write_scan(tmp_path / "a.pcd", P, ring=ring)
    got = read_sweep(tmp_path / "a.pcd")
    assert got.ring_note is None
    np.testing.assert_array_equal(got.ring, ring)


@pytest.mark.parametrize("kind", ["zeros", "columns"])
def test_a_ring_field_that_does_not_index_beams_is_set_aside(tmp_path, kind):
    # A converter that writes ring 0 for every return, or an index that counts azimuth columns, not lasers: the
    # sweep is read as one without a beam index, and says why.
    from estimators.io.pointcloud_io import read_sweep

    P, ring = _spinning_sweep(np.random.default_rng(2))
    bad = np.zeros_like(ring) if kind == "zeros" else np.tile(np.arange(900), 16) % 16
    write_scan(tmp_path / "a.pcd", P, ring=bad)
    got = read_sweep(tmp_path / "a.pcd")
    assert got.ring is None and "is not one" in got.ring_note
    assert "(1 ring value in all)" in got.ring_note if kind == "zeros" else "(16 ring values in all)" in got.ring_note
    np.testing.assert_allclose(got.points, P, atol=1e-4)


def test_each_rings_elevation_spread_is_numpys_percentile_of_its_returns():
    """The ring check's per-ring quartiles, all rings at once: the same bits as ``np.percentile`` ring by ring
    (groups of 1 to 400 values, ties included)."""
    from estimators.io.pointcloud_io import _sorted_percentiles

    rng = np.random.default_rng(3)
    counts = rng.integers(1, 400, 60)
    groups = [np.sort(np.round(rng.normal(0.0, rng.uniform(0.01, 5.0), c), int(rng.integers(1, 6))))
              for c in counts]
    values, starts = np.concatenate(groups), np.concatenate([[0], np.cumsum(counts)[:-1]])
    for q in (25.0, 75.0, 50.0, 10.0):
        np.testing.assert_array_equal(_sorted_percentiles(values, starts, counts, q),
                                      [np.percentile(g, q) for g in groups])


def test_a_scan_in_millimetres_or_degrees_is_refused_with_its_units_named(tmp_path):
    # An office's returns written in millimetres lie thousands of "metres" away: refused, the units named, where a
    # sweep whose median return lies 100 m off (an open road's) is read.
    rng = np.random.default_rng(3)
    P, _ = _spinning_sweep(rng)
    np.save(tmp_path / "mm.npy", 1000.0 * P)
    with pytest.raises(ScanReadError, match="millimetres") as info:
        read_scan(tmp_path / "mm.npy")
    assert "mm.npy" in info.value.message and "\n" not in info.value.message
    np.save(tmp_path / "far.npy", P * (100.0 / np.median(np.linalg.norm(P, axis=1))))
    assert len(read_scan(tmp_path / "far.npy")) == len(P)
    a = np.linspace(-2.0, 2.0, 500)
    write_scan_2d(tmp_path / "mm.csv", a, np.full(len(a), 4000.0))
    with pytest.raises(ScanReadError, match="millimetres"):
        read_scan_2d(tmp_path / "mm.csv")
    write_scan_2d(tmp_path / "m.csv", a, np.full(len(a), 4.0))
    assert len(read_scan_2d(tmp_path / "m.csv")) == len(a)
    # a 270-degree scanner's angles written in degrees span 270 "radians": refused as such, where a whole turn in
    # radians is read
    write_scan_2d(tmp_path / "deg.csv", np.degrees(a), np.full(len(a), 4.0))
    with pytest.raises(ScanReadError, match="angles in degrees"):
        read_scan_2d(tmp_path / "deg.csv")
    write_scan_2d(tmp_path / "turn.csv", np.linspace(-np.pi, np.pi, 500), np.full(500, 4.0))
    assert len(read_scan_2d(tmp_path / "turn.csv")) == 500
