"""The warm-start server of `omnidata generate` (services.cli.warm_start has the why and the client).

`python -m services.cli.warm_server FOLDER NAME`: holds FOLDER/NAME.lock while it lives, imports what a run
imports (the command, the worker's modules, numba's CPU target; not Blender, whose thread pools do not survive
a fork), listens on FOLDER/NAME.sock, and forks one run per connection. The run takes over the client's
stdin/stdout/stderr, folder, environment, umask and CPU affinity, then calls the same `main` a cold command
calls. One thread, one select loop: connections, and a pidfd per run for its end.
"""

from __future__ import annotations

import atexit
import fcntl
import gc
import hashlib
import json
import logging
import os
import select
import signal
import socket
import struct
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from services.cli import warm_start

CODE_ROOT = Path(__file__).resolve().parents[1]  # services/: a change in it retires the server
REQUEST_TIMEOUT_S = 5.0  # a client sends its request at once; one that does not is dropped


@dataclass
class Run:
    pid: int
    conn: socket.socket | None  # None once its client died


def preload() -> None:
    """What every run imports and makes before its first task, once, its workers' compiled kernels included
    (gc.freeze: out of every collection's walk, the runs' and their workers')."""
    from services.core.gc_pause import collections_paused

    with collections_paused():
        import services.cli.generate  # noqa: F401  (pins the numeric libraries before numpy loads)
        import services.cli.plan  # noqa: F401
        from services.core.ingest.parsed_cache import loader_version
        from services.embedded.pool import WORKER_MODULES
        from services.worker.process import kernel_target

        for name in WORKER_MODULES:
            __import__(name)
        kernel_target.load()
        kernel_target.load_cached_kernels()
        loader_version()  # the digest of the loader's sources, made once (a change retires the server)
    gc.collect()
    gc.freeze()


def idle_s() -> float:
    """How long the server waits for a run before it exits (OMNIDATA_WARM_IDLE_S, else IDLE_S)."""
    return float(os.environ.get("OMNIDATA_WARM_IDLE_S") or warm_start.IDLE_S)


def code_stamp() -> str:
    """A digest of every Python source under services/ (path, size, mtime): whether what the server loaded is
    still the code."""
    digest = hashlib.sha1()
    for folder, dirs, files in os.walk(CODE_ROOT):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                st = os.stat(os.path.join(folder, name))
                digest.update(f"{folder}/{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def serve(folder: Path, name: str) -> None:
    """Serve runs until retired (idle, code changed, socket gone) and the last run has ended."""
    lock = os.open(folder / f"{name}.lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return  # another server of this code is starting or serving
    os.ftruncate(lock, 0)
    os.write(lock, f"{os.getpid()}\n".encode())  # who to stop
    warm_start.serving = True
    preload()
    stamp = code_stamp()
    path = folder / f"{name}.sock"
    listener: socket.socket | None
    listener, inode = _listen(path)
    runs: dict[int, Run] = {}  # pidfd -> run
    idle_since = time.monotonic()
    while listener is not None or runs:
        watched: list[socket.socket | int] = [r.conn for r in runs.values() if r.conn is not None]
        watched += [*runs, *([listener] if listener else [])]
        ready, _, _ = select.select(watched, [], [], min(5.0, idle_s()))
        for item in ready:
            if listener is not None and item is listener:
                listener = _accept(listener, (path, inode), stamp, runs, lock)
            elif isinstance(item, int):
                _ended(runs.pop(item), item)
            elif isinstance(item, socket.socket):  # a client's connection ended while its run goes on
                _client_gone(item, runs)
        if runs:
            idle_since = time.monotonic()
        elif listener is not None and (
            time.monotonic() - idle_since > idle_s() or not _ours(path, inode)
        ):
            listener = _retire(listener, path, inode)


def _listen(path: Path) -> tuple[socket.socket, int]:
    """Listen on `path`, put in place atomically (a client never sees a socket that is not listening): the
    listener and the socket file's inode."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(tmp))
    sock.listen(16)
    os.replace(tmp, path)
    return sock, os.stat(path).st_ino


def _ours(path: Path, inode: int) -> bool:
    """Whether `path` is still this server's socket (removed or replaced: retire)."""
    try:
        return os.stat(path).st_ino == inode
    except OSError:
        return False


def _retire(listener: socket.socket, path: Path, inode: int) -> socket.socket | None:
    """Stop taking runs (the ones under way still end and report): None, the server's listener from now."""
    if _ours(path, inode):
        path.unlink(missing_ok=True)
    listener.close()
    return None


def _accept(listener: socket.socket, socket_file: tuple[Path, int], stamp: str,
            runs: dict[int, Run], lock: int) -> socket.socket | None:
    conn, _ = listener.accept()
    conn.settimeout(REQUEST_TIMEOUT_S)
    fds: list[int] = []
    try:
        peer_uid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))[1]
        if peer_uid != os.getuid():
            conn.close()
            return listener
        head, fds, _, _ = socket.recv_fds(conn, warm_start.HEADER.size, 3)
        body = warm_start.read_exactly(conn, warm_start.HEADER.unpack(head)[0]) if head else None
        if body is None or len(fds) != 3:
            raise OSError("incomplete request")
        request = json.loads(body)
        if code_stamp() != stamp:  # the code changed since this server loaded it: the client runs cold
            print("warm server: the code changed since it started: a run refused, retiring",
                  file=sys.stderr, flush=True)
            warm_start.send(conn, {"refused": "code changed"})
            conn.close()
            return _retire(listener, *socket_file)
        conn.settimeout(None)
        pid = os.fork()
        if pid == 0:
            others = [r.conn.fileno() for r in runs.values() if r.conn is not None]
            _run(request, fds, keep=conn, close=[listener.fileno(), lock, *others, *runs])
        runs[os.pidfd_open(pid)] = Run(pid, conn)
        # logged before the client hears of the run: a quick run's client may otherwise end before the line
        print(f"run {pid}: omnidata {' '.join(request['argv'])}", file=sys.stderr, flush=True)
        warm_start.send(conn, {"pid": pid})
    except (OSError, ValueError) as e:
        print(f"warm server: a request dropped: {e}", file=sys.stderr)
        conn.close()
    finally:
        for fd in fds:
            os.close(fd)
    return listener


