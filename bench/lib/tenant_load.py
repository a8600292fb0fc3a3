"""One tenant's heavy load against another's reads (issue 51): the `tenants` scenario of
bench/api/health_load.py.

Tenant 0 (the loud one) uploads 10 copies of the ICL living room and gets a job whose manifest is several
MB (a synthetic plan, its tasks marked done with long keys); tenant 1 (the quiet one) has a small job. A
prober in this process GETs /health and tenant 1's GET /jobs/{id} in turn, every 20 ms, over keep-alive
connections, while the loud tenant, from separate processes:
- up_choice: runs 40 concurrent `PUT /spaces/{id}/up` over its 10 rooms (each loads the mesh), in a loop; a
  429 is retried after its Retry-After (at most 1 s), as a well-behaved client would;
- stalled_manifest: opens 45 readers of its manifest.jsonl that read the first bytes and then stop reading
  (small receive buffers: the server's writes block within a few KB);
- views_burst: runs 20 concurrent `GET /jobs/{id}/views?limit=1000&urls=true` in a loop.
Per phase: /health and the other tenant's GET p50/p99/max, the other tenant's non-200 answers, and the loud
tenant's answers by status. All on 127.0.0.1, every loop bounded by the phase's time.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import secrets
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from bench.scale.fanout import percentiles
from services.core.db.engine import make_engine, make_sessionmaker

REPO = Path(__file__).resolve().parents[2]
ROOM = REPO.parent / "shared" / "scenes" / "icl_livingroom" / "livingroom.obj"
BUNNY = REPO.parent / "shared" / "scenes" / "stanford_bunny" / "bun_zipper_res2.ply"
ROOMS = 10
UP_CLIENTS = 40
STALLED_READERS = 45
VIEW_CLIENTS = 20
PHASE_S = {"idle": 5.0, "up_choice": 20.0, "stalled_manifest": 15.0, "views_burst": 15.0}
SPEC = {"name": "bench", "points": {"count": 2, "min_views": 1}, "accept_up_guess": True}
MANIFEST_POINTS, MANIFEST_VIEWS = 800, 3  # 2,400 views x ~17 done cues: a manifest of several MB


def _auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _setup(base: str, db_url: str, loud: str, quiet: str) -> tuple[list[int], int, int]:
    """The loud tenant's rooms and big job, the quiet tenant's small job: (room ids, loud job, quiet job)."""
    from tests.fixtures.api import fake_plan, mark_all_done

    rooms = []
    with httpx.Client(timeout=600) as client:
        for k in range(ROOMS):
            r = client.post(f"{base}/spaces", files={"file": (f"room{k}.obj", ROOM.read_bytes())},
                            headers=_auth(loud))
            assert r.status_code == 201, r.text
            rooms.append(r.json()["id"])
        r = client.post(f"{base}/jobs", json={"space_ids": rooms[:1], "spec": SPEC}, headers=_auth(loud))
        assert r.status_code == 201, r.text
        loud_job = r.json()["id"]
        r = client.post(f"{base}/spaces", files={"file": ("bunny.ply", BUNNY.read_bytes())},
                        headers=_auth(quiet))
        assert r.status_code == 201, r.text
        r = client.post(f"{base}/jobs", json={"space_ids": [r.json()["id"]], "spec": SPEC},
                        headers=_auth(quiet))
        assert r.status_code == 201, r.text
        quiet_job = r.json()["id"]
    engine = make_engine(db_url)
    with make_sessionmaker(engine)() as session:
        fake_plan(session, loud_job, points=MANIFEST_POINTS, views=MANIFEST_VIEWS)
        mark_all_done(session, loud_job)
    engine.dispose()
    return rooms, loud_job, quiet_job


def probe(base: str, quiet: str, quiet_job: int, seconds: float) -> dict[str, Any]:
    """/health and the quiet tenant's GET /jobs/{id} in turn, every 20 ms: latencies, its non-200 answers."""
    health: list[float] = []
    reads: list[float] = []
    failed: Counter[str] = Counter()
    with httpx.Client(timeout=60) as client:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for url, out, headers in ((f"{base}/health", health, {}),
                                      (f"{base}/jobs/{quiet_job}", reads, _auth(quiet))):
                t = time.perf_counter()
                try:
                    code = client.get(url, headers=headers).status_code
                except httpx.HTTPError as e:
                    code = type(e).__name__
                out.append(time.perf_counter() - t)
                if code != 200:
                    failed[str(code)] += 1
            time.sleep(0.02)
    return {"health": percentiles(health), "other_tenant_get_job": percentiles(reads),
            "other_tenant_not_200": dict(failed)}


