"""/health latency under load (issue 19 section 3): 200 event-stream clients, then 50 concurrent uploads on
top.

`omnidata serve` (one uvicorn process, Postgres, a local folder store) on loopback. Load comes from separate
processes so the prober's own event loop is not the one under load:
- streams: 10 tenants x 20 `/events` streams each (the per-tenant cap, OMNIDATA_SSE_MAX_PER_TENANT=20), read
  continuously; one more stream per tenant is attempted and must get 429;
- uploads: 50 clients uploading the bunny (660 KB PLY) to POST /spaces concurrently, each a bounded number of
  times (every upload is parsed in its own capped child process on the server); a 429 (a tenant's uploads
  beyond OMNIDATA_TENANT_SCAN_CONCURRENCY) is retried after its Retry-After.
The prober GETs /health every 20 ms over one keep-alive connection: p50/p99/max per phase (idle, streams,
streams + uploads). All on 127.0.0.1, every loop bounded.

`--scenario tenants` (issue 51, bench/lib/tenant_load.py): one tenant's 40 concurrent up choices, 45 stalled
manifest readers and 20 concurrent `views?limit=1000&urls=true`, against /health and another tenant's GET
/jobs/{id}.

Appends a run to bench/results/health_load.json.
Run: .venv/bin/python bench/api/health_load.py [--scenario tenants]  (about 1.5 minutes; tenants: about 2)
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import platform
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import add_run, results_dir  # noqa: E402
from bench.lib.smoke import SMOKE, SMOKE_HELP  # noqa: E402
from bench.scale.fanout import create_database, drop_database, percentiles  # noqa: E402
from services.core.db.engine import migrate  # noqa: E402
from services.core.settings import hash_token  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BUNNY = REPO.parent / "shared" / "scenes" / "stanford_bunny" / "bun_zipper_res2.ply"
OUT = results_dir() / "health_load.json"
TENANTS = 2 if SMOKE else 10
STREAMS_PER_TENANT = 2 if SMOKE else 20
UPLOADERS = 2 if SMOKE else 50
UPLOADS_EACH = 1 if SMOKE else 2
PHASE_S = {"idle": 5.0, "streams": 15.0, "streams_and_uploads": 30.0}
if SMOKE:
    PHASE_S = dict.fromkeys(PHASE_S, 1.0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def hold_streams(base: str, tokens: list[str], ready: Any, stop: Any, refused: Any) -> None:
    """Open STREAMS_PER_TENANT streams per tenant and read them until `stop`; count the 429s of one more
    each."""
    async def one(client: httpx.AsyncClient, token: str, opened: asyncio.Event) -> None:
        async with client.stream("GET", f"{base}/events?token={token}") as r:
            opened.set()
            async for _ in r.aiter_bytes():
                if stop.is_set():
                    return

    async def main() -> None:
        limits = httpx.Limits(max_connections=TENANTS * (STREAMS_PER_TENANT + 2))
        async with httpx.AsyncClient(timeout=httpx.Timeout(60.0), limits=limits) as client:
            events = []
            tasks = []
            for token in tokens:
                for _ in range(STREAMS_PER_TENANT):
                    ev = asyncio.Event()
                    events.append(ev)
                    tasks.append(asyncio.create_task(one(client, token, ev)))
            await asyncio.wait_for(asyncio.gather(*(e.wait() for e in events)), 60)
            for token in tokens:
                r = await client.get(f"{base}/events?token={token}")
                refused.value += int(r.status_code == 429)
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.2)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())


def upload_load(base: str, tokens: list[str], done: Any) -> None:
    """UPLOADERS concurrent clients, each uploading the bunny UPLOADS_EACH times."""
    body = BUNNY.read_bytes()

    async def one(client: httpx.AsyncClient, k: int) -> None:
        token = tokens[k % len(tokens)]
        for n in range(UPLOADS_EACH):
            while True:  # a tenant has a few uploads under way at once (429 beyond): wait as told, then retry
                r = await client.post(f"{base}/spaces", files={"file": (f"bunny-{k}-{n}.ply", body)},
                                      headers={"Authorization": f"Bearer {token}"})
                if r.status_code != 429:
                    break
                await asyncio.sleep(float(r.headers.get("retry-after", "1")))
            done.value += int(r.status_code == 201)

    async def main() -> None:
        async with httpx.AsyncClient(
            timeout=httpx.Timeout(300.0), limits=httpx.Limits(max_connections=UPLOADERS)
        ) as c:
            await asyncio.gather(*(one(c, k) for k in range(UPLOADERS)))

    asyncio.run(main())


def probe(base: str, seconds: float) -> list[float]:
    """/health latencies (s), one request every 20 ms for `seconds`."""
    out = []
    with httpx.Client(timeout=30) as client:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t = time.perf_counter()
            r = client.get(f"{base}/health")
            out.append(time.perf_counter() - t)
            assert r.status_code == 200
            time.sleep(0.02)
    return out


def summary(seconds: list[float]) -> dict[str, float]:
    return percentiles(seconds)


@contextlib.contextmanager
def served(tokens: list[str], env_extra: dict[str, str] | None = None) -> Iterator[tuple[str, str, Path]]:
    """`omnidata serve` on a fresh database and store, tenants tenant-0.. of `tokens`: (base, db URL, tmp)."""
    url = create_database()
    tmp = Path(tempfile.mkdtemp(prefix="bench-health-"))
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")}
    env.update(
        OMNIDATA_DATABASE_URL=url, OMNIDATA_STORAGE_URL=f"file://{tmp / 'store'}", OMNIDATA_DATA_DIR=str(tmp),
        OMNIDATA_BROKER_URL=os.environ.get("OMNIDATA_BENCH_REDIS_URL", "redis://127.0.0.1:6379/4"),
        OMNIDATA_API_TOKENS=json.dumps({hash_token(t): f"tenant-{k}" for k, t in enumerate(tokens)}),
        **(env_extra or {}),
    )
    server = None
    try:
        migrate(url)
        server = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--port", str(port), "--log-level", "warning"],
            cwd=REPO, env=env, start_new_session=True, stdout=(tmp / "api.log").open("ab"),
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, (tmp / "api.log").read_text()[-2000:]
            time.sleep(0.3)
        yield base, url, tmp
    finally:
        if server is not None:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(30)
        drop_database(url)


def streams_scenario(results: dict[str, Any]) -> None:
    """/health while 200 event streams are open, then with 50 uploaders on top (issue 19)."""
    tokens = [secrets.token_urlsafe(16) for _ in range(TENANTS)]
    results.update(streams=TENANTS * STREAMS_PER_TENANT, uploaders=UPLOADERS)
    ctx = mp.get_context("spawn")
    # the server's cap is the streams each tenant holds: the one more each opens is refused (429)
    with served(tokens, {"OMNIDATA_SSE_MAX_PER_TENANT": str(STREAMS_PER_TENANT)}) as (base, _url, _tmp):
        results["idle"] = summary(probe(base, PHASE_S["idle"]))
        ready, stop, refused, uploaded = ctx.Event(), ctx.Event(), ctx.Value("i", 0), ctx.Value("i", 0)
        streams = ctx.Process(target=hold_streams, args=(base, tokens, ready, stop, refused), daemon=True)
        streams.start()
        assert ready.wait(90), "the streams did not open"
        results["streams_refused_over_cap"] = refused.value  # one attempt per tenant beyond its cap
        results["with_streams"] = summary(probe(base, PHASE_S["streams"]))
        uploads = ctx.Process(target=upload_load, args=(base, tokens, uploaded), daemon=True)
        t0 = time.monotonic()
        uploads.start()
        results["with_streams_and_uploads"] = summary(probe(base, PHASE_S["streams_and_uploads"]))
        uploads.join(240)
        results["uploads_201"] = uploaded.value
        results["uploads_wall_s"] = round(time.monotonic() - t0, 1)
        stop.set()
        streams.join(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", choices=["streams", "tenants"], default="streams",
                        help="streams: 200 event streams + 50 uploaders (issue 19); tenants: one tenant's "
                        "up-choice storm, stalled manifest readers and views bursts against another tenant's "
                        "reads (issue 51)")
    parser.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = parser.parse_args()
    machine = f"{platform.node()} ({os.cpu_count()} cores, loaded by other developers' work)"
    results: dict[str, Any] = {"machine": machine, "scenario": args.scenario}
    if args.scenario == "streams":
        streams_scenario(results)
    else:
        from bench.lib.tenant_load import tenants_scenario

        tenants_scenario(results, served)
    results["load_avg_end"] = [round(x, 2) for x in os.getloadavg()]  # 1, 5, 15 min: the machine is shared
    results["label"] = os.environ.get("BENCH_LABEL", "")
    print(json.dumps(results, indent=1))
    add_run(OUT, results, default_scenario="streams")


if __name__ == "__main__":
    main()
