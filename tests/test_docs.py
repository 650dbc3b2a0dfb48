"""The documentation: the site builds with no warning, every public name has a docstring in the one style, and
the README stays short and free of history."""
from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import estimators

ROOT = Path(__file__).resolve().parents[1]


def test_the_site_builds_without_a_warning(tmp_path):
    """`make docs` as a test: Sphinx with warnings as errors, every page, the API and CLI references. The
    notebooks are not executed here (tests/test_notebooks.py runs each one)."""
    pytest.importorskip("sphinx")
    env = {**os.environ, "LIDARCAM_DOCS_EXECUTE": "off"}
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-b", "html", "-W", "--keep-going", "-q",
                           str(ROOT / "docs"), str(tmp_path / "html"), "-d", str(tmp_path / "doctrees")],
                          capture_output=True, text=True, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for page in ("index", "tutorial", "howto/index", "reference/cli", "reference/api", "reference/errors",
                 "method", "benchmarks", "examples", "notebooks/quickstart"):
        assert (tmp_path / "html" / f"{page}.html").is_file(), page
    cli = (tmp_path / "html" / "reference" / "cli.html").read_text()
    assert "--max-sensor-separation" in cli and "--strict" in cli  # generated from the parser
    api = (tmp_path / "html" / "reference" / "api.html").read_text()
    missing = [n for n in estimators.__all__ if n != "__version__" and f'id="estimators.{n}"' not in api]
    assert not missing, f"public names absent from the API page: {missing}"


def _public():
    return [(n, getattr(estimators, n)) for n in estimators.__all__ if n != "__version__"]


@pytest.mark.parametrize("name,obj", _public(), ids=[n for n, _ in _public()])
def test_every_public_name_has_a_numpydoc_docstring(name, obj):
    """A summary line, then for a function a ``Parameters`` section naming each parameter and a ``Returns``
    section; for a class, ``Parameters`` or ``Attributes``."""
    doc = inspect.getdoc(obj)
    assert doc, f"{name} has no docstring"
    summary = doc.split("\n\n")[0]
    assert summary.strip() and len(summary) <= 400, f"{name}: the first paragraph is a short summary"
    sections = set(re.findall(r"^(\w[\w ]*)\n-{3,}$", doc, flags=re.M))
    if inspect.isclass(obj):
        assert sections & {"Parameters", "Attributes"}, f"{name}: no Parameters or Attributes section"
        return
    params = [p for p in inspect.signature(obj).parameters.values()
              if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if params:
        assert "Parameters" in sections, f"{name}: no Parameters section"
        after = doc.split("Parameters\n----------\n", 1)[1]
        block = re.split(r"^\w[\w ]*\n-{3,}$", after, flags=re.M)[0]  # up to the next section
        named = {n.strip(" *") for line in re.findall(r"^([\w*][\w, *]*?)\s*:", block, flags=re.M)
                 for n in line.split(",")}
        absent = [p.name for p in params if p.name not in named]
        assert not absent, f"{name}: parameters not described: {absent}"
    assert "Returns" in sections, f"{name}: no Returns section"


def test_readme_is_short_and_has_no_history():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert not re.search(r"\bissue \d+|#\d{2,}\b", text, flags=re.I), "issue numbers belong in commit messages"
    assert "make demo" in text and "make test" in text


def _readme_commands(text: str) -> list[str]:
    """The README's `lidarcam ...` commands (in shell blocks and inline) that name no placeholder (DS, CAL,
    rig.bag: the user's own data), in the order a reader meets them."""
    found = set(re.findall(r"`(lidarcam [^`]+)`", text))
    for block in re.findall(r"```sh\n(.*?)```", text, flags=re.S):
        found |= {line.split("#")[0].strip() for line in block.replace("\\\n", " ").splitlines()}
    runnable = [c for c in found if c.startswith("lidarcam ") and not re.search(r"\b[A-Z]{2,}\b|rig\.bag", c)]
    return sorted(runnable, key=text.find)


def test_readme_commands_run_as_written(tmp_path, monkeypatch, capsys):
    """Every README command that needs no data of the user's own runs as written (its /tmp paths moved into a
    temporary folder), and so does the Python example; each writes what the README says it writes. Both run in
    this process (the console script's ``main`` and the example's code as given): the interpreter is not what they
    test, and each child had paid for its imports again."""
    from estimators.cli import main

    text = (ROOT / "README.md").read_text()
    commands = _readme_commands(text)
    assert any(c.startswith("lidarcam simulate") for c in commands)
    assert any(c.startswith("lidarcam calibrate") for c in commands)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    for cmd in commands:
        code = main(cmd.replace("/tmp/", f"{tmp_path}/").split()[1:])
        assert code == 0, f"{cmd}: {capsys.readouterr().err[-2000:]}"
    assert (tmp_path / "cal" / "calibration.json").is_file()
    example = re.search(r"```python\n(.*?)```", text, flags=re.S).group(1).replace("/tmp/", f"{tmp_path}/")
    exec(compile(example, "README.md", "exec"), {"__name__": "readme_example"})
    assert (tmp_path / "cal-py" / "calibration.json").is_file() and (tmp_path / "cal-py" / "report.html").is_file()


def test_docs_carry_no_issue_numbers():
    pages = [p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts and "notebooks" not in p.parts]
    hits = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in pages
            for m in re.finditer(r"\bissue \d+", p.read_text(), flags=re.I)]
    assert not hits, hits


def test_a_benchmark_run_becomes_a_docs_page(tmp_path):
    """`make bench` runs each benchmark through benchmarks/record.py: its output, the command, the date and the
    machine become a page; a failing command leaves the previous page alone and passes on its status."""
    env = {**os.environ, "LIDARCAM_BENCH_PAGES": str(tmp_path)}
    script = "print('configuration  rot deg\\ndefault          0.051')"
    ok = subprocess.run([sys.executable, "benchmarks/record.py", "demo_table", "--", sys.executable, "-c", script],
                        capture_output=True, text=True, env=env, cwd=ROOT)
    assert ok.returncode == 0 and "default          0.051" in ok.stdout
    page = (tmp_path / "demo_table.md").read_text()
    assert "default          0.051" in page and "- machine: " in page and "cores" in page and "-c" in page
    # the versions of the libraries that can move the numbers, as installed where it ran
    from importlib.metadata import version

    assert f"- libraries: numpy {version('numpy')}, " in page and f"gtsam {version('gtsam')}" in page
    assert f"opencv {version('opencv-python-headless')}" in page
    bad = subprocess.run([sys.executable, "benchmarks/record.py", "demo_table", "--", sys.executable, "-c",
                          "import sys; print('partial'); sys.exit(3)"], capture_output=True, text=True, env=env,
                         cwd=ROOT)
    assert bad.returncode == 3
    assert (tmp_path / "demo_table.md").read_text() == page


def test_every_cli_command_and_option_is_described():
    """The CLI reference is generated from the parser: each command needs its description (with an example)
    and each argument its help."""
    import argparse

    from estimators.cli.parser import build_parser, study_spec_parser

    def walk(p, name):
        yield name, p
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, sp in action.choices.items():
                    yield from walk(sp, f"{name} {sub}")

    for name, p in [*walk(build_parser(), "lidarcam"), ("lidarcam study SPEC.yaml", study_spec_parser())]:
        assert p.description, f"{name}: no description"
        bare = [a.dest for a in p._actions
                if not a.help and not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
        assert not bare, f"{name}: arguments without help: {bare}"
