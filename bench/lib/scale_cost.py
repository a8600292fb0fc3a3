"""What the scale simulation measures besides throughput: the real task grain and the orchestration CPU.

- CUE_SECONDS: seconds of work per task of each cue on one core at 512x512, from the task rows of a real room
  (`omnidata generate` of a 31k-face textured room, issue 20's per-cue figures): the render with every pass
  ~0.3 s, derivations 5-200 ms. A simulated task sleeps its cue's figure times a log-normal jitter.
- ProcessCpu: CPU seconds (user + system, /proc/<pid>/stat) of a set of processes between two readings:
  the scheduler, a private Redis server, the Postgres backends serving the benchmark's database, the
  simulated worker processes. Orchestration CPU per task = (scheduler + Postgres + Redis) / tasks done.
- PrivateRedis: a redis-server of our own on a free port, so its CPU is ours alone (the shared one serves
  seven other developers).
"""

from __future__ import annotations

import math
import os
import random
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

from sqlalchemy import text

# Issue 20's per-cue task time (sum of duration_s / views) on a real room; "the rest < 0.015 each" -> 0.010.
CUE_SECONDS: dict[str, float] = {
    "passes": 0.295, "segment_unsup25d": 0.188, "segment_unsup2d": 0.172, "keypoints3d": 0.098,
    "position": 0.065, "keypoints2d": 0.042, "normal": 0.031, "edge_texture": 0.026,
    "principal_curvature": 0.024, "rgb": 0.022, "edge_occlusion": 0.022,
    "depth_zbuffer": 0.010, "depth_euclidean": 0.010, "mask_valid": 0.010, "reshading": 0.010,
    "fragments": 0.010, "point_info": 0.010, "nonfixated": 0.010, "vanishing_points": 0.010,
}
# The 18 cues of an unlabelled room (every output cue but the three semantic ones); 19 tasks on view 0 with
# passes.
ROOM_CUES = [c for c in CUE_SECONDS if c != "passes"]
JITTER_SIGMA = 0.25  # log-normal spread of one task's time around its cue's mean


def task_seconds(cue: str, rng: random.Random, scale: float = 1.0) -> float:
    """One draw of a task's work time: the cue's mean (unknown cues 10 ms) times a mean-1 log-normal
    factor."""
    mean = CUE_SECONDS.get(cue, 0.010) * scale
    return mean * math.exp(rng.gauss(-JITTER_SIGMA**2 / 2, JITTER_SIGMA))


def mean_task_seconds(cues: Iterable[str], scale: float = 1.0) -> float:
    """Mean work per task of a view with these cues plus its render (what one worker does per task on
    average)."""
    per_view = ["passes", *[c for c in cues if c != "nonfixated"]]
    return scale * sum(CUE_SECONDS.get(c, 0.010) for c in per_view) / len(per_view)


_TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICK  # utime, stime (fields 14, 15 of the whole line)


class ProcessCpu:
    """CPU seconds of named groups of processes between `start()` and `stop()` (a pid new at stop counts from
    0)."""

    def __init__(self) -> None:
        self.first: dict[str, dict[int, float]] = {}
        self.last: dict[str, dict[int, float]] = {}

    def _read(self, groups: dict[str, Iterable[int]]) -> dict[str, dict[int, float]]:
        return {name: {pid: cpu_seconds(pid) for pid in pids} for name, pids in groups.items()}

    def start(self, groups: dict[str, Iterable[int]]) -> None:
        """First reading of every group's processes."""
        self.first = self._read(groups)

    def stop(self, groups: dict[str, Iterable[int]]) -> dict[str, float]:
        """Second reading; CPU seconds used per group in between."""
        self.last = self._read(groups)
        return {name: round(sum(t - self.first.get(name, {}).get(pid, 0.0) for pid, t in now.items()), 3)
                for name, now in self.last.items()}


def backend_pids(session: object) -> dict[str, list[int]]:
    """Pids of the Postgres backends connected to the session's database (ours alone: a database per run), by
    the application_name their client gave (which part of the system they serve)."""
    rows = session.execute(text(  # type: ignore[attr-defined]
        "SELECT application_name, pid FROM pg_stat_activity WHERE datname = current_database() "
        "AND backend_type = 'client backend'"
    ))
    out: dict[str, list[int]] = {}
    for app, pid in rows:
        out.setdefault(f"pg:{app or 'other'}", []).append(int(pid))
    session.rollback()  # type: ignore[attr-defined]
    return out


def with_app_name(url: str, name: str) -> str:
    """The database URL with libpq's application_name set, so its backends' CPU can be told apart."""
    return f"{url}{'&' if '?' in url else '?'}application_name={name}"


def sample_waits(session: object, into: dict[str, int]) -> None:
    """Add what the database's active backends are waiting on now (CPU when nothing) to `into`."""
    for kind, n in session.execute(text(  # type: ignore[attr-defined]
        "SELECT coalesce(wait_event_type || ':' || wait_event, 'CPU'), count(*) FROM pg_stat_activity "
        "WHERE datname = current_database() AND state = 'active' AND pid <> pg_backend_pid() GROUP BY 1"
    )):
        into[kind] = into.get(kind, 0) + int(n)
    session.rollback()  # type: ignore[attr-defined]


class PrivateRedis:
    """A redis-server of our own (no persistence) on a free local port; `url` is its database 0."""

    def __init__(self) -> None:
        exe = shutil.which("redis-server")
        if exe is None:
            raise RuntimeError("redis-server is not on PATH (pass --redis URL to use a running one)")
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = int(s.getsockname()[1])
        self.dir = tempfile.mkdtemp(prefix="omnidata-bench-redis-")
        self.proc = subprocess.Popen(
            [exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", self.dir, "--daemonize", "no"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        self.url = f"redis://127.0.0.1:{self.port}/0"
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                time.sleep(0.05)
        self.close()
        raise RuntimeError("the private redis-server did not start")

    @property
    def pid(self) -> int:
        """The server's process id (for ProcessCpu)."""
        return int(self.proc.pid)

    def close(self) -> None:
        """Stop the server we started and remove its folder."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


def publish_cost(n: int = 20_000, batch: int = 1_000) -> dict[str, float]:
    """CPU per message of the scheduler's CeleryTransport (kombu's pipelined batch publish) and of a private
    Redis."""
    from services.core.settings import get_settings
    from services.scheduler.celery_transport import CeleryTransport

    redis = PrivateRedis()
    try:
        transport = CeleryTransport(settings=get_settings(broker_url=redis.url))
        tasks = [(i, "rgb" if i % 2 else "passes") for i in range(n)]
        transport.send(tasks[:100])  # queues declared, connection open
        own0, redis0, t0 = os.times(), cpu_seconds(redis.pid), time.perf_counter()
        for k in range(0, n, batch):
            transport.send(tasks[k : k + batch])
        own1 = os.times()
        wall = time.perf_counter() - t0
        transport.close()
        return {
            "messages": n, "batch": batch,
            "scheduler_cpu_us_per_message": round(
                1e6 * (own1.user + own1.system - own0.user - own0.system) / n, 1
            ),
            "redis_cpu_us_per_message": round(1e6 * (cpu_seconds(redis.pid) - redis0) / n, 1),
            "wall_us_per_message": round(1e6 * wall / n, 1),
        }
    finally:
        redis.close()
