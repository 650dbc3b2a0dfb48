"""The coverage study's plumbing on a few measurement-level trials (its statistics are in make bench)."""
from __future__ import annotations

import csv
import json

import numpy as np
from scipy.stats import chi2

from estimators.analysis.coverage_study import AXES, summarize
from estimators.cli import main


def test_study_coverage_writes_one_row_per_trial_and_a_consistent_summary(tmp_path, capsys):
    out = tmp_path / "cov"
    assert main(["study", "coverage", "--trials", "3", "--out", str(out), "--workers", "1", "--samples", "300"]) == 0
    rows = list(csv.DictReader((out / "coverage.csv").open()))
    assert len(rows) == 3 and len({r["seed"] for r in rows}) == 3
    for r in rows:
        d2 = float(r["d2_posterior"])
        assert int(r["in95_joint_chi2"]) == int(d2 <= chi2.ppf(0.95, 6))
        assert int(r["in68_joint"]) <= int(r["in95_joint"])
        assert all(int(r[f"in68_{a}"]) <= int(r[f"in95_{a}"]) for a in AXES)
        assert float(r["trans_err_mm"]) < 30  # 8 boards, 2 cm ranges: millimetres, not centimetres
    summary = json.loads((out / "coverage.json").read_text())
    assert summary["trials"] == 3
    frac = summary["coverage"]["95%"]["joint"]["fraction"]
    assert frac == np.mean([int(r["in95_joint"]) for r in rows])
    assert "coverage over 3 measurement trials" in capsys.readouterr().out


def test_wilson_ranges_are_the_wilson_score_intervals():
    """The summary's 95% ranges are Wilson's score intervals, as SciPy's binomial test computes them, for 30 of
    40 trials inside and at the edges (none and all of 10)."""
    from scipy.stats import binomtest

    for k, n in ((30, 40), (0, 10), (10, 10)):
        rows = [{"d2_posterior": 1.0, "d2_laplace": 1.0, **{f"in{level}_{a}": int(i < k) for level in (68, 95)
                                                            for a in (*AXES, "joint", "joint_chi2")}}
                for i in range(n)]
        c = summarize(rows)["coverage"]["95%"]["joint"]
        ci = binomtest(k, n).proportion_ci(0.95, method="wilson")
        assert c["fraction"] == k / n
        np.testing.assert_allclose([c["low"], c["high"]], [ci.low, ci.high], atol=1e-3)
