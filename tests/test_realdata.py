"""Recorded data from ../shared/realdata (skipped cleanly where absent)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estimators.calibration import calibrate
from estimators.dataset import load_dataset
from geometry.rotations import rotation_error

from .conftest import REALDATA

VLP16 = REALDATA / "acfr_vlp16_a"


@pytest.mark.skipif(not (VLP16 / "dataset.yaml").is_file(), reason="shared/realdata/acfr_vlp16_a is absent")
def test_recorded_vlp16_fisheye_calibrates_near_its_reference():
    """Every frame's board is found (all 12 checkerboards are visible), and the result lies within 2 degrees
    and 10 cm of the source tool's reference extrinsic (a median of its own solutions, not ground truth)."""
    ds = load_dataset(VLP16)
    result = calibrate(ds, rng=np.random.default_rng(0))
    assert result.frames_used == len(ds.frames) == 12, [f.reason for f in result.frames if not f.usable]
    ref = np.array(json.loads((VLP16 / "reference.json").read_text())["T_camera_lidar"])
    rot = np.degrees(rotation_error(result.T_camera_lidar[:3, :3], ref[:3, :3]))
    trans = np.linalg.norm(result.T_camera_lidar[:3, 3] - ref[:3, 3])
    assert rot < 2.0 and trans < 0.10, (rot, trans)
