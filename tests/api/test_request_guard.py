"""Request bodies: the token and the size are checked before a body is read; 422s never echo a huge input."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from urllib.parse import urlparse

import httpx

from services.core.storage import LocalStore
from tests.fixtures.api import Api, live_server, make_api

BIG = 50 * 1024**2


def _raw_post(base: str, path: str, headers: dict[str, str], declared: int, sent: bytes) -> tuple[int, float]:
    """POST declaring `declared` body bytes but sending only `sent`; (status, seconds to the response)."""
    u = urlparse(base)
    with socket.create_connection((u.hostname, u.port), timeout=10) as s:
        head = (
            f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: "
            f"{declared}\r\n"
        )
        head += "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n"
        t0 = time.monotonic()
        s.sendall(head.encode() + sent)
        reply = s.recv(4096).decode("latin-1")
        return int(reply.split(" ", 2)[1]), time.monotonic() - t0


def test_a_body_without_a_token_is_refused_before_it_is_read(api: Api) -> None:
    health_times: list[float] = []
    with live_server(api.app) as base:
        stop = threading.Event()

        def poll_health() -> None:
            with httpx.Client(base_url=base) as c:
                while not stop.is_set():
                    t0 = time.monotonic()
                    assert c.get("/health").status_code == 200
                    health_times.append(time.monotonic() - t0)

        t = threading.Thread(target=poll_health)
        t.start()
        try:
            # 50 MB declared, 1 MB sent: the answer comes without waiting for (or parsing) the rest
            code, _ = _raw_post(base, "/jobs", {}, BIG, b"[" * 2**20)
            assert code == 401
            code, _ = _raw_post(base, "/jobs", {"Authorization": "Bearer wrong"}, BIG, b"[" * 2**20)
            assert code == 401
            # with a valid token the declared size alone is enough for a 413
            code, _ = _raw_post(base, "/jobs", api.a.headers, BIG, b"[" * 2**20)
            assert code == 413
            # a chunked body (no Content-Length) is counted and cut off at the limit
            def chunks() -> Iterator[bytes]:
                for _ in range(50):
                    yield b" " * 2**20

            r = httpx.post(
                f"{base}/jobs", content=chunks(),
                headers={**api.a.headers, "Content-Type": "application/json"},
            )
            assert r.status_code == 413 and "OMNIDATA_REQUEST_MAX_BYTES" in r.json()["detail"]
        finally:
            # the posts can all be answered before the poller's first request is (a loaded machine): let it
            # finish one
            deadline = time.monotonic() + 10
            while not health_times and t.is_alive() and time.monotonic() < deadline:
                time.sleep(0.01)
            stop.set()
            t.join()
        assert health_times and httpx.get(f"{base}/health").status_code == 200
    # ordinary requests still work through the guard
    r = api.client.post("/jobs", json={"space_ids": [10**9]}, headers=api.a.headers)
    assert r.status_code == 404


def test_validation_errors_do_not_echo_huge_inputs(pg_url: str, local_store: LocalStore) -> None:
    with make_api(pg_url, local_store, request_max_bytes=64 * 1024**2) as api:
        huge = "x" * (5 * 1024**2)
        bodies = [
            {"space_ids": [1], "spec": {"name": huge}},
            {"space_ids": [1], "spec": {"cues": [huge]}},
            {"space_ids": [1], "spec": {huge: 1}},  # an unknown field named by the input
            {"space_ids": [1], "spec": {"cues": [f"c{i}" for i in range(10_000)]}},
            {"space_ids": [1], "spec": {"params": {"keypoints2d_sigmas": [1e9] * 100_000}}},
        ]
        for body in bodies:
            r = api.client.post(
                "/jobs", content=json.dumps(body),
                headers={**api.a.headers, "Content-Type": "application/json"},
            )
            assert r.status_code == 422, r.text[:300]
            assert len(r.content) < 20_000, (len(r.content), r.text[:300])
            assert r.json()["detail"]


def test_many_errors_are_listed_up_to_a_limit_and_counted(api: Api) -> None:
    body = {
        "space_ids": [1], "spec": {"cues": [f"c{i}" for i in range(5)], **{f"x{i}": 1 for i in range(50)}},
    }
    r = api.client.post("/jobs", json=body, headers=api.a.headers)
    assert r.status_code == 422
    # 51 errors: the cues and 50 unknown fields, r.json()["detail"][-80:]
    assert len(r.json()["errors"]) == 20 and r.json()["detail"].endswith("... and 41 more")
