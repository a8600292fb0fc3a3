"""`omnidata warm [status|stop]`: the user's warm-start server of `generate` and `plan`
(services.cli.warm_start): whether one runs, its process, memory and runs; `stop` retires it (runs under way
end and report first). Exit status 1 when no server runs."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from services.cli import warm_start
from services.cli.errors import CliError

STOP_WAIT_S = 10.0  # `stop` waits this long for an idle server to leave (one with runs leaves after them)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata warm`."""
    parser.add_argument("action", nargs="?", choices=("status", "stop"), default="status")


def run(args: argparse.Namespace) -> int:
    folder = warm_start.runtime_dir()
    if folder is None:
        raise CliError("no private folder for the warm-start server (OMNIDATA_WARM_DIR, XDG_RUNTIME_DIR or "
                       f"/tmp/omnidata-{os.getuid()} is missing, not a folder, or reachable by other users)")
    name = warm_start.server_name()
    pid = _server_pid(folder / f"{name}.lock")
    if pid is None:
        print(f"no warm-start server runs for this installation ({folder})")
        return 1
    if args.action == "stop":
        (folder / f"{name}.sock").unlink(missing_ok=True)  # the server retires when its socket goes
        deadline = time.monotonic() + STOP_WAIT_S
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        print(f"warm-start server {pid}: " + ("stopped" if not _alive(pid) else
                                              "takes no new runs; it leaves when its runs end"))
        return 0
    log = folder / f"{name}.log"
    runs = sum(line.startswith("run ") and " ended: " not in line
               for line in (log.read_text(errors="replace").splitlines() if log.exists() else []))
    print(f"warm-start server {pid}: {_rss_mb(pid):.0f} MB resident, up {_uptime_s(pid):.0f} s, "
          f"{runs} run(s) logged; socket {folder / f'{name}.sock'}; log {log}")
    return 0


def _server_pid(lock: Path) -> int | None:
    """The pid the running server wrote into its lock (None when no server holds the lock)."""
    if not warm_start.locked(lock):
        return None
    try:
        return int(lock.read_text().strip())
    except (OSError, ValueError):
        return None


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1][0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _uptime_s(pid: int) -> float:
    ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].split()[19])
    boot = float(Path("/proc/uptime").read_text().split()[0])
    return boot - ticks / os.sysconf("SC_CLK_TCK")
