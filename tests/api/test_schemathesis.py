"""Property-based run over the OpenAPI schema (schemathesis): no generated request gets a server error.

The SSE routes never end by themselves, so they are left to progress/test_sse.py. Bounded examples keep it <
60 s.
"""

from __future__ import annotations

from pathlib import Path

import hypothesis
import schemathesis
from hypothesis import HealthCheck
from schemathesis import runner
from schemathesis.checks import not_a_server_error
from schemathesis.runner import events

from tests.fixtures.api import Api, fake_plan, run_tasks, task_ids


def test_no_server_errors_over_the_schema(api: Api, bunny: Path) -> None:
    # Give the generator something real to find: a space, and a planned job with some outputs.
    sid = api.client.post(
        "/spaces", files={"file": ("b.ply", bunny.read_bytes())}, headers=api.a.headers
    ).json()["id"]
    job_id = api.client.post(
        "/jobs", json={"space_ids": [sid], "spec": {"cues": ["rgb"]}}, headers=api.a.headers
    ).json()["id"]
    with api.session() as s:
        fake_plan(s, job_id)
        run_tasks(s, api.store, job_id, task_ids(s, job_id)[:3])
        run_tasks(s, api.store, job_id, task_ids(s, job_id, state="pending")[:1], fail=True)

    schemathesis.experimental.OPEN_API_3_1.enable()  # FastAPI emits OpenAPI 3.1
    schema = schemathesis.from_asgi(
        "/openapi.json", app=api.app, data_generation_methods=schemathesis.DataGenerationMethod.all()
    ).exclude(path_regex=r"events$")
    assert schema.operations_count >= 20
    run = runner.from_schema(
        schema,
        checks=[not_a_server_error],
        headers=api.a.headers,
        hypothesis_settings=hypothesis.settings(
            max_examples=30,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        ),
        seed=1,
    )
    failures: list[str] = []
    errors: list[str] = []
    tested = 0
    for event in run.execute():
        if isinstance(event, events.AfterExecution):
            tested += 1
            for check in event.result.checks:
                if check.value.name == "failure":
                    failures.append(
                        f"{event.result.method} {event.result.path}: {check.message or check.name}"
                    )
            for err in event.result.errors:
                errors.append(f"{event.result.method} {event.result.path}: {err.exception}")
    assert tested >= 20
    assert not failures, "\n".join(sorted(set(failures))[:20])
    assert not errors, "\n".join(errors[:20])
    assert api.client.get("/health").status_code == 200
