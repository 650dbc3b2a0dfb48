"""Shared fixtures: small simulated datasets, made once per test session with fixed seeds."""
from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import settings

# Property tests check correctness, not speed: no per-example deadline on a loaded 2-core CI machine.
settings.register_profile("lidarcam", deadline=None, max_examples=100)
settings.load_profile("lidarcam")

from estimators.simulation.simulator import simulate_dataset

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@pytest.fixture(scope="session")
def sim_hdl64e(tmp_path_factory) -> Path:
    """8 poses, HDL-64E-like, 2 cm range noise (the issue's acceptance setting)."""
    return simulate_dataset(tmp_path_factory.mktemp("sim") / "hdl64e", n_poses=8, seed=11, lidar="hdl64e",
                            sigma_range_m=0.02)


@pytest.fixture(scope="session")
def sim_vlp16(tmp_path_factory) -> Path:
    return simulate_dataset(tmp_path_factory.mktemp("sim") / "vlp16", n_poses=8, seed=12, lidar="vlp16",
                            sigma_range_m=0.02)


@pytest.fixture(scope="session")
def sim_2d(tmp_path_factory) -> Path:
    """6 poses, 270-degree single-line scanner, 1 cm range noise, CSV scans (invalid returns as 0)."""
    return simulate_dataset(tmp_path_factory.mktemp("sim") / "scan2d", n_poses=6, seed=5, lidar="2d",
                            sigma_range_m=0.01, scan_format="csv")
