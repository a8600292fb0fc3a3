"""Every route but /health, /ready, the dashboard's files and signed blob links needs a valid bearer token."""

from __future__ import annotations

import re

import pytest

from tests.fixtures.api import Api

# signed links: the signature is the credential
PUBLIC = {"/health", "/ready", "/blobs/{key}", "/previews/{key}"}


def _routes(api: Api) -> list[tuple[str, str]]:
    out = []
    for path, ops in api.app.openapi()["paths"].items():
        if path in PUBLIC:
            continue
        for method in ops:
            out.append((method.upper(), re.sub(r"\{[^}]+\}", "1", path)))
    return out


def test_every_route_needs_a_token(api: Api) -> None:
    routes = _routes(api)
    assert len(routes) >= 25
    for method, path in routes:
        r = api.client.request(method, path)
        assert r.status_code == 401, (method, path, r.status_code)
        assert (
            r.json()["detail"].startswith("missing API token") and r.headers["www-authenticate"] == "Bearer"
        )
        r = api.client.request(method, path, headers={"Authorization": "Bearer not-a-token"})
        assert r.status_code == 401 and r.json()["detail"] == "invalid API token", (method, path)
        r = api.client.request(method, path, headers={"Authorization": "Basic dXNlcjpwYXNz"})
        assert r.status_code == 401, (method, path)


def test_query_token_only_on_sse_routes(api: Api) -> None:
    assert api.client.get(f"/jobs?token={api.a.token}").status_code == 401
    assert api.client.get(f"/spaces?token={api.a.token}").status_code == 401
    assert api.client.get("/events?token=wrong").status_code == 401
    assert api.client.get("/jobs/1/events").status_code == 401
    # a valid query token gets past auth on the SSE route (404: no such job for this tenant)
    assert api.client.get(f"/jobs/999999999/events?token={api.a.token}").status_code == 404


@pytest.mark.parametrize("path", ["/ui/", "/ui/app.js", "/ui/style.css", "/docs", "/openapi.json"])
def test_dashboard_files_and_docs_are_public(api: Api, path: str) -> None:
    r = api.client.get(path)
    assert r.status_code == 200, path


def test_root_redirects_to_dashboard(api: Api) -> None:
    r = api.client.get("/", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"] == "/ui/"


def test_unknown_route_and_method_are_json(api: Api) -> None:
    r = api.client.get("/nope", headers=api.a.headers)
    assert r.status_code == 404 and r.json() == {"detail": "Not Found"}
    r = api.client.put("/jobs", headers=api.a.headers)
    assert r.status_code == 405 and "detail" in r.json()
    r = api.client.post(
        "/jobs", content=b"{not json", headers={**api.a.headers, "Content-Type": "application/json"}
    )
    assert r.status_code == 422 and "json" in r.json()["detail"].lower()
