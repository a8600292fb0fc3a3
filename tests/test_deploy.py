"""docker-compose.yml, the Dockerfile and the Kubernetes manifests, checked by parsing (no Docker engine
here)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import yaml

from services.cli.main import COMMANDS
from services.core.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
SETTINGS_ENV = {f"OMNIDATA_{name.upper()}" for name in Settings.model_fields}
EXTRA_ENV = {"OMNIDATA_ROLE"}  # read by the healthcheck only


def _compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _k8s_docs() -> list[dict]:
    docs = []
    for f in sorted((ROOT / "deploy" / "k8s").glob("*.yaml")):
        docs += [d for d in yaml.safe_load_all(f.read_text()) if d]
    return docs


def _check_command(cmd: list[str]) -> None:
    if cmd[0] == "omnidata":
        assert cmd[1] in COMMANDS, f"unknown omnidata subcommand in {cmd}"
    else:
        assert cmd[:2] == ["alembic", "upgrade"], cmd


def test_compose_has_the_services_and_a_scalable_worker():
    services = _compose()["services"]
    for name in ("postgres", "redis", "minio", "api", "scheduler", "worker"):
        assert name in services, f"docker-compose.yml lacks {name}"
    worker = services["worker"]
    # --scale needs copies that do not clash: no fixed container name, no host port
    assert "container_name" not in worker and "ports" not in worker
    for name in ("api", "scheduler", "worker", "migrate"):
        _check_command(services[name]["command"])
    assert services["api"]["depends_on"]["migrate"]["condition"] == "service_completed_successfully"


def test_compose_env_names_real_settings():
    compose = _compose()
    env = dict(compose["x-omnidata-env"])
    env.update(compose["services"]["api"]["environment"])
    unknown = {k for k in env if k.startswith("OMNIDATA_")} - SETTINGS_ENV - EXTRA_ENV
    assert not unknown, f"compose sets variables no setting reads: {unknown}"
    assert env["OMNIDATA_ENV"] == "production"
    assert env["OMNIDATA_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert env["OMNIDATA_STORAGE_URL"].startswith("s3://")
    # production refuses a default secret: compose must demand one instead of shipping it
    assert "?" in env["OMNIDATA_SECRET_KEY"]


def test_dockerfile_targets_python_311_and_installs_the_project():
    text = (ROOT / "deploy" / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11", text, re.M), "bpy 4.5 wheels need Python 3.11"
    assert "pip install" in text and "COPY services" in text and "COPY migrations" in text
    cmd = re.search(r"^CMD (\[.*\])$", text, re.M)
    assert cmd is not None
    _check_command(yaml.safe_load(cmd.group(1)))
    for copied in re.findall(r"^COPY (.+) \S+$", text, re.M):
        for src in shlex.split(copied):
            assert (ROOT / src).exists(), f"Dockerfile copies missing {src}"


def test_dockerfile_compiles_the_kernels_into_a_cache_the_service_user_can_use():
    lines = [
        ln
        for ln in (ROOT / "deploy" / "Dockerfile").read_text().splitlines()
        if ln and not ln.startswith("#")
    ]
    at = {
        key: next(i for i, ln in enumerate(lines) if key in ln)
        for key in ("pip install", "NUMBA_CACHE_DIR=", "omnidata compile-kernels", "chown", "USER omnidata")
    }
    # installed, then compiled (as root, into the cache numba will read), then handed to the user the pods run
    # as
    assert (
        at["pip install"]
        < at["NUMBA_CACHE_DIR="]
        < at["omnidata compile-kernels"]
        < at["chown"]
        < at["USER omnidata"]
    )
    assert lines[at["NUMBA_CACHE_DIR="]].startswith("ENV ")  # an ENV: the running pods read the same folder
    # pods run on CPUs of any level, not the builder's
    assert "--every-level" in lines[at["omnidata compile-kernels"]]
    assert "compile-kernels" in COMMANDS


@pytest.mark.parametrize("doc", _k8s_docs(), ids=lambda d: f"{d['kind']}-{d['metadata']['name']}")
def test_k8s_manifests_are_well_formed(doc):
    assert doc["apiVersion"] and doc["kind"] and doc["metadata"]["name"]
    if doc["kind"] == "Deployment":
        spec = doc["spec"]
        assert spec["selector"]["matchLabels"].items() <= spec["template"]["metadata"]["labels"].items()
        for c in spec["template"]["spec"]["containers"]:
            _check_command(c["command"])
    if doc["kind"] == "ConfigMap":
        unknown = set(doc["data"]) - SETTINGS_ENV
        assert not unknown, f"ConfigMap sets variables no setting reads: {unknown}"


def test_k8s_covers_every_service():
    kinds = {(d["kind"], d["metadata"]["name"]) for d in _k8s_docs()}
    for name in ("omnidata-api", "omnidata-scheduler", "omnidata-worker-render", "omnidata-worker-derive"):
        assert ("Deployment", name) in kinds
    assert ("Service", "omnidata-api") in kinds
