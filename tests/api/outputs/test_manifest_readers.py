"""Readers of manifest.jsonl that stop reading hold no database connection: with more of them stalled than the
pool has connections, none is checked out while they stall, another tenant's request is answered, and each
stalled stream is still whole."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from sqlalchemy import Engine

from services.core.db.engine import make_engine
from services.core.storage import LocalStore
from tests.fixtures.api import Api, live_server, make_api, mark_all_done, planned_job
from tests.fixtures.waiting import wait_until

POOL = 2
READERS = 5  # more than the pool's connections
POINTS, VIEWS = 400, 3  # 1,200 lines of ~2.5 KB: MBs, far more than the socket buffers of a stalled reader


@dataclass
class SmallPool:
    api: Api
    engine: Engine  # the API's, POOL connections: what the stalled readers must not hold


@pytest.fixture()
def small_pool(pg_url: str, local_store: LocalStore) -> Iterator[SmallPool]:
    # a stream gives its connection back once the socket buffers are full: on a loaded 2-core host that took
    # over 3 s, and the next reader's wait for the pool was answered 503; a stream that kept its connection
    # would still hold it after 30 s (`pool.checkedout()` below)
    engine = make_engine(pg_url, pool_size=POOL, max_overflow=0, pool_timeout=30)
    try:
        with make_api(pg_url, local_store, engine=engine, tenant_bulk_concurrency=READERS) as api:
            yield SmallPool(api, engine)
    finally:
        engine.dispose()


def _stalled_reader(base: str, path: str, token: str) -> socket.socket:
    """A client that sends the request, reads the status line and then stops reading."""
    host, port = base.removeprefix("http://").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # set before connecting: it bounds the window
    sock.settimeout(30)
    sock.connect((host, int(port)))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {token}\r\n"
                 "Connection: close\r\n\r\n".encode())
    assert sock.recv(12) == b"HTTP/1.1 200"
    return sock


def _rest_of_body(sock: socket.socket) -> bytes:
    """Read the rest of a chunked response until the server closes; its body, de-chunked."""
    data = bytearray()
    while True:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)  # no 40 ms delayed ACK per window of 4 KB
        chunk = sock.recv(1 << 16)
        if not chunk:
            break
        data += chunk
    body = bytearray()
    rest = bytes(data).split(b"\r\n\r\n", 1)[1]
    while True:
        size_line, rest = rest.split(b"\r\n", 1)
        size = int(size_line, 16)
        if size == 0:
            return bytes(body)
        body += rest[:size]
        rest = rest[size + 2:]


def test_stalled_manifest_readers_hold_no_connection(small_pool: SmallPool, bunny: Path) -> None:
    api, pool = small_pool.api, small_pool.engine.pool
    loud = planned_job(api, api.a, bunny, points=POINTS, views=VIEWS)
    with api.session() as session:
        mark_all_done(session, loud)
    quiet = planned_job(api, api.b, bunny)
    with live_server(api.app) as base:
        readers = [_stalled_reader(base, f"/jobs/{loud}/manifest.jsonl", api.a.token) for _ in range(READERS)]
        try:
            # each stream sends what the sockets take (far less than its body), then waits for its reader: a
            # stream that kept its connection while it waits would keep it checked out for good
            wait_until(lambda: pool.checkedout() == 0, 30.0, "the stalled streams to give back connections")
            other = httpx.get(f"{base}/jobs/{quiet}", headers=api.b.headers, timeout=30)
            assert other.status_code == 200, other.text  # was a 500 after the pool's timeout
            own = httpx.get(f"{base}/jobs/{loud}", headers=api.a.headers, timeout=30)
            assert own.status_code == 200  # the stalled tenant's own small reads go on too
            more = httpx.get(f"{base}/jobs/{loud}/manifest.jsonl", headers=api.a.headers, timeout=30)
            # but not one more bulk read
            assert more.status_code == 429 and more.headers["retry-after"] == "1"
            assert "OMNIDATA_TENANT_BULK_CONCURRENCY" in more.json()["detail"]
            body = _rest_of_body(readers[0])  # a stalled stream resumes and is whole
        finally:
            for sock in readers:
                sock.close()
    lines = [json.loads(line) for line in body.decode().splitlines()]
    assert [(x["point"], x["view"]) for x in lines] == [(p, v) for p in range(POINTS) for v in range(VIEWS)]
    assert all(x["outputs"] and all(o["size"] == 123456 for o in x["outputs"].values()) for x in lines)
