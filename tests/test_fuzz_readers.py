"""Every reader fuzzed (issue 20): malformed and hostile inputs give a LidarcamError naming the file, never another
exception. A bounded run here (hypothesis, fixed derandomised seed); the long run is benchmarks/bench_fuzz.py.

Also: special files in place of regular ones, YAML tags, nesting and alias bombs, the two reported cases (a PNG
declaring gigapixels, an ASCII PCD whose header claims more points than it holds), a damaged frame skipped with
its reason while the rest calibrate, and every CLI command refusing a malformed argument file in one line."""
from __future__ import annotations

import os
import resource
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from estimators.calibration import calibrate_pair
from estimators.cli import main
from estimators.errors import LidarcamError
from estimators.io.dataset import load_dataset
from estimators.io.image_io import read_gray, to_gray8
from estimators.io.input_files import load_yaml
from estimators.io.pointcloud_io import read_sweep

from .fuzz_targets import FILE_TARGETS, MESSAGE_TARGETS, mutate, mutations

# Cases per target in `make test` (the long run tries 10,000 per reader).
EXAMPLES = 40
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _only_lidarcam_errors(read, path: Path, check=None) -> None:
    try:
        out = read(path)
    except LidarcamError as exc:
        assert "\n" not in exc.message, exc.message
        return
    if check is not None:
        check(out)


@pytest.mark.parametrize("target", FILE_TARGETS, ids=[t.name for t in FILE_TARGETS])
def test_mutated_files_read_or_raise_a_lidarcam_error(target, tmp_path_factory):
    folder = tmp_path_factory.mktemp(target.name)
    seed = target.seed(folder)
    seed_path = folder / f"seed{target.suffix}"
    seed_path.write_bytes(seed)
    target.read(seed_path)  # the seed itself is well-formed

    @FUZZ
    @given(ops=mutations())
    def run(ops):
        path = folder / f"case{target.suffix}"
        path.write_bytes(mutate(seed, ops))
        _only_lidarcam_errors(target.read, path, target.check)

    run()


@pytest.mark.parametrize("name,strategy,decode", MESSAGE_TARGETS, ids=[m[0] for m in MESSAGE_TARGETS])
def test_malformed_ros_messages_raise_bag_errors(name, strategy, decode):
    @FUZZ
    @given(msg=strategy())
    def run(msg):
        try:
            decode(msg)
        except LidarcamError as exc:
            assert "\n" not in exc.message

    run()


# --- special files -------------------------------------------------------------------------------------------

def _specials(tmp_path: Path) -> dict[str, Path]:
    d = tmp_path / "dir.pcd"
    d.mkdir()
    fifo = tmp_path / "fifo.pcd"
    os.mkfifo(fifo)
    dev = tmp_path / "zero.pcd"
    dev.symlink_to("/dev/zero")
    empty = tmp_path / "empty.pcd"
    empty.write_bytes(b"")
    dangling = tmp_path / "dangling.pcd"
    dangling.symlink_to(tmp_path / "nowhere")
    return {"a directory": d, "a FIFO": fifo, "a device": dev, "empty": empty, "not found": dangling}


@pytest.mark.parametrize("reader", [read_sweep, read_gray, lambda p: load_yaml(p)], ids=["scan", "image", "yaml"])
def test_directories_fifos_devices_and_empty_files_are_refused_without_blocking(reader, tmp_path):
    """A FIFO would block a reader that opened it and /dev/zero never ends: neither is opened."""
    for kind, path in _specials(tmp_path).items():
        if kind == "empty" and reader not in (read_sweep, read_gray):
            continue  # an empty YAML document is valid (None); its callers refuse what is not a mapping
        with pytest.raises(LidarcamError) as info:
            reader(path)
        assert str(path) in info.value.message, (kind, info.value.message)
        if kind not in ("empty",):
            assert kind.split()[-1] in info.value.message or "not found" in info.value.message, info.value.message


