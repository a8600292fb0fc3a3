"""`omnidata compile-kernels [--every-level]`: compile the worker's kernels into numba's on-disk cache before
any job needs them.

Run where the workers will run from: `make venv` does (the editable install: the cache sits beside the
sources, for this machine's x86-64 level), and so does the image build with --every-level (NUMBA_CACHE_DIR of
deploy/Dockerfile: one set of kernels per level the build machine runs, so a pod on any machine of those
levels only loads them). See services/worker/process/kernel_warm_up.py and kernel_target.py. Exit status 1
when a kernel was not reached (a job would compile it itself).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys

from services.worker.process.numeric_threads import pin_numeric_threads

pin_numeric_threads()  # before numpy loads: the kernels' linear algebra as a worker runs it


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata compile-kernels`."""
    parser.add_argument(
        "--every-level", action="store_true",
        help="compile for every x86-64 level this machine runs (x86-64-v4, "
        "x86-64-v3), each in its own process, not only for the best one: a cache for machines of any of "
        "them (image builds)",
    )


def run(args: argparse.Namespace) -> int:
    """Compile (or load) every kernel; one line per CPU target with what was done and where."""
    if args.every_level:
        return _every_level()
    from services.worker.process.kernel_warm_up import compile_kernels

    report = compile_kernels()
    target = os.environ.get("NUMBA_CPU_NAME") or "this machine's CPU"
    where = os.environ.get("NUMBA_CACHE_DIR") or "__pycache__ beside the sources"
    print(f"omnidata compile-kernels: {report.kernels} kernels ({report.versions} compiled versions) for "
          f"{target} in {report.seconds:.1f} s; cache: {where}", flush=True)
    if report.missed:
        print(
            f"omnidata compile-kernels: not reached (a job compiles them itself): {', '.join(report.missed)}",
            file=sys.stderr,
        )
        return 1
    return 0


def _every_level() -> int:
    """This command once per level the machine runs, in a child process whose numba builds for that level."""
    from services.worker.process.kernel_target import host_features, level_environment, levels_for

    levels = levels_for(platform.machine(), host_features())
    if not levels:
        print(
            "omnidata compile-kernels: this machine runs no x86-64 level: compiling for its own CPU",
            flush=True,
        )
        levels = [""]
    worst = 0
    for level in levels:
        env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU")}
        env.update(level_environment(level) if level else {})
        worst = max(
            worst,
            subprocess.run([sys.executable, "-m", "services.cli", "compile-kernels"], env=env).returncode,
        )
    return worst