def up_choice_load(base: str, token: str, rooms: list[int], stop: Any, codes: Any) -> None:
    """UP_CLIENTS concurrent PUT /spaces/{id}/up over the rooms until `stop`; counts answers by status."""
    seen: Counter[int] = Counter()

    async def one(client: httpx.AsyncClient, k: int) -> None:
        while not stop.is_set():
            r = await client.put(f"{base}/spaces/{rooms[k % len(rooms)]}/up", json={}, headers=_auth(token))
            seen[r.status_code] += 1
            if r.status_code == 429:
                await asyncio.sleep(min(1.0, float(r.headers.get("retry-after", "1"))))

    async def main() -> None:
        limits = httpx.Limits(max_connections=UP_CLIENTS)
        async with httpx.AsyncClient(timeout=httpx.Timeout(600.0), limits=limits) as client:
            await asyncio.gather(*(one(client, k) for k in range(UP_CLIENTS)))

    asyncio.run(main())
    codes.update(dict(seen))


def stalled_readers(base: str, token: str, job: int, ready: Any, stop: Any, codes: Any) -> None:
    """STALLED_READERS manifest readers that read the status line and then stop reading until `stop`."""
    host, port = base.removeprefix("http://").split(":")
    seen: Counter[str] = Counter()
    socks = []
    for _ in range(STALLED_READERS):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # the server's writes block within KBs
        sock.settimeout(60)
        sock.connect((host, int(port)))
        sock.sendall(f"GET /jobs/{job}/manifest.jsonl HTTP/1.1\r\nHost: {host}\r\n"
                     f"Authorization: Bearer {token}\r\n\r\n".encode())
        socks.append(sock)
    for sock in socks:
        try:
            seen[sock.recv(64).split(b" ", 2)[1].decode()] += 1  # "HTTP/1.1 200 OK"
        except (OSError, IndexError):
            seen["no answer"] += 1
    ready.set()
    stop.wait(300)
    for sock in socks:
        sock.close()
    codes.update(dict(seen))


def views_burst(base: str, token: str, job: int, stop: Any, codes: Any) -> None:
    """VIEW_CLIENTS concurrent GET /jobs/{id}/views?limit=1000&urls=true until `stop`."""
    seen: Counter[int] = Counter()

    async def one(client: httpx.AsyncClient) -> None:
        while not stop.is_set():
            r = await client.get(f"{base}/jobs/{job}/views", params={"limit": 1000, "urls": "true"},
                                 headers=_auth(token))
            seen[r.status_code] += 1
            if r.status_code == 429:
                await asyncio.sleep(min(1.0, float(r.headers.get("retry-after", "1"))))

    async def main() -> None:
        limits = httpx.Limits(max_connections=VIEW_CLIENTS)
        async with httpx.AsyncClient(timeout=httpx.Timeout(600.0), limits=limits) as client:
            await asyncio.gather(*(one(client) for _ in range(VIEW_CLIENTS)))

    asyncio.run(main())
    codes.update(dict(seen))


@contextlib.contextmanager
def _running(target: Callable[..., None], *args: Any) -> Iterator[dict[str, int]]:
    """`target(*args, stop, codes)` in a spawned process until the block ends; yields a dict that then holds
    the load's answers by status."""
    ctx = mp.get_context("spawn")
    manager = ctx.Manager()
    stop, codes = manager.Event(), manager.dict()
    answers: dict[str, int] = {}
    proc = ctx.Process(target=target, args=(*args, stop, codes), daemon=True)
    proc.start()
    try:
        yield answers
    finally:
        stop.set()
        proc.join(120)
        if proc.is_alive():
            proc.kill()
        answers.update({str(k): v for k, v in codes.copy().items()})
        manager.shutdown()


def tenants_scenario(results: dict[str, Any], served: Callable[..., Any]) -> None:
    """Fill `results` with the issue 51 phases (see the module docstring)."""
    loud, quiet = secrets.token_urlsafe(16), secrets.token_urlsafe(16)
    results.update(up_clients=UP_CLIENTS, rooms=ROOMS, room=ROOM.name, stalled_readers=STALLED_READERS,
                   view_clients=VIEW_CLIENTS)
    with served([loud, quiet]) as (base, db_url, _tmp):
        t0 = time.monotonic()
        rooms, loud_job, quiet_job = _setup(base, db_url, loud, quiet)
        results["setup_s"] = round(time.monotonic() - t0, 1)
        with httpx.Client(timeout=120) as client:
            r = client.get(f"{base}/jobs/{loud_job}/manifest.jsonl", headers=_auth(loud))
            results["manifest_bytes"] = len(r.content)
        results["tenants_idle"] = probe(base, quiet, quiet_job, PHASE_S["idle"])
        with _running(up_choice_load, base, loud, rooms) as answers:
            results["up_choice"] = probe(base, quiet, quiet_job, PHASE_S["up_choice"])
        results["up_choice"]["loud_tenant_answers"] = answers
        ready = mp.get_context("spawn").Event()
        with _running(stalled_readers, base, loud, loud_job, ready) as answers:
            assert ready.wait(120), "the stalled readers did not start"
            results["stalled_manifest"] = probe(base, quiet, quiet_job, PHASE_S["stalled_manifest"])
        results["stalled_manifest"]["loud_tenant_answers"] = answers
        with _running(views_burst, base, loud, loud_job) as answers:
            results["views_burst"] = probe(base, quiet, quiet_job, PHASE_S["views_burst"])
        results["views_burst"]["loud_tenant_answers"] = answers
