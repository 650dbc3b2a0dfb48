"""The ``lidarcam`` command line: a thin shell over the library. Arguments are parsed before heavy imports.

``parser`` builds the arguments and the options taken from them, ``commands`` runs each command, ``printing``
says what a result holds.
"""
from __future__ import annotations

import os
import sys

from .commands import (calibrate_command, check_command, demo_command, export_command, extract_command,
                       layout_command, simulate_command, study_command, study_spec_command, validate_command)
from .parser import build_parser


# The exit code of a command whose reader closed its output (``lidarcam ... | head``): a Unix tool's, killed by
# SIGPIPE (128 + 13).
EXIT_PIPE_CLOSED = 141


def run() -> None:
    """The ``lidarcam`` console script: :func:`main`, then the process ends at once with its exit code. Every
    file is written and closed by then; skipping the interpreter's orderly teardown of GTSAM, OpenCV, scipy
    and the rest saves a quarter of a second per command. A reader that closes the output early ends the command
    there, quietly, as it ends any Unix tool (``EXIT_PIPE_CLOSED``), not with a traceback."""
    try:
        code = main()
        sys.stdout.flush()
    except BrokenPipeError:
        code = EXIT_PIPE_CLOSED
    sys.stderr.flush()
    os._exit(code)


def _check_out(args) -> None:
    """``--out`` must be a folder (made when missing; ``export``'s is a file), and for a command that reads a dataset
    folder not that folder itself: its report's images (``board_choice_lidar0_0000.png``) would be read as frames
    the next time, and the folder refused. One-line errors, before anything is read or written."""
    from pathlib import Path

    from ..errors import LidarcamError

    out = getattr(args, "out", None)
    if not out or args.command == "export":  # export's --out is the file it writes
        return
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LidarcamError("--out is a file, where a folder for the results is expected", path=out,
                            hint="give a folder (made when missing)")
    dataset = getattr(args, "dataset", None)
    if dataset and args.command in ("calibrate", "validate", "check") and Path(dataset).is_dir() and out.exists() \
            and out.resolve() == Path(dataset).resolve():
        raise LidarcamError("--out is the dataset folder itself: the results' files would be read as its frames "
                            "next time", path=out, hint="give another folder, e.g. a new one beside it")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    spec_study = len(argv) >= 2 and argv[0] == "study" and argv[1] not in ("coverage", "-h", "--help")
    args = None if spec_study else build_parser().parse_args(argv)
    # The pipeline parallelises over frames itself; OpenBLAS's own threads would compete with it for the
    # cores (and keep spinning after large products, slowing the small-matrix work that follows).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..errors import LidarcamError

    handlers = {"calibrate": calibrate_command, "validate": validate_command, "simulate": simulate_command,
                "demo": demo_command, "study": study_command, "layout": layout_command, "extract": extract_command,
                "export": export_command, "check": check_command}
    try:
        if spec_study:
            return study_spec_command(argv[1:])
        _check_out(args)
        return handlers[args.command](args)
    except LidarcamError as exc:
        print(f"lidarcam: error: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lidarcam: interrupted", file=sys.stderr)
        return 130
