"""Each return's beam found from its elevation, for sweeps whose files hold no ring field (lidar.beam_rings)."""
from pathlib import Path

import numpy as np
import pytest

from estimators.errors import ScanReadError
from estimators.lidar.beam_rings import beam_rings
from estimators.lidar.lidar_models import BEAM_MODELS, Rosette

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"


def _agreement(found: np.ndarray, true: np.ndarray) -> tuple[float, bool]:
    """The share of the returns given a beam whose beam is the one the truth's beam maps to, and whether the map
    from found beams to true ones is one to one."""
    given = found >= 0
    mapping, agree = {}, 0
    for k in np.unique(found[given]):
        vals, counts = np.unique(true[found == k], return_counts=True)
        mapping[k] = vals[np.argmax(counts)]
        agree += counts.max()
    return agree / given.sum(), len(set(mapping.values())) == len(mapping)


def _sweep(model: str, height_m: float, radius_m: float, rng: np.random.Generator):
    """A sweep of ``model``'s beams, ranges from 0.8 to 30 m at random (no scene: every range next to every other),
    a third of the returns missing, each beam leaving from ``radius_m`` off the spin axis and ``height_m`` above the
    points' origin (an Ouster's sensor frame: 16 and 36 mm)."""
    d, ring = BEAM_MODELS[model]().directions()
    keep = rng.random(len(d)) < 0.67
    d, ring = d[keep], ring[keep]
    r = rng.uniform(0.8, 30.0, len(d))
    az = np.arctan2(d[:, 1], d[:, 0])
    origin = np.column_stack([radius_m * np.cos(az), radius_m * np.sin(az), np.full(len(d), height_m)])
    return origin + r[:, None] * d, ring


@pytest.mark.parametrize("model", ["vlp16", "os64", "hdl64e"])
@pytest.mark.parametrize("height_m, radius_m", [(0.0, 0.0), (0.036, 0.016)])
def test_every_return_is_given_its_own_beam(model, height_m, radius_m):
    """Every return, near or far, is given a beam, and each found beam is one of the model's, one to one; the beams'
    origin is found to 1 mm."""
    points, ring = _sweep(model, height_m, radius_m, np.random.default_rng(7))
    got = beam_rings(points)
    assert len(got.elevations_deg) == len(np.unique(ring))
    assert np.all(got.ring >= 0)
    share, one_to_one = _agreement(got.ring, ring)
    assert share == 1.0 and one_to_one
    assert abs(got.height_m - height_m) <= 1e-3 and abs(got.radius_m - radius_m) <= 1e-3


def test_a_lidar_without_rings_and_a_turned_sweep_are_refused_in_one_line():
    """A rosette's returns cover its field of view without bands, and a VLP-16's turned 10 degrees in its file (z
    no longer its spin axis) smear its bands into each other: both refused, naming the file and the fix."""
    rng = np.random.default_rng(3)
    d = Rosette().directions(rng)
    rosette = d * rng.uniform(2.0, 30.0, (len(d), 1))
    points, _ = _sweep("vlp16", 0.0, 0.0, rng)
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    turned = points @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    for cloud in (rosette, turned):
        with pytest.raises(ScanReadError) as err:
            beam_rings(cloud, path="sweep.bin")
        assert "do not fall into" in str(err.value) and "sweep.bin" in str(err.value) and "\n" not in str(err.value)
        assert "ring field" in str(err.value)


@pytest.mark.skipif(not REALDATA.is_dir(), reason="the recorded sets (../shared/realdata) are absent")
@pytest.mark.parametrize("name", ["acfr_vlp16_a", "acfr_ouster64_b"])
def test_recorded_sweeps_beams_are_their_ring_fields(name):
    """The recorded VLP-16 and Ouster sweeps with their ring fields set aside: every return is given the beam its
    file says (the Ouster's points lie 36 mm below and 16 mm inside its beams' origin), on three frames of each."""
    from estimators.io.pointcloud_io import read_sweep

    for stem in ("0000", "0005", "0010"):
        sweep = read_sweep(REALDATA / name / f"{stem}.pcd")
        got = beam_rings(sweep.points)
        assert np.all(got.ring >= 0)
        share, one_to_one = _agreement(got.ring, sweep.ring)
        assert share == 1.0 and one_to_one
        assert len(got.elevations_deg) == len(np.unique(sweep.ring))



@pytest.mark.skipif(not REALDATA.is_dir(), reason="the recorded sets (../shared/realdata) are absent")
def test_the_recorded_vlp16_set_as_kitti_bin_is_checked_as_from_its_pcds(tmp_path):
    """The recorded VLP-16 set rewritten as KITTI .bin (x, y, z, intensity): the scene's check of its reference
    extrinsic finds the same contour returns, estimate and p-value as from the PCDs' ring field."""
    import json

    from estimators.io.pointcloud_io import read_sweep, write_scan
    from estimators.pipeline.scene_check import check_scene

    src, kitti = REALDATA / "acfr_vlp16_a", tmp_path / "vlp16"
    kitti.mkdir()
    for f in src.iterdir():
        if f.suffix == ".pcd":
            sweep = read_sweep(f)
            write_scan(kitti / f"{f.stem}.bin", sweep.points, sweep.intensity)
        elif f.is_file():
            (kitti / f.name).symlink_to(f.resolve())
    T = np.array(json.loads((src / "reference.json").read_text())["T_camera_lidar"])
    pcd, bin_ = check_scene(src, T), check_scene(kitti, T)
    assert bin_.skipped == pcd.skipped and bin_.fit.points == pcd.fit.points > 0
    assert np.allclose(bin_.fit.T_camera_lidar, pcd.fit.T_camera_lidar, atol=1e-9)
    assert abs(bin_.test["p_value"] - pcd.test["p_value"]) <= 1e-9 * max(pcd.test["p_value"], 1e-300) + 1e-15


def test_a_dataset_without_ring_fields_is_measured_as_with_them(tmp_path):
    """One simulated 64-beam dataset written with and without its ring field: the ring-less sweeps have their
    beams found over all of them, so every frame's board has the same returns, partitioned into the same rings,
    as with the field (measured by direction bins, one frame's board held two more returns, and the boards' points
    had no rings: the range terms clustered their elevations)."""
    from estimators import measure, simulate

    with_field = measure(simulate(tmp_path / "rings", n_poses=5, seed=11, lidar="os64"))
    without = measure(simulate(tmp_path / "none", n_poses=5, seed=11, lidar="os64", ring_field=False))
    used = [(a, b) for a, b in zip(with_field.frames, without.frames) if a.usable]
    assert len(used) >= 4 and all(b.usable for _, b in used)
    for a, b in used:
        assert np.array_equal(a.lidar.points, b.lidar.points)
        share, one_to_one = _agreement(np.asarray(b.lidar.rings), np.asarray(a.lidar.rings))
        assert share == 1.0 and one_to_one
