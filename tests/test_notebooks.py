"""Every notebook runs top to bottom (small sizes: LIDARCAM_NOTEBOOK_FAST=1), as a user would run it from
notebooks/ with the project's environment. Outputs stay stripped in git."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
# A cell plots when it draws with pyplot or an axes, or displays a figure the library wrote (PNG, or JPEG: the
# overlays).
PLOTS = re.compile(r"\bplt\.\w|\.(plot|bar|hist|scatter|imshow)\(|\bImage\(")


def test_notebooks_are_stored_without_outputs():
    assert len(NOTEBOOKS) >= 5
    for path in NOTEBOOKS:
        nb = json.loads(path.read_text())
        for cell in nb["cells"]:
            # every cell has its id (nbformat 4.5): a cell without one is a warning today, an error in later nbformat
            assert cell.get("id"), f"{path.name}: a cell without an id"
            if cell["cell_type"] == "code":
                assert cell.get("outputs") == [] and cell.get("execution_count") is None, path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_top_to_bottom(path, monkeypatch, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("LIDARCAM_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's own inline backend, as a user has it
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the folders the notebooks make go with the test's own
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()  # raises CellExecutionError, naming the cell, on any failure
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
    assert any(c.get("outputs") for c in nb.cells if c.cell_type == "code")
    # Every plotting cell leaves its figure: the library must not have switched the notebook's backend.
    plotting = [c for c in nb.cells if c.cell_type == "code" and PLOTS.search(c.source)]
    shown = ("image/png", "image/jpeg")
    missing = [c.source.splitlines()[0] for c in plotting
               if not any(kind in o.get("data", {}) for o in c.get("outputs", []) for kind in shown)]
    assert plotting, f"{path.name}: no plotting cell found"
    assert not missing, f"{path.name}: cells that plot but show no figure: {missing}"


def test_library_leaves_the_plotting_state_alone():
    """Importing the report and drawing a study's figures neither switches matplotlib's backend nor opens
    pyplot figures (run in a fresh interpreter whose backend is set to something other than Agg first)."""
    code = textwrap.dedent("""
        import sys, matplotlib
        matplotlib.use("pdf")
        import estimators.analysis.report
        from estimators.analysis.study import parse_spec, summary_plots
        spec = parse_spec({"name": "t", "lidar": "3d", "solvers": ["closed-form"],
                           "layouts": ["spread", "frontal"], "frames": [4], "trials": 1})
        row = {"solver": "closed-form", "layout": "spread", "frames": 4, "range_noise_m": spec.range_noise_m[0],
               "corner_noise_px": spec.corner_noise_px[0], "rms_rot_err_deg": 0.1, "rms_trans_err_mm": 1.0,
               "rms_bound_rot_deg": 0.05, "rms_bound_trans_mm": 0.5, "mean_seconds": 0.01}
        figures = summary_plots(spec, [row, row | {"layout": "frontal"}])
        assert figures[0][0] == "errors_vs_layout.png", figures[0][0]
        assert all(png.startswith(bytes([0x89]) + b"PNG") for _, png in figures)
        pyplot = sys.modules.get("matplotlib.pyplot")
        print(matplotlib.get_backend(), len(pyplot.get_fignums()) if pyplot else 0)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["pdf", "0"]
