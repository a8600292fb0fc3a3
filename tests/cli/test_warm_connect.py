"""How a warm-start client finds its server (services.cli.warm_start._connect), with a real lock and a real
Unix socket: it waits for a server that holds the lock and has not bound its socket yet (still importing),
runs cold at once when no server holds the lock, and gives up after STARTING_WAIT_S on one that never
binds."""

from __future__ import annotations

import fcntl
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.cli import warm_start


@pytest.fixture()
def held_lock(tmp_path: Path) -> Iterator[Path]:
    """The lock a starting server holds (flock, as services.cli.warm_server takes it)."""
    lock = tmp_path / "server.lock"
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        yield lock
    finally:
        os.close(fd)


def _bind_later(path: Path, after_s: float) -> tuple[threading.Thread, list[socket.socket]]:
    """A server that binds and listens on `path` after `after_s` seconds (its imports done)."""
    bound: list[socket.socket] = []

    def bind() -> None:
        time.sleep(after_s)
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(str(path))
        server.listen(1)
        bound.append(server)

    thread = threading.Thread(target=bind)
    thread.start()
    return thread, bound


def test_a_client_waits_for_a_server_that_is_still_starting(tmp_path: Path, held_lock: Path) -> None:
    path = tmp_path / "server.sock"
    thread, bound = _bind_later(path, 0.5)
    try:
        sock = warm_start._connect(path, held_lock)
        assert sock is not None, "the client ran cold while a server was starting"
        sock.close()
        assert bound, "connected before the server bound its socket"
    finally:
        thread.join()
        for s in bound:
            s.close()


def test_a_client_runs_cold_without_a_server_and_gives_up_on_one_that_never_binds(
    tmp_path: Path, held_lock: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "server.sock"
    assert warm_start._connect(path, tmp_path / "nobody.lock") is None  # no lock file: no server
    free = tmp_path / "free.lock"
    free.touch()
    assert warm_start._connect(path, free) is None  # nobody holds it: no server is starting
    monkeypatch.setattr(warm_start, "STARTING_WAIT_S", 0.3)
    assert warm_start._connect(path, held_lock) is None  # held, never bound: the client runs cold
