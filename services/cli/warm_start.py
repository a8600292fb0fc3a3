"""Warm start of `omnidata generate` (and `plan`): a local server process keeps the command's imports and
compiled kernels loaded between runs and forks each run from them (services.cli.warm_server), so a run skips
about 1 CPU-s of start-up (bench/render/warm_start.py).

This is the client half, imported before anything heavy. It hands the server its arguments, working folder,
environment, umask, CPU affinity and its stdin/stdout/stderr; the forked run is the cold run's code on the
same inputs, writing to the same terminal, and its exit status comes back. Signals the client gets (Ctrl-C,
SIGTERM, SIGHUP) go on to the run, and Ctrl-Z stops the run with its workers (its own process group); a
client that dies ends its run as a killed `generate` ends (SIGKILL: its workers notice and stop, and the job
resumes on the next run). With no server, the command runs cold and then starts one, detached; it exits after
IDLE_S without a run, when the code it loaded changes on disk, or when its socket is removed.

OMNIDATA_WARM_START=0 turns it off (the test suite does, but for the tests of this module). Linux only: fork,
file descriptors passed over a Unix socket, pidfds.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import select
import signal
import socket
import stat
import struct
import subprocess
import sys
import time
from pathlib import Path

IDLE_S = 600.0  # a server with no run for this long exits (it holds ~250 MB resident)
STARTING_WAIT_S = 5.0  # a client waits this long for a server still importing (a cold run would import too)
FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
HEADER = struct.Struct("!I")  # each message: its length, then that much JSON

COMMANDS = ("generate", "plan")  # the commands that run warm (they import the same ~1 CPU-s)

serving = False  # True inside the server and its runs: a run never asks a server


def wanted(argv: list[str]) -> bool:
    """Whether this command line may run warm: `generate` or `plan` (not their help), not turned off, on
    Linux."""
    return (
        bool(argv) and argv[0] in COMMANDS
        and not {"-h", "--help"} & set(argv)
        and os.environ.get("OMNIDATA_WARM_START", "1") != "0"
        and sys.platform == "linux"
        and hasattr(os, "pidfd_open")
        and not serving
    )


def runtime_dir() -> Path | None:
    """The folder of this user's servers ($OMNIDATA_WARM_DIR, else $XDG_RUNTIME_DIR/omnidata, else
    /tmp/omnidata-UID), made private; None when it is not this user's alone (nothing is run from it)."""
    base = os.environ.get("OMNIDATA_WARM_DIR")
    if not base:
        xdg = os.environ.get("XDG_RUNTIME_DIR")
        base = f"{xdg}/omnidata" if xdg else f"/tmp/omnidata-{os.getuid()}"
    path = Path(base)
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = os.lstat(path)
    except OSError:
        return None
    private = stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and not st.st_mode & 0o077
    return path if private else None


def server_name() -> str:
    """One server per interpreter, code location and dynamic loader setting (read when a process starts, so a
    run could not take it over): another checkout, venv or LD_LIBRARY_PATH gets its own."""
    code = Path(__file__).resolve().parents[1]
    loader = [os.environ.get(k, "") for k in ("LD_LIBRARY_PATH", "LD_PRELOAD")]
    python = [sys.prefix, os.path.realpath(sys.executable), sys.version]  # `python`, `python3.11`: one
    key = hashlib.sha256("\0".join([*python, str(code), *loader]).encode())
    return f"warm-{key.hexdigest()[:16]}"


def send(sock: socket.socket, message: dict, fds: list[int] | None = None) -> None:
    data = json.dumps(message).encode()
    if fds:
        socket.send_fds(sock, [HEADER.pack(len(data)) + data], fds)
    else:
        sock.sendall(HEADER.pack(len(data)) + data)


def receive(sock: socket.socket) -> dict | None:
    """The next message, or None at the end of the connection."""
    head = read_exactly(sock, HEADER.size)
    if head is None:
        return None
    body = read_exactly(sock, HEADER.unpack(head)[0])
    return None if body is None else json.loads(body)


def read_exactly(sock: socket.socket, size: int) -> bytes | None:
    """`size` bytes from `sock`, or None when the connection ends first."""
    chunks, left = [], size
    while left:
        try:
            chunk = sock.recv(left)
        except InterruptedError:
            continue
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def run_warm(argv: list[str]) -> int | None:
    """Run the command in the user's warm server: its exit status, or None when no server took it (run it
    cold)."""
    folder = runtime_dir()
    if folder is None:
        return None
    sock = _connect(folder / f"{server_name()}.sock", folder / f"{server_name()}.lock")
    if sock is None:
        return None
    with sock:
        try:
            request = {"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ), "umask": _umask(),
                       "affinity": sorted(os.sched_getaffinity(0))}
            send(sock, request, [0, 1, 2])
            reply = receive(sock)
        except OSError:
            return None
        if reply is None or "pid" not in reply:  # refused (its code changed) or gone: run cold
            return None
        return _follow(sock, reply["pid"])


def _connect(path: Path, lock: Path) -> socket.socket | None:
    """A connection to the server, waiting for one that is still starting (it holds the lock)."""
    deadline = time.monotonic() + STARTING_WAIT_S
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.connect(str(path))
            return sock
        except OSError:
            sock.close()
        if not locked(lock) or time.monotonic() > deadline:
            return None
        time.sleep(0.05)


def locked(lock: Path) -> bool:
    """Whether a server holds `lock` (one is starting or serving)."""
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError:
        return True
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _follow(sock: socket.socket, pid: int) -> int:
    """Pass signals on to the run until its status arrives; a run killed by a signal kills this process
    with it, as the cold command would have died."""
    try:
        pidfd = os.pidfd_open(pid)
    except OSError:  # ended already
        pidfd = -1

    def running() -> bool:
        return pidfd >= 0 and not select.select([pidfd], [], [], 0)[0]

    def forward(signum: int, _frame: object) -> None:
        if running():
            signal.pidfd_send_signal(pidfd, signum)

    def suspend(_signum: int, _frame: object) -> None:
        # Ctrl-Z: the run and its workers (its process group) stop, then this process, which the shell
        # watches; continued (fg, bg), it continues them
        if running():
            os.killpg(pid, signal.SIGTSTP)
        os.kill(os.getpid(), signal.SIGSTOP)
        if running():
            os.killpg(pid, signal.SIGCONT)

    previous = {s: signal.signal(s, forward) for s in FORWARDED}
    previous[signal.SIGTSTP] = signal.signal(signal.SIGTSTP, suspend)
    try:
        status = receive(sock)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if pidfd >= 0:
            os.close(pidfd)
    if status is None:
        print(f"omnidata: the warm-start server ended during the run (pid {pid}); its outcome is unknown: "
              "run the same command again to resume it", file=sys.stderr)
        return 1
    if status.get("signal"):
        signum = int(status["signal"])
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return 128 + signum
    return int(status["exit"])


def start_server() -> None:
    """Start this user's server in the background unless one is running or starting; never fails the
    command (a warm start only saves time)."""
    folder = runtime_dir()
    if folder is None or locked(folder / f"{server_name()}.lock"):
        return
    try:
        with open(folder / f"{server_name()}.log", "wb") as log:
            subprocess.Popen(
                [sys.executable, "-m", "services.cli.warm_server", str(folder), server_name()],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True, close_fds=True,
                cwd="/", env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
                    str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH"))))},
            )
    except OSError:
        pass
