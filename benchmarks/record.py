"""Run one benchmark and write its output into the documentation as a page (`make bench` runs every benchmark
through it): `python benchmarks/record.py NAME -- COMMAND ...`.

The page `docs/bench/NAME.md` holds the command, the date, the machine, the numerical libraries' versions and the
printed output, unedited: the documented numbers are the ones a rerun of that command prints. The output is also
streamed to the terminal.
A command that fails leaves the previous page in place and exits with its status."""
from __future__ import annotations

import datetime
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PAGES = Path(os.environ.get("LIDARCAM_BENCH_PAGES", ROOT / "docs" / "bench"))


def machine() -> str:
    """CPU model, cores, memory, OS and Python: what the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
        mem_text = f", {mem:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        mem_text = ""
    return f"{cpu}, {os.cpu_count()} cores{mem_text}, {platform.system()} {platform.release()}, " \
           f"Python {platform.python_version()}"


# The libraries whose versions can move a benchmark's numbers (OpenCV's corner search, GTSAM's solver, ...).
LIBRARIES = ("numpy", "scipy", "opencv-python-headless", "gtsam", "emcee")


def libraries() -> str:
    """The installed versions of ``LIBRARIES`` (this interpreter's: ``make bench`` runs each benchmark with it)."""
    from importlib.metadata import PackageNotFoundError, version

    def one(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "absent"

    return ", ".join(f"{name.removesuffix('-python-headless')} {one(name)}" for name in LIBRARIES)


def revision() -> str:
    try:
        out = subprocess.run(["git", "describe", "--always"], capture_output=True, text=True, cwd=ROOT)
        # Dirty when anything but the pages differs from the commit: a run of `make bench` writes them one by one.
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                  ":(exclude)docs/bench"], capture_output=True, text=True, cwd=ROOT)
        rev = out.stdout.strip() or "unknown"
        return rev + ("-dirty" if changed.stdout.strip() else "")
    except OSError:
        return "unknown"


def title_of(command: list[str]) -> str:
    """The benchmark script's docstring's first paragraph up to its first parenthesis, a study file's ``name:``,
    or the command."""
    for arg in command:
        if arg.endswith(".yaml") and (ROOT / arg).is_file():
            import yaml

            spec = yaml.safe_load((ROOT / arg).read_text())
            if isinstance(spec, dict) and isinstance(spec.get("name"), str):
                return spec["name"]
        if arg.endswith(".py") and (ROOT / arg).is_file():
            text = (ROOT / arg).read_text()
            for quote in ('"""', "'''"):
                if text.lstrip().startswith(quote):
                    first = " ".join(text.lstrip()[3:].split("\n\n")[0].split(quote)[0].split())
                    return first.split(" (")[0].strip().rstrip(".:")
    return " ".join(command)


def page(name: str, command: list[str], output: str, seconds: float, when: datetime.datetime, rev: str) -> str:
    shown = " ".join(shlex.quote(c) for c in command)
    return "\n".join([
        f"# {title_of(command)}", "",
        f"`{shown}`", "",
        f"- run: {when:%Y-%m-%d %H:%M} UTC, {seconds / 60:.1f} min; lidarcam {rev}",
        f"- machine: {machine()}",
        f"- libraries: {libraries()}", "",
        "```text", output.rstrip("\n"), "```", ""])


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "--":
        print(__doc__.split("\n\n")[0], file=sys.stderr)
        return 2
    name, command = argv[0], argv[2:]
    when = datetime.datetime.now(datetime.timezone.utc)
    rev = revision()  # the code that runs: taken before the run, as edits meanwhile do not reach it
    start = datetime.datetime.now().timestamp()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=None, text=True, cwd=ROOT)
    lines = []
    for line in proc.stdout:
        sys.stdout.write(line)
        sys.stdout.flush()
        lines.append(line)
    code = proc.wait()
    if code != 0:
        print(f"record.py: {' '.join(command)} exited with {code}; docs/bench/{name}.md left as it was",
              file=sys.stderr)
        return code
    from estimators.io.output import write_atomic

    PAGES.mkdir(parents=True, exist_ok=True)
    text = page(name, command, "".join(lines), datetime.datetime.now().timestamp() - start, when, rev)
    write_atomic(PAGES / f"{name}.md", lambda fh: fh.write(text))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
