"""The ``roadmap3d`` command line.

This module only names the commands (their options are frozen dataclasses in
:mod:`app.cli.configs` and :mod:`app.cli.options`), runs the chosen command's runner with its
options, and turns errors into messages; each runner lives in the module that owns the work
(imported when it runs, so ``--help`` is fast).
Errors meant for users (bad files, bad values) become ``error: ...`` on stderr and exit code 2;
set ``ROADMAP3D_DEBUG=1`` to see the traceback instead.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Annotated

import tyro

from app.cli._perf import exit_code, exit_without_teardown, read_ahead_for_register, small_pages
from app.cli.configs import (
    App,
    Audit,
    Bench,
    Demo,
    Info,
    Listen,
    Mesh,
    Password,
    Phantom,
    PhantomRun,
    Register,
    Serve,
    Track,
)
from app.cli.errors import UserError
from app.cli.options import (
    BiplaneStudy,
    CalibrationStudy,
    CaptureStudy,
    ClinicalStudy,
    GeometryStudy,
    PhantomStudy,
    RotationalRunStudy,
    Table1,
    TrackingStudy,
    VolumeStudy,
)

Study = (
    Annotated[Table1, tyro.conf.subcommand("table1")]
    | Annotated[PhantomStudy, tyro.conf.subcommand("phantom")]
    | Annotated[ClinicalStudy, tyro.conf.subcommand("clinical")]
    | Annotated[CalibrationStudy, tyro.conf.subcommand("calibration")]
    | Annotated[TrackingStudy, tyro.conf.subcommand("tracking")]
    | Annotated[RotationalRunStudy, tyro.conf.subcommand("rotational-run")]
    | Annotated[BiplaneStudy, tyro.conf.subcommand("biplane")]
    | Annotated[VolumeStudy, tyro.conf.subcommand("volume")]
    | Annotated[CaptureStudy, tyro.conf.subcommand("capture")]
    | Annotated[GeometryStudy, tyro.conf.subcommand("geometry")]
)


def validate(study: Study) -> Study:
    """Run one of the paper's validation studies."""
    return study


#: Each command's options (tyro builds its flags from them; ``validate``: one of its studies).
COMMANDS: dict[str, object] = {
    "demo": Demo,
    "app": App,
    "validate": validate,
    "bench": Bench,
    "register": Register,
    "info": Info,
    "phantom": Phantom,
    "mesh": Mesh,
    "listen": Listen,
    "audit": Audit,
    "password": Password,
    "track": Track,
    "phantom-run": PhantomRun,
    "serve": Serve,
}

#: Each command's runner, ``(module, function)`` taking its options: imported when it runs, so that
#: ``--help`` loads no engine module.
RUNNERS: dict[type, tuple[str, str]] = {
    Demo: ("app.cli.web_commands", "run_demo"),
    App: ("app.cli.web_commands", "run_app"),
    Bench: ("app.cli.study_commands", "run_bench"),
    Register: ("app.cli.register_command", "run_register"),
    Serve: ("app.cli.worker", "run_serve"),
    Info: ("app.cli.commands", "run_info"),
    Phantom: ("app.cli.phantom_commands", "run_phantom_export"),
    Mesh: ("app.cli.commands", "run_mesh"),
    Listen: ("app.cli.net_commands", "run_listen"),
    Audit: ("app.cli.local_commands", "run_audit"),
    Password: ("app.cli.local_commands", "run_password"),
    Track: ("app.cli.track_commands", "run_track"),
    PhantomRun: ("app.cli.track_commands", "run_phantom_run_export"),
    Table1: ("app.cli.study_commands", "run_table1"),
    PhantomStudy: ("app.cli.study_commands", "run_phantom_study"),
    ClinicalStudy: ("app.cli.study_commands", "run_clinical_study"),
    CalibrationStudy: ("app.cli.study_commands", "run_calibration_study"),
    TrackingStudy: ("app.cli.study_commands", "run_tracking_study"),
    RotationalRunStudy: ("app.cli.rotational_commands", "run_rotational_validation"),
    BiplaneStudy: ("app.cli.study_commands", "run_biplane_study"),
    VolumeStudy: ("app.cli.study_commands", "run_volume_validation"),
    CaptureStudy: ("app.cli.capture_commands", "run_capture_study"),
    GeometryStudy: ("app.cli.study_commands", "run_geometry_study"),
}


def run(options: object, *, in_worker: bool = False) -> int:
    """Run the command whose options these are."""
    module, function = RUNNERS[type(options)]
    seed = getattr(options, "seed", None)
    if isinstance(seed, int) and seed < 0:  # refused before any work: numpy takes no negative seed
        raise UserError(f"--seed must be a non-negative integer, got {seed}")
    if isinstance(options, Register) and not in_worker:
        small_pages()
        if options.pacs is None and options.image:
            read_ahead_for_register(options.volume, options.image)  # read in while the engine is imported
    return int(getattr(importlib.import_module(module), function)(options) or 0)


def execute(argv: list[str], *, in_worker: bool = False) -> int:
    """Parse ``argv`` (the arguments after ``roadmap3d``), run the command and return its exit code;
    errors meant for users are printed as ``error: ...`` and give 2 (``ROADMAP3D_DEBUG=1`` raises
    them instead). ``in_worker``: run inside ``roadmap3d serve`` (no per-process start-up tweaks)."""
    debug = os.environ.get("ROADMAP3D_DEBUG") == "1"
    try:
        options = tyro.extras.subcommand_cli_from_dict(
            COMMANDS, args=argv, config=(tyro.conf.OmitArgPrefixes,), prog="roadmap3d"
        )
        return run(options, in_worker=in_worker)
    except SystemExit as exc:  # tyro's --help and usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (UserError, ValueError, OSError) as exc:
        if debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (ArithmeticError, RecursionError, MemoryError, LookupError, TypeError) as exc:
        # Reachable only from a value no check caught (a file or an option): still a message, exit 2.
        if debug:
            raise
        what = str(exc).strip()[:200] or "no details"
        given = " ".join(argv)
        given = given if len(given) <= 300 else given[:297] + "..."
        print(f"error: {type(exc).__name__} ({what}) on the input of: roadmap3d {given}; rerun with "
              "ROADMAP3D_DEBUG=1 to see where", file=sys.stderr)  # fmt: skip
        return 2


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``roadmap3d`` console script (:func:`app.launch.main` first offers a
    ``register`` to a running worker)."""
    if argv is None:  # the console script: the process ends after its exit handlers, without teardown
        exit_without_teardown()
    code = execute(sys.argv[1:] if argv is None else list(argv))
    sys.exit(exit_code(code) if argv is None else code)


if __name__ == "__main__":
    main()
