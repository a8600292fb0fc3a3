"""The designer's warm processes: a few long-lived children that plan specs and render small previews.

Why warm processes and not the render queue: a preview wants 4 views of 96 px now, while the workers are busy
with jobs' 512 px views (seconds each) and a task goes through the database, the broker and object storage;
and a cold process needs 3-7 s (imports, Blender, the room's scene) before its first pixel. A warm child keeps
the loaded space, its last plans and its Blender scene: on the ICL room a knob change costs a plan (0.3-0.5 s
for 500 views) and 16 small renders (0.05-0.1 s). The pool is bounded (OMNIDATA_DESIGNER_PROCESSES), a call
waits for a free process in a thread, and each answer is awaited within OMNIDATA_DESIGNER_TIMEOUT_S: a process
past it is killed (the plan or render stops at once) and the next call starts a fresh one. The API itself
never imports the planner or Blender: the child runs the function named by TARGET.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import threading
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from services.core.domain.errors import Invalid

log = logging.getLogger("omnidata.designer")

TARGET = "services.embedded.design_preview:serve"
# where `services` is imported from, for the child (a checkout run without installing it)
_SOURCE_ROOT = str(Path(__file__).resolve().parents[3])


class DesignFailed(RuntimeError):
    """The preview process failed for a reason other than the spec (it crashed, or a bug)."""


class _Child:
    """A fresh interpreter (not a fork of the API's threads, and not a multiprocessing spawn, which would run
    the API's main module again) serving TARGET over a socket pair; it exits when its socket closes."""

    def __init__(self) -> None:
        mine, theirs = socket.socketpair()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            p for p in (_SOURCE_ROOT, os.environ.get("PYTHONPATH")) if p))
        with theirs:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "services.core.named_call", TARGET, str(theirs.fileno())],
                pass_fds=[theirs.fileno()], env=env, stdin=subprocess.DEVNULL)
        self.conn = Connection(mine.detach())
        self.owed = 0  # answers to requests sent without waiting (the warm-up), read before the next request

    def alive(self) -> bool:
        return self.process.poll() is None

    def end(self) -> None:
        self.conn.close()
        if self.alive():
            self.process.kill()
        self.process.wait(5)


class DesignPool:
    """At most `size` warm designer processes, each serving one call at a time; a tenant's calls take one
    process at a time, so with two or more another tenant's call never waits behind a tenant's slow plans."""

    def __init__(self, size: int, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._slots = threading.BoundedSemaphore(size)
        self._idle: list[_Child] = []
        self._children: list[_Child] = []  # every process started, to end them all at shutdown
        self._lock = threading.Lock()
        self._tenants: dict[str, threading.Lock] = {}

    def call(self, kind: str, payload: dict[str, Any], *, tenant: str = "") -> dict[str, Any]:
        """The answer of a warm process to (kind, payload): Invalid for a spec the spaces cannot meet or one
        that runs past the time budget, DesignFailed when the process fails. Blocks: call it from a thread."""
        with self._lock:
            turn = self._tenants.setdefault(tenant, threading.Lock())
        with turn, self._slots:
            with self._lock:
                child = self._idle.pop() if self._idle else None
            if child is None or not child.alive():
                child = _Child()
                with self._lock:
                    self._children = [c for c in self._children if c.alive()] + [child]
            try:
                while child.owed:  # a warming process: its warm-up first (the imports this call needs)
                    self._answer(child, "warm-up")
                    child.owed -= 1
                child.conn.send((kind, payload))
                outcome, value = self._answer(child, kind)
            except (EOFError, OSError) as e:
                child.end()
                raise DesignFailed(
                    f"the designer's process ended during a {kind} (exit code {child.process.poll()})"
                ) from e
            with self._lock:
                self._idle.append(child)
        if outcome == "invalid":
            raise Invalid(value)
        if outcome != "ok":
            raise DesignFailed(value)
        return dict(value)

    def _answer(self, child: _Child, kind: str) -> tuple[str, Any]:
        """The next answer of `child`, within the time budget (Invalid past it: the process is ended)."""
        if not child.conn.poll(self.timeout_s):
            child.end()
            raise Invalid(
                f"the designer's {kind} took longer than {self.timeout_s:g} s "
                "(OMNIDATA_DESIGNER_TIMEOUT_S): lower points.count or points.max_views"
            )
        outcome, value = child.conn.recv()
        if outcome not in ("ok", "invalid"):
            log.warning("designer %s failed: %s", kind, value)
        return outcome, value

    def warm(self) -> None:
        """Start a process that loads its imports and Blender now, unless one was started: the first call
        waits for that warm-up rather than starting a second cold process beside it (returns at once)."""
        with self._lock:
            if self._children:
                return
            child = _Child()
            self._children.append(child)
            child.conn.send(("warm", {}))
            child.owed = 1
            self._idle.append(child)

    def close(self) -> None:
        """End the processes (the API is shutting down)."""
        with self._lock:
            children, self._children, self._idle = self._children, [], []
        for child in children:
            child.end()
