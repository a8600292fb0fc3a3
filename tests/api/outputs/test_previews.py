"""Preview links: every output link carries a signed preview URL; the API makes the PNG on first request and
stores it next to the job's files under _previews/, then serves the cached object."""

from __future__ import annotations

import io
import time
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlparse

import numpy as np
from PIL import Image

from services.api.outputs.service import blob_signature
from tests.api.outputs.test_views_outputs import _job, _space
from tests.fixtures.api import Api, run_tasks, task_ids


def _png_pixels(data: bytes) -> np.ndarray:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def test_preview_links_make_then_serve_cached_pngs(api: Api, bunny: Path) -> None:
    h = api.a.headers
    job_id = _job(api, bunny, ["rgb", "depth_zbuffer", "nonfixated"], points=1, views=2)
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    space = _space(api, job_id)
    outs = api.client.get(f"/jobs/{job_id}/views/{space}/0/1/outputs", headers=h).json()["outputs"]
    assert list(outs) == ["rgb", "depth_zbuffer", "nonfixated"]
    link = outs["depth_zbuffer"]["preview_url"]
    path = unquote(urlparse(link).path)
    pkey = f"jobs/{job_id}/_previews/v1/depth_zbuffer/omnidata/bunny/point_0_view_1_domain_depth_zbuffer.png"
    assert path == f"/previews/{pkey}" and not api.store.exists(pkey)
    got = api.client.get(link)  # no token: the signature is the credential
    assert got.status_code == 200 and got.headers["content-type"] == "image/png"
    assert _png_pixels(got.content).shape == (8, 8, 3) and api.store.get_bytes(pkey) == got.content
    # served from the cache afterwards
    marker = io.BytesIO()
    Image.new("RGB", (2, 2), (1, 2, 3)).save(marker, format="PNG")
    api.store.put_bytes(pkey, marker.getvalue())
    assert api.client.get(link).content == marker.getvalue()
    # a per-point JSON cue is drawn per view; the gallery's listing carries the same links
    nf = outs["nonfixated"]["preview_url"]
    assert "point_0_view_1_domain_nonfixated.png" in nf and api.client.get(nf).status_code == 200
    listing = api.client.get(f"/jobs/{job_id}/views?urls=true&complete=true", headers=h).json()["items"]
    assert [v["view"] for v in listing] == [0, 1]
    assert "point_0_view_0_domain_nonfixated.png" in listing[0]["outputs"]["nonfixated"]["preview_url"]
    assert all(o["preview_url"] for v in listing for o in v["outputs"].values())


def test_preview_links_are_checked(api: Api, bunny: Path) -> None:
    job_id = _job(api, bunny, ["rgb"], points=1, views=1)
    with api.session() as s:
        run_tasks(s, api.store, job_id, task_ids(s, job_id))
    link = api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/0/outputs",
                          headers=api.a.headers).json()["outputs"]["rgb"]["preview_url"]
    url = urlparse(link)
    q = parse_qs(url.query)
    assert (
        api.client.get(f"{url.path}?job={job_id}&expires={q['expires'][0]}&signature={'0' * 64}").status_code
        == 403
    )
    other = url.path.replace("view_0", "view_1")
    assert api.client.get(
        f"{other}?job={job_id}&expires={q['expires'][0]}&signature={q['signature'][0]}").status_code == 403
    settings = api.app.state.settings
    future = int(time.time()) + 60

    def signed(key: str) -> str:
        sig = blob_signature(settings, key, future, route="previews", job_id=job_id)
        return f"/previews/{key}?job={job_id}&expires={future}&signature={sig}"

    # signed, but not a preview key, or a preview of an output that does not exist: 404 and nothing stored
    assert (
        api.client.get(signed(f"jobs/{job_id}/rgb/omnidata/bunny/point_0_view_0_domain_rgb.png")).status_code
        == 404
    )
    missing = f"jobs/{job_id}/_previews/v1/rgb/omnidata/bunny/point_9_view_0_domain_rgb.png"
    assert api.client.get(signed(missing)).status_code == 404 and not api.store.exists(missing)
    passes = f"jobs/{job_id}/_previews/v1/passes/omnidata/bunny/point_0_view_0_domain_passes.png"
    assert api.client.get(signed(passes)).status_code == 404
    past = int(time.time()) - 5
    key = unquote(url.path)[len("/previews/"):]
    sig = blob_signature(settings, key, past, route="previews", job_id=job_id)
    expired = api.client.get(f"{url.path}?job={job_id}&expires={past}&signature={sig}")
    assert expired.status_code == 403 and "expired" in expired.json()["detail"]


def test_previews_on_s3(pg_url: str, s3_server, bunny: Path) -> None:  # type: ignore[no-untyped-def]
    from services.core.storage import open_store
    from tests.fixtures.api import make_api

    settings = s3_server.settings(prefix="preview-test")
    store = open_store(settings.storage_url, settings)
    with make_api(pg_url, store, **{k: getattr(settings, k) for k in (
        "storage_url", "s3_endpoint_url", "s3_region", "aws_access_key_id", "aws_secret_access_key")}) as api:
        job_id = _job(api, bunny, ["depth_zbuffer"], points=1, views=1)
        with api.session() as s:
            run_tasks(s, store, job_id, task_ids(s, job_id))
        link = api.client.get(f"/jobs/{job_id}/views/{_space(api, job_id)}/0/0/outputs",
                              headers=api.a.headers).json()["outputs"]["depth_zbuffer"]
        assert link["url"].startswith(s3_server.endpoint_url)  # the raw file: S3's own pre-signed URL
        got = api.client.get(link["preview_url"])
        assert got.status_code == 200 and _png_pixels(got.content).shape == (8, 8, 3)
        pkey = (
            f"jobs/{job_id}/_previews/v1/depth_zbuffer/omnidata/bunny/point_0_view_0_domain_depth_zbuffer.png"
        )
        assert store.get_bytes(pkey) == got.content
        store.delete_prefix("")