@pytest.mark.parametrize("text,match", [
    ("a: !!python/object/apply:os.system ['true']\n", "invalid YAML"),
    ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply|invalid YAML"),
    ("a: &a [1, 2, 3, 4, 5, 6, 7, 8, 9]\n" + "".join(
        f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9) + "]\n" for p, c in zip("abcdefgh", "bcdefghi")), "expands to more"),
    ("\xff\xfe bad", "not UTF-8"),
])
def test_hostile_yaml_is_refused(tmp_path, text, match):
    path = tmp_path / "dataset.yaml"
    path.write_bytes(text.encode("latin-1") if "\xff" in text else text.encode())
    with pytest.raises(LidarcamError, match=match):
        load_yaml(path)


# --- the two reported cases ----------------------------------------------------------------------------------

def _png_header_only(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + \
        chunk(b"IEND", b"")


def test_png_declaring_gigapixels_is_refused_before_decoding(tmp_path):
    path = tmp_path / "huge.png"
    path.write_bytes(_png_header_only(60000, 60000))
    with pytest.raises(LidarcamError, match="declares|more than") as info:
        read_gray(path)
    assert str(path) in info.value.message


def test_png_chunk_claiming_gigabytes_is_refused_before_decoding(tmp_path):
    # The long fuzz run found it: OpenCV's PNG reader allocates a chunk's declared length before reading
    # it, so one damaged length word of an 800-byte file cost 4 GB.
    ok, buf = cv2.imencode(".png", np.arange(24 * 32, dtype=np.uint8).reshape(24, 32))
    honest = tmp_path / "honest.png"
    honest.write_bytes(buf.tobytes())
    assert read_gray(honest).shape == (24, 32)
    data = bytearray(buf.tobytes())
    idat = data.index(b"IDAT") - 4
    data[idat:idat + 4] = (4_000_000_000).to_bytes(4, "big")
    path = tmp_path / "lying_chunk.png"
    path.write_bytes(bytes(data))
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(LidarcamError, match="chunk IDAT declares 4000000000 bytes") as info:
        read_gray(path)
    assert str(path) in info.value.message
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before < 100_000  # kB: nothing allocated


def test_a_plan_whose_board_is_out_of_reach_is_refused_and_a_far_one_analysed(tmp_path):
    # The long fuzz run found it: a pose 2^31 m away made the board-pose information singular (LinAlgError).
    import yaml

    from estimators.analysis.layout_analysis import analyse, layout_from_plan

    from .fuzz_targets import _plan_yaml

    plan = yaml.safe_load(_plan_yaml())
    plan["poses"][-1]["centre_m"][2] = 2**31
    with pytest.raises(LidarcamError, match="centre_m must be within 1000 m"):
        layout_from_plan(plan, str(tmp_path / "PLAN.yaml"))
    plan["poses"][-1]["centre_m"][2] = 999.0  # within reach, but its squares span a fraction of a pixel
    with pytest.raises(LidarcamError, match="px in the image"):
        layout_from_plan(plan, str(tmp_path / "PLAN.yaml"))
    plan["poses"][-1]["centre_m"][2] = 10.0  # far, still found: it adds little, and nothing singular
    analysis = analyse(layout_from_plan(plan, "PLAN.yaml")[0])
    assert np.all(np.isfinite(analysis.covariance)) and np.linalg.eigvalsh(analysis.covariance)[0] > 0


def test_16_bit_images_are_scaled_to_8_bits_by_their_range_without_a_wide_copy():
    # min -> 0, max -> 255, linear between (OpenCV rounds); the long fuzz run's 1 GB bound depends on the
    # conversion not making a float64 copy of a 64-megapixel 16-bit image (512 MB).
    img = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000 + 500)
    expected = np.rint(255 * (img.astype(float) - 500) / 11000).astype(np.uint8)
    out = to_gray8(img)
    assert out.dtype == np.uint8 and np.array_equal(out, expected)
    colour = np.stack([img, img, img], axis=2)
    assert np.array_equal(to_gray8(colour), expected)


def test_ascii_pcd_claiming_more_points_than_it_holds_is_an_error(tmp_path):
    rows = "".join(f"{k}.0 1.0 2.0\n" for k in range(1, 6))
    head = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\n"
            "DATA ascii\n")
    path = tmp_path / "lying.pcd"
    path.write_text(head.format(n=500) + rows)
    with pytest.raises(LidarcamError, match="declares 500 points"):
        read_sweep(path)
    path.write_text(head.format(n=5) + rows)
    assert len(read_sweep(path).points) == 5


