"""Signed links (issue 19): built from the configured public base URL, never the Host header; bound to the
route, the job and the job's own keys. The dashboard and the docs: CSP without inline script, no framing,
nosniff, and /docs served from installed files (no CDN)."""

from __future__ import annotations

import re
import time
from pathlib import Path
from urllib.parse import parse_qs, quote, urlparse

from services.api.outputs.service import blob_signature
from services.core.storage import LocalStore
from tests.fixtures.api import Api, fake_plan, make_api, run_tasks, task_ids


def _done_job(api: Api, bunny: Path, name: str = "bunny") -> tuple[int, int]:
    r = api.client.post("/spaces", files={"file": (f"{name}.ply", bunny.read_bytes())}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    space_id = int(r.json()["id"])
    r = api.client.post(
        "/jobs", json={"space_ids": [space_id], "spec": {"cues": ["rgb"]}}, headers=api.a.headers
    )
    assert r.status_code == 201, r.text
    job_id = int(r.json()["id"])
    with api.session() as s:
        fake_plan(s, job_id, points=1, views=1)
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    return job_id, space_id


def _rgb_link(api: Api, job_id: int, space_id: int, host: str = "evil.example") -> dict[str, str]:
    r = api.client.get(
        f"/jobs/{job_id}/views/{space_id}/0/0/outputs", headers={**api.a.headers, "Host": host}
    )
    assert r.status_code == 200, r.text
    link: dict[str, str] = r.json()["outputs"]["rgb"]
    return link


def test_links_use_the_configured_base_url_never_the_host_header(
    pg_url: str, local_store: LocalStore, bunny: Path
) -> None:
    with make_api(pg_url, local_store, public_base_url="https://omnidata.example.org/api/") as api:
        job_id, space_id = _done_job(api, bunny)
        link = _rgb_link(api, job_id, space_id)
        for url in (link["url"], link["preview_url"]):
            assert url.startswith("https://omnidata.example.org/api/") and "evil" not in url, url
        listed = api.client.get(
            f"/jobs/{job_id}/views?urls=true", headers={**api.a.headers, "Host": "evil.example"}
        )
        assert "evil.example" not in listed.text and "omnidata.example.org" in listed.text
    with make_api(pg_url, local_store) as api:  # unset: root-relative links, still not the Host header
        job_id, space_id = _done_job(api, bunny)
        link = _rgb_link(api, job_id, space_id)
        assert link["url"].startswith("/blobs/jobs/") and link["preview_url"].startswith("/previews/jobs/")
        assert api.client.get(link["url"]).status_code == 200


def test_a_link_serves_only_its_own_jobs_keys(api: Api, bunny: Path) -> None:
    job_id, space_id = _done_job(api, bunny)
    other_job, _ = _done_job(api, bunny, "other")
    link = _rgb_link(api, job_id, space_id)
    url = urlparse(link["url"])
    q = parse_qs(url.query)
    assert api.client.get(link["url"]).status_code == 200
    settings = api.app.state.settings
    future = int(time.time()) + 60

    def get(
        route: str, key: str, job: int, *, sign_route: str | None = None, sign_job: int | None = None
    ) -> int:
        sig = blob_signature(settings, key, future, route=sign_route or route,
                             job_id=job if sign_job is None else sign_job)
        return api.client.get(f"/{route}/{quote(key)}?job={job}&expires={future}&signature={sig}").status_code

    key = f"jobs/{job_id}/rgb/omnidata/bunny/point_0_view_0_domain_rgb.png"
    assert get("blobs", key, job_id) == 200
    # a correctly signed key outside the job's root: another job's file, the space's source: not served
    assert get("blobs", key.replace(f"jobs/{job_id}/", f"jobs/{other_job}/"), job_id) == 404
    source = api.client.get(f"/spaces/{space_id}", headers=api.a.headers).json()["source_key"]
    assert api.store.exists(source) and get("blobs", source, job_id) == 404
    # the job in the link is part of the signature, and so is the route
    assert get("blobs", key, other_job, sign_job=job_id) == 403
    assert get("previews", key, job_id, sign_route="blobs") == 403
    # the real link's signature does not carry over to another job or route
    swapped = f"{url.path}?job={other_job}&expires={q['expires'][0]}&signature={q['signature'][0]}"
    assert api.client.get(swapped).status_code == 403
    assert api.client.get(f"{url.path.replace('/blobs/', '/previews/', 1)}?{url.query}").status_code == 403
    # a deleted job's links stop working
    assert api.client.delete(f"/jobs/{job_id}", headers=api.a.headers).status_code in (200, 202, 204)
    assert api.client.get(link["url"]).status_code == 404


def test_a_link_giving_a_signed_parameter_twice_is_refused(api: Api, bunny: Path) -> None:
    job_id, space_id = _done_job(api, bunny)
    link = _rgb_link(api, job_id, space_id)
    url = urlparse(link["url"])
    q = {k: v[0] for k, v in parse_qs(url.query).items()}
    assert api.client.get(link["url"]).status_code == 200
    forged = "0" * 64
    for query in (f"job={job_id}&expires={q['expires']}&signature={forged}&signature={q['signature']}",
                  f"job={job_id}&expires={q['expires']}&signature={q['signature']}&signature={forged}",
                  f"job={job_id}&expires=1&expires={q['expires']}&signature={q['signature']}",
                  f"job=999999&job={job_id}&expires={q['expires']}&signature={q['signature']}"):
        for route in ("/blobs/", "/previews/"):
            r = api.client.get(f"{url.path.replace('/blobs/', route, 1)}?{query}")
            assert r.status_code == 403 and "more than once" in r.json()["detail"], (route, query, r.text)


def test_dashboard_and_docs_headers(api: Api) -> None:
    for path in ("/ui/", "/ui/app.js", "/docs"):
        r = api.client.get(path)
        assert r.status_code == 200, path
        csp = r.headers["content-security-policy"]
        script_src = re.search(r"script-src ([^;]*)", csp)
        assert script_src is not None and "'unsafe-inline'" not in script_src.group(1), csp
        assert "'unsafe-eval'" not in csp and "frame-ancestors 'none'" in csp
        assert r.headers["x-frame-options"] == "DENY" and r.headers["x-content-type-options"] == "nosniff"
    assert api.client.get("/health").headers["x-content-type-options"] == "nosniff"
    index = api.client.get("/ui/").text
    assert all(re.search(r"\bsrc=", tag) for tag in re.findall(r"<script[^>]*>", index)), (
        "inline script in /ui"
    )
    assert not re.search(r"\son[a-z]+=", index), "inline event handler in /ui"


def test_docs_work_offline(api: Api) -> None:
    page = api.client.get("/docs").text
    assets = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert assets and not [a for a in assets if a.startswith(("http:", "https:", "//"))], assets  # no CDN
    assert all(re.search(r"\bsrc=", tag) for tag in re.findall(r"<script[^>]*>", page))
    for asset in assets:
        if not asset.startswith("data:"):
            assert api.client.get(asset).status_code == 200, asset
    assert "SwaggerUIBundle" in api.client.get("/docs/swagger-ui/swagger-ui-bundle.js").text
    assert api.client.get("/openapi.json").status_code == 200
    assert api.client.get("/redoc").status_code in (401, 404)  # ReDoc would need a CDN: not served
