"""Shared fixtures: small simulated datasets, made once per run with fixed seeds (one folder for all the test
processes: the tests read them and never write into them)."""
from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread per test process, as the CLI runs (and every child process inherits it): the suite runs two
# processes on two cores, and OpenBLAS's own threads would compete with the other process (they keep spinning
# after each large product). Set before numpy loads OpenBLAS, and limited again below where it was loaded already.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

threadpool_limits(int(os.environ["OPENBLAS_NUM_THREADS"]))

# Property tests check correctness, not speed: no per-example deadline on a loaded 2-core CI machine. Their
# examples are drawn from a fixed seed (derandomize) and no example database is kept, so every run, here or in CI,
# checks the same 100 examples and a failure reproduces.
settings.register_profile("lidarcam", deadline=None, max_examples=100, derandomize=True, database=None)
settings.load_profile("lidarcam")

from estimators.simulation.simulator import simulate_dataset  # noqa: E402

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


def _run_folder(tmp_path_factory) -> Path:
    """The temporary folder of the whole run: a test process's own, or, under pytest-xdist, its workers' parent."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def shared_folder(tmp_path_factory, name: str, make) -> Path:
    """Folder ``name`` made once by ``make(path)`` for the whole run, however many test processes share it
    (pytest-xdist's workers: the first to take the lock makes it, the others wait and read it)."""
    import fcntl

    root = _run_folder(tmp_path_factory)
    target = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / f"{name}.made").is_file():
            make(target)
            (root / f"{name}.made").touch()
    return target


@pytest.fixture(scope="session", autouse=True)
def _measurement_cache(tmp_path_factory):
    """Every calibration the tests run, the command line's in child processes too, keeps its measurement cache in
    the run's own folder, one for all its test processes (the cache is keyed by the files' content, the options and
    the code, and written atomically, so a process reads only what another measured alike): never the user's
    (``~/.cache/lidarcam``, which the suite filled with 130 MB of test rigs), and no test reads measurements an
    earlier run left there. A test that checks a first measurement sets its own."""
    folder = _run_folder(tmp_path_factory) / "measurement_cache"
    folder.mkdir(exist_ok=True)
    patch = pytest.MonkeyPatch()
    patch.setenv("LIDARCAM_CACHE_DIR", str(folder))
    yield
    patch.undo()


@pytest.fixture(scope="session")
def sim_hdl64e(tmp_path_factory) -> Path:
    """8 poses, HDL-64E-like, 2 cm range noise (the issue's acceptance setting)."""
    return shared_folder(tmp_path_factory, "sim_hdl64e", lambda path: simulate_dataset(
        path, n_poses=8, seed=11, lidar="hdl64e", sigma_range_m=0.02))


@pytest.fixture(scope="session")
def sim_vlp16(tmp_path_factory) -> Path:
    return shared_folder(tmp_path_factory, "sim_vlp16", lambda path: simulate_dataset(
        path, n_poses=8, seed=12, lidar="vlp16", sigma_range_m=0.02))


@pytest.fixture(scope="session")
def sim_2d(tmp_path_factory) -> Path:
    """6 poses, 270-degree single-line scanner, 1 cm range noise, CSV scans (invalid returns as 0)."""
    return shared_folder(tmp_path_factory, "sim_2d", lambda path: simulate_dataset(
        path, n_poses=6, seed=5, lidar="2d", sigma_range_m=0.01, scan_format="csv"))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """One line when recorded-data tests skipped (../shared/realdata absent), so that a green run without the
    recordings never reads as one that checked them."""
    skipped = [r for r in terminalreporter.stats.get("skipped", [])
               if isinstance(r.longrepr, tuple) and "realdata" in str(r.longrepr[2])]
    if skipped:
        names = sorted({str(r.longrepr[2]).split("realdata/")[-1].split()[0] for r in skipped})
        terminalreporter.write_line(f"{len(skipped)} recorded-data test(s) skipped: {', '.join(names)} absent from "
                                    f"{REALDATA} (the recorded sets are not checked in this run)", yellow=True)