# --- a damaged frame among good ones -------------------------------------------------------------------------

def test_a_damaged_image_and_a_damaged_scan_skip_their_frames_and_the_rest_calibrate(sim_vlp16, tmp_path):
    import shutil

    ds_path = tmp_path / "ds"
    shutil.copytree(sim_vlp16, ds_path)
    frames = load_dataset(ds_path).frames
    frames[0].image.write_bytes(_png_header_only(60000, 60000))
    data = frames[1].scan.read_bytes()
    frames[1].scan.write_bytes(data[: len(data) // 2])
    # another frame's image of another size than the camera entry
    import cv2

    img = cv2.imread(str(frames[2].image), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(frames[2].image), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))
    result = calibrate_pair(load_dataset(ds_path), posterior=None, rng=np.random.default_rng(0))
    reasons = {f.name: f.reason for f in result.frames}
    assert "image header declares" in reasons[frames[0].name]
    assert "scan:" in reasons[frames[1].name] and "truncated" in reasons[frames[1].name]
    assert "another resolution" in reasons[frames[2].name]
    assert result.frames_used == len(frames) - 3


# --- every CLI command refuses a malformed argument file -----------------------------------------------------

COMMANDS = {
    "calibrate": lambda f, out: ["calibrate", str(f.parent), "--out", str(out)],
    "initial-guess": lambda f, out: ["calibrate", str(f.parent), "--out", str(out), "--initial-guess", str(f)],
    "layout": lambda f, out: ["layout", str(f), "--json", str(out / "layout.json")],
    "study": lambda f, out: ["study", str(f), "--out", str(out)],
    "extract": lambda f, out: ["extract", str(f), "--board", "9x7:0.1", "--out", str(out), "--image-topic", "/a",
                               "--cloud-topic", "/b"],
    "export": lambda f, out: ["export", str(f), "--format", "urdf", "--out", str(out / "x.urdf")],
    "validate": lambda f, out: ["validate", str(f.parent), "--calibration", str(f), "--out", str(out)],
    "simulate": lambda f, out: ["simulate", "--out", str(f)],  # a file where the dataset folder would go
}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("content", [b"{\x00\xff: [", b"", b"a: &a [*a, *a]\nb: [*a, *a]\n",
                                     b"- - - -\n  x: !!binary AAAA\n"],
                         ids=["garbage", "empty", "alias", "wrong-types"])
def test_every_command_turns_a_malformed_file_into_one_line_and_exit_2(command, content, tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    f = folder / ("dataset.yaml" if command == "calibrate" else "plan.yaml" if command in ("layout", "study") else
                  "calibration.json" if command in ("export", "validate", "initial-guess") else "rig.bag")
    f.write_bytes(content)
    if command in ("initial-guess", "validate"):  # a well-formed dataset beside it: the argument file fails
        from .fuzz_targets import _dataset_yaml

        (folder / "dataset.yaml").write_bytes(_dataset_yaml())
        for name in ("0000.png", "0000.pcd"):
            (folder / name).touch()
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(COMMANDS[command](f, out)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lidarcam: error:") and "\n" not in err, err
    assert not out.exists()
    assert f.read_bytes() == content


def test_measurements_files_fuzzed(sim_vlp16, tmp_path):
    """measurements.npz (a zip) and its .json, each mutated with the other intact."""
    from estimators.calibration import measure
    from estimators.io.measurement_store import save_measurements

    from .fuzz_targets import measurements_target

    m = measure(load_dataset(sim_vlp16), rng=np.random.default_rng(0))
    save_measurements(tmp_path, m)
    seed_npz, seed_json = (tmp_path / "measurements.npz").read_bytes(), (tmp_path / "measurements.json").read_bytes()
    for target in measurements_target(seed_npz, seed_json):
        folder = tmp_path / target.name
        folder.mkdir()

        @FUZZ
        @given(ops=mutations())
        def run(ops):
            path = folder / f"measurements{target.suffix}"
            path.write_bytes(mutate(target.seed(folder), ops))
            _only_lidarcam_errors(target.read, path)

        run()
