"""`omnidata` command line: the composition root (DESIGN.md section 8).

Each subcommand lives in its service as `add_arguments(parser)` + `run(args) -> int`, imported lazily
so `omnidata --help` starts fast and the API/scheduler never import bpy.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "plan": ("services.scheduler.plan_cli", "sample cameras, points and views of spaces (no rendering)"),
    "generate": ("services.generate_cli", "plan and render a dataset locally (SQLite, local folder, local workers)"),
    "serve": ("services.api.cli", "run the REST API and dashboard"),
    "scheduler": ("services.scheduler.cli", "run the scheduler (plans jobs, dispatches tasks)"),
    "worker": ("services.worker.cli", "run a Celery render worker"),
    "submit": ("services.submit_cli", "submit a job to a running service and follow its progress"),
    "sheet": ("services.contact_sheet", "draw a contact sheet PNG of every cue of a few views of an output folder"),
    "export": ("services.datasets.export", "export an output as WebDataset shards or the public Omnidata loader's tree"),
    "preview": ("services.datasets.preview_cli", "preview PNGs of an output's cues, or one MP4 per cue (--video)"),
    "migrate": ("services.migrate_cli", "upgrade the database schema to this version's head (Alembic)"),
    "token": ("services.token_cli", "create an API token for a tenant (or an operator) and print its settings entry"),
}


class CliError(Exception):
    """A user mistake on the command line; printed as `omnidata: error: ...`, exit status 2."""


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser, with the arguments of the subcommand named in argv (only that module is imported)."""
    parser = argparse.ArgumentParser(prog="omnidata", description="Omnidata: multi-task vision datasets from 3D scans")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name in argv[:1]:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except CliError as e:
        print(f"omnidata {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Exception as e:
        from services.core.settings import ConfigurationError  # loaded already if e is one

        if not isinstance(e, ConfigurationError):
            raise
        print(f"omnidata {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"omnidata {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # `python -m services.cli` runs this file as __main__; use the importable module so that
    # CliError raised by subcommands is the same class we catch.
    from services.cli import main as _main

    sys.exit(_main())