def _ended(run: Run, pidfd: int) -> None:
    """Report a finished run's status to its client."""
    os.close(pidfd)
    _, status, usage = os.wait4(run.pid, 0)
    message = {"signal": os.WTERMSIG(status)} if os.WIFSIGNALED(status) else {"exit": os.WEXITSTATUS(status)}
    # the run's CPU with its workers' (reaped by it): what bench/render/warm_start.py reads
    print(f"run {run.pid} ended: {json.dumps(message)}, cpu_s {usage.ru_utime + usage.ru_stime:.3f}",
          file=sys.stderr, flush=True)
    if run.conn is None:
        return
    try:
        warm_start.send(run.conn, message)
    except OSError:
        pass
    run.conn.close()


def _client_gone(conn: socket.socket, runs: dict[int, Run]) -> None:
    """The client died (kill -9, its terminal closed): its run is killed as a killed cold command is."""
    for run in runs.values():
        if run.conn is conn:
            os.kill(run.pid, signal.SIGKILL)  # not reaped yet: the pid is still the run's
            run.conn = None
    conn.close()


def _run(request: dict, fds: list[int], keep: socket.socket, close: list[int]) -> None:
    """The forked run: become the client's command, run it, leave with its status (never returns)."""
    code = 1
    try:
        os.setpgid(0, 0)  # the run and its workers: one group, which the client's Ctrl-Z stops
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for s in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(s, signal.SIG_DFL)
        keep.close()
        for fd in close:
            os.close(fd)
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        _adopt(request)
        warm_start.serving = True
        from services.cli.main import run_command

        code = run_command(request["argv"])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except BaseException:
        traceback.print_exc()
    try:
        atexit._run_exitfuncs()  # what a cold command runs at its exit (logging, multiprocessing)
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


def _adopt(request: dict) -> None:
    """The client's process state: folder, environment, umask, CPU affinity, standard streams, argv."""
    from services.worker.process.numeric_threads import pin_numeric_threads

    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    pin_numeric_threads()  # as the cold command's import of generate does
    os.umask(request["umask"])
    os.sched_setaffinity(0, request["affinity"])
    tempfile.tempdir = None  # read again from this environment
    encoding = sys.stdout.encoding
    sys.stdin = open(0, closefd=False, encoding=encoding)
    sys.stdout = open(1, "w", buffering=1 if os.isatty(1) else -1, closefd=False, encoding=encoding)
    sys.stderr = open(2, "w", buffering=1, closefd=False, encoding=encoding, errors="backslashreplace")
    sys.argv = ["omnidata", *request["argv"]]
    logging.getLogger().handlers.clear()  # `generate` configures logging itself


if __name__ == "__main__":
    serve(Path(sys.argv[1]), sys.argv[2])
