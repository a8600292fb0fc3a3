"""Server-sent progress events against a real uvicorn server: initial snapshot, changes only, heartbeats."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.fixtures.api import Api, fake_plan, live_server, run_tasks, task_ids


class SSEReader:
    """Reads `event:`/`data:` blocks and comment lines from a streaming response."""

    def __init__(self, response: httpx.Response):
        self.lines: Iterator[str] = response.iter_lines()
        self.comments: list[str] = []

    def next_event(self, timeout: float = 10.0) -> tuple[str, dict[str, Any]]:
        deadline = time.monotonic() + timeout
        event, data = None, None
        for line in self.lines:
            if time.monotonic() > deadline:
                break
            if line.startswith(":"):
                self.comments.append(line)
            elif line.startswith("event:"):
                event = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                data = json.loads(line.split(":", 1)[1])
            elif line == "" and event is not None:
                assert data is not None
                return event, data
        raise AssertionError("no event before the deadline")

    def until(self, pred, timeout: float = 10.0) -> dict[str, Any]:  # type: ignore[no-untyped-def]
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ev, data = self.next_event(timeout=deadline - time.monotonic())
            if ev == "job" and pred(data):
                return data
        raise AssertionError("condition not met before the deadline")


@pytest.fixture()
def job_id(api: Api, bunny: Path) -> int:
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    r = api.client.post("/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}}, headers=api.a.headers)
    return int(r.json()["id"])


def test_job_events_follow_the_counters(api: Api, job_id: int) -> None:
    with live_server(api.app) as base, httpx.stream(
        "GET", f"{base}/jobs/{job_id}/events?token={api.a.token}", timeout=httpx.Timeout(10.0)
    ) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        sse = SSEReader(r)
        ev, first = sse.next_event()
        assert ev == "job" and first["id"] == job_id and first["state"] == "pending"
        with api.session() as s:
            fake_plan(s, job_id)  # 8 tasks, running
        planned = sse.until(lambda d: d["state"] == "running")
        assert planned["progress"]["total"] == 8 and planned["progress"]["fraction"] == 0
        with api.session() as s:
            run_tasks(s, api.store, job_id, task_ids(s, job_id)[:4])
        half = sse.until(lambda d: d["progress"]["finished"] == 4)
        assert (
            half["progress"]["fraction"] == 0.5
            and half["cues"]["passes"]["done"] + half["cues"]["rgb"]["done"] == 4
        )
        # nothing changes now: only heartbeat comments, no further event
        t0 = time.monotonic()
        n_comments = len(sse.comments)
        while time.monotonic() - t0 < 1.2:
            line = next(sse.lines)
            assert not line.startswith("event:"), line
            if line.startswith(":"):
                sse.comments.append(line)
        assert len(sse.comments) > n_comments and any("heartbeat" in c for c in sse.comments)
        # deleting the job ends its stream: `deleted`, or `end` when a poll fell between the delete's two
        # steps (the cancel commits first, then the rows go)
        assert api.client.delete(f"/jobs/{job_id}", headers=api.a.headers).status_code == 204
        ev, data = sse.next_event()
        while ev == "job":
            ev, data = sse.next_event()
        assert (ev, data) in (("deleted", {"id": job_id}), ("end", {"id": job_id, "state": "cancelled"}))
        assert api.client.get(f"/jobs/{job_id}", headers=api.a.headers).status_code == 404


def test_all_events_stream_is_per_tenant(api: Api, job_id: int, bunny: Path) -> None:
    sid_b = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.b.headers
    ).json()["id"]
    job_b = api.client.post("/jobs", json={"space_ids": [sid_b]}, headers=api.b.headers).json()["id"]
    with live_server(api.app) as base, httpx.stream(
        "GET", f"{base}/events", headers=api.a.headers, timeout=httpx.Timeout(10.0)
    ) as r:
        sse = SSEReader(r)
        ev, first = sse.next_event()
        assert first["id"] == job_id
        job2 = api.client.post(
            "/jobs",
            json={
                "space_ids": [api.client.get(f"/jobs/{job_id}", headers=api.a.headers).json()["space_ids"][0]]
            },
            headers=api.a.headers,
        ).json()["id"]
        seen = sse.until(lambda d: d["id"] == job2)
        assert seen["state"] == "pending"
        with api.session() as s:
            fake_plan(s, job_b)  # tenant b's job changes: tenant a hears nothing about it
            fake_plan(s, job_id)
        got = sse.until(lambda d: d["id"] == job_id and d["state"] == "running")
        assert got["progress"]["total"] == 8
    # wrong or missing token, other tenant's job
    with live_server(api.app) as base:
        assert httpx.get(f"{base}/events").status_code == 401
        assert httpx.get(f"{base}/jobs/{job_b}/events?token={api.a.token}").status_code == 404


def test_query_token_is_not_logged(api: Api, job_id: int, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("INFO", logger="uvicorn.access"), live_server(api.app, access_log=True) as base:
        with httpx.stream("GET", f"{base}/jobs/{job_id}/events?token={api.a.token}&x=1", timeout=10) as r:
            assert r.status_code == 200
            assert SSEReader(r).next_event()[1]["id"] == job_id
        time.sleep(0.2)
    logged = [rec.getMessage() for rec in caplog.records if rec.name == "uvicorn.access"]
    assert any(f"/jobs/{job_id}/events?x=1" in m for m in logged), logged
    assert not any(api.a.token in m for m in logged)


def test_job_stream_closes_after_a_final_state(api: Api, job_id: int) -> None:
    with api.session() as s:
        fake_plan(s, job_id)
    with live_server(api.app) as base:
        with httpx.stream("GET", f"{base}/jobs/{job_id}/events", headers=api.a.headers, timeout=10) as r:
            sse = SSEReader(r)
            assert sse.next_event()[1]["state"] == "running"
            with api.session() as s:
                run_tasks(s, api.store, job_id, task_ids(s, job_id))
                api.client.post(f"/jobs/{job_id}/cancel", headers=api.a.headers)  # final even if not yet done
            events = []
            for line in sse.lines:  # ends only when the server closes the stream
                if line.startswith("event:"):
                    events.append(line.split(":", 1)[1].strip())
            assert events[-1] == "end"
        # a stream opened on a finished job sends the job, then `end`, and closes at once
        t0 = time.monotonic()
        with httpx.stream("GET", f"{base}/jobs/{job_id}/events", headers=api.a.headers, timeout=10) as r:
            text = r.read().decode()
        assert time.monotonic() - t0 < 5
        assert text.count("event: job") == 1 and "event: end" in text
        end = json.loads(text.split("event: end\ndata: ", 1)[1].split("\n", 1)[0])
        assert end["id"] == job_id and end["state"] in ("done", "cancelled")
