"""Benchmark: what a hostile request body costs the API (issue 11, bug 3), on a real uvicorn process.

Starts `uvicorn services.api.app:app_from_env` from `--repo` (default: this checkout; pass another checkout to
compare) on a fresh SQLite database, then sends 50 MB JSON bodies to POST /jobs (without a token, and with
one) while a client polls /health, and a spec with a 5 MB field (422). Reports per case the status, seconds
until the answer, the worst /health latency meanwhile, the size of the answer, and the server's peak resident
memory.

Writes bench/results/hostile_requests.json. Run: .venv/bin/python bench/api/hostile_requests.py [--repo DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import secrets
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.db.engine import migrate  # noqa: E402
from services.core.settings import hash_token  # noqa: E402

BODY_MB = 50


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _post(port: int, body: bytes, headers: dict[str, str]) -> tuple[int, float, int]:
    """POST /jobs with `body` over a raw socket; (status, seconds to the answer, answer bytes)."""
    head = (
        f"POST /jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\n"
    )
    head += "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "Connection: close\r\n\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=120) as s:
        t0 = time.monotonic()

        def send() -> None:
            try:
                s.sendall(head.encode() + body)
            except OSError:  # the server answered early and closed: what a guard should do
                pass

        sender = threading.Thread(target=send)
        sender.start()
        reply = b""
        first = None
        try:
            while chunk := s.recv(1 << 16):
                first = first or time.monotonic()
                reply += chunk
        except ConnectionResetError:  # closed while our body was still arriving: the answer came first
            pass
        sender.join()
    status = int(reply.split(b" ", 2)[1]) if reply else 0
    return status, (first or time.monotonic()) - t0, len(reply)


def _measure(port: int, pid: int, body: bytes, headers: dict[str, str]) -> dict[str, Any]:
    worst = [0.0]
    stop = threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as c:
            while not stop.is_set():
                t0 = time.monotonic()
                c.get("/health")
                worst[0] = max(worst[0], time.monotonic() - t0)
                time.sleep(0.01)

    poller = threading.Thread(target=poll)
    poller.start()
    status, seconds, size = _post(port, body, headers)
    time.sleep(0.3)
    stop.set()
    poller.join()
    return {"status": status, "answer_s": round(seconds, 3), "answer_bytes": size,
            "health_worst_ms": round(worst[0] * 1000, 1), "server_peak_rss_mb": round(_peak_rss_mb(pid), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[2])
    ap.add_argument("--out", type=Path, default=results_dir() / "hostile_requests.json")
    args = ap.parse_args()
    token = secrets.token_urlsafe(24)
    with tempfile.TemporaryDirectory(prefix="omnidata-bench-") as tmp:
        db = f"sqlite:///{tmp}/api.db"
        migrate(db)
        port = _free_port()
        env = {**os.environ, "PYTHONPATH": str(args.repo.resolve()), "OMNIDATA_DATABASE_URL": db,
               "OMNIDATA_STORAGE_URL": Path(tmp, "objects").as_uri(), "OMNIDATA_DATA_DIR": tmp,
               "OMNIDATA_API_TOKENS": json.dumps({hash_token(token): "bench"})}
        server = subprocess.Popen(
            [
                sys.executable, "-m", "uvicorn", "--factory", "services.api.app:app_from_env", "--port",
                str(port), "--log-level", "warning",
            ],
            env=env, cwd=args.repo,
        )
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    if httpx.get(f"http://127.0.0.1:{port}/health").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError("the API did not start")
                time.sleep(0.2)
            big = json.dumps(
                {"space_ids": [1], "spec": {"cues": ["x" * 64] * (BODY_MB * 2**20 // 70)}}
            ).encode()
            field = json.dumps({"space_ids": [1], "spec": {"name": "x" * (5 * 2**20)}}).encode()
            auth = {"Authorization": f"Bearer {token}"}
            results = {
                "idle_rss_mb": round(_peak_rss_mb(server.pid), 1),
                f"{BODY_MB}mb_body_without_token": _measure(port, server.pid, big, {}),
                f"{BODY_MB}mb_body_with_token": _measure(port, server.pid, big, auth),
                "5mb_field_with_token": _measure(port, server.pid, field, auth),
            }
        finally:
            server.terminate()
            server.wait(10)
    report = {"repo": str(args.repo), "machine": platform.node(), "cpus": os.cpu_count(), **results}
    print(json.dumps(report, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
