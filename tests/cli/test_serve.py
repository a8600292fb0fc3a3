"""`omnidata serve`: argument checks, and a real server process answering with settings from the
environment."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from services.cli import main
from services.core.settings import hash_token
from tests.fixtures.api import free_port


def test_serve_refuses_a_bad_port(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "argv", ["omnidata"])  # main() rewrites sys.argv
    assert main(["serve", "--port", "70000"]) == 2
    assert "--port 70000 is not a TCP port" in capsys.readouterr().err


@pytest.mark.slow
def test_serve_runs_the_api(pg_url: str, tmp_path: Path, repo_root: Path) -> None:
    port = free_port()
    env = dict(os.environ)
    env.update({
        "OMNIDATA_DATABASE_URL": pg_url,
        "OMNIDATA_STORAGE_URL": (tmp_path / "objects").as_uri(),
        "OMNIDATA_API_TOKENS": json.dumps({hash_token("cli-token"): "cli-tenant"}),
    })
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "services.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
            "--log-level", "warning",
        ],
        cwd=repo_root, env=env,
    )
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, "omnidata serve did not come up"
            time.sleep(0.2)
        assert httpx.get(f"{base}/jobs").status_code == 401
        r = httpx.get(f"{base}/jobs", headers={"Authorization": "Bearer cli-token"})
        assert r.status_code == 200 and r.json()["total"] == 0
        assert httpx.get(f"{base}/ui/").status_code == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)
