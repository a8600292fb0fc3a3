"""`omnidata` command line: the composition root, the one place that wires the services together.

Each subcommand is a module with `add_arguments(parser)` + `run(args) -> int`, imported only when named, so
`omnidata --help` starts fast and the API/scheduler never import bpy. Errors the user can fix (CliError and
the domain errors of the library) end as one line and exit status 2; anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import sys

from services.cli import warm_start
from services.cli.errors import CliError
from services.core.domain.errors import DomainError
from services.core.gc_pause import collections_paused

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "plan": ("services.cli.plan", "sample cameras, points and views of spaces (no rendering)"),
    "generate": (
        "services.cli.generate", "plan and render a dataset locally (SQLite, local folder, local workers)",
    ),
    "serve": ("services.cli.serve", "run the REST API and dashboard"),
    "scheduler": ("services.cli.scheduler", "run the scheduler (plans jobs, dispatches tasks)"),
    "worker": ("services.cli.worker", "run a Celery render worker"),
    "submit": ("services.cli.submit", "submit a job to a running service and follow its progress"),
    "sheet": (
        "services.cli.contact_sheet",
        "draw a contact sheet PNG of every cue of a few views of an output folder",
    ),
    "export": (
        "services.cli.export", "export an output as WebDataset shards or the public Omnidata loader's tree",
    ),
    "preview": ("services.cli.preview", "preview PNGs of an output's cues, or one MP4 per cue (--video)"),
    "compile-kernels": (
        "services.cli.compile_kernels",
        "compile the worker's kernels into numba's on-disk cache "
        "(image build, `make venv`): workers then only load them",
    ),
    "warm": ("services.cli.warm", "the warm-start server of generate and plan: status (default) or stop"),
    "migrate": ("services.cli.migrate", "upgrade the database schema to this version's head (Alembic)"),
    "token": (
        "services.cli.token_create",
        "create an API token for a tenant (or an operator) and print its settings entry",
    ),
}


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser, with the arguments of the subcommand named in argv (only that module is imported)."""
    parser = argparse.ArgumentParser(
        prog="omnidata", description="Omnidata: multi-task vision datasets from 3D scans"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name in argv[:1]:
            with collections_paused():  # the command's imports: most of its start-up
                command = importlib.import_module(module)
                # their ~10^6 long-lived objects out of every later collection's walk (a forked worker's
                # too): `generate` spent ~0.1 CPU-s of its start-up collecting them, finding nothing
                gc.freeze()
            command.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The `omnidata` command: `generate` and `plan` run in the user's warm server when one is up, and
    start one after a cold run (services.cli.warm_start)."""
    argv = sys.argv[1:] if argv is None else argv
    if not warm_start.wanted(argv):
        return run_command(argv)
    code = warm_start.run_warm(argv)
    if code is None:
        code = run_command(argv)
        warm_start.start_server()
    return code


def run_command(argv: list[str]) -> int:
    """Run one command line in this process: its exit status."""
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except (CliError, DomainError) as e:
        print(f"omnidata {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Exception as e:
        from services.core.settings import (
            ConfigurationError,  # loaded already if e is one (keeps --help fast)
        )

        if not isinstance(e, ConfigurationError):
            raise
        print(f"omnidata {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"omnidata {args.command}: interrupted", file=sys.stderr)
        return 130
