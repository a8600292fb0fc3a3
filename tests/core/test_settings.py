"""Settings: embedded defaults, environment overrides, the production secret refusal, token hashing."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from pydantic import ValidationError

from services.core.settings import DEFAULT_SECRET_KEY, Settings, get_settings, hash_token
from services.core.storage import LocalStore, open_store


@pytest.fixture()
def clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No OMNIDATA_* variables, HOME and cwd in a temp folder (no stray .env)."""
    import os

    for name in list(os.environ):
        if name.startswith("OMNIDATA_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_defaults_are_the_embedded_setup(clean_env: Path) -> None:
    s = get_settings()
    data_dir = clean_env / ".omnidata"
    assert s.env == "development"
    assert s.data_dir == data_dir
    assert s.database_url == f"sqlite:///{data_dir / 'omnidata.db'}"
    assert s.is_sqlite
    assert s.storage_url == (data_dir / "objects").as_uri()
    assert s.broker_url == "redis://127.0.0.1:6379/0"
    assert s.secret_key.get_secret_value() == DEFAULT_SECRET_KEY
    assert (s.upload_max_bytes, s.presign_expiry_s, s.lease_s, s.max_attempts) == (2 * 1024**3, 3600, 300, 3)
    assert (s.dispatch_window, s.worker_max_tasks, s.worker_max_memory_mb) == (2000, 500, 4096)
    assert (s.render_device, s.queue_render, s.queue_derive) == ("auto", "render", "derive")
    assert s.api_tokens == {}
    store = open_store(s.storage_url, s)
    assert isinstance(store, LocalStore) and store.root == data_dir / "objects"


def test_data_dir_moves_the_derived_defaults(clean_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(clean_env / "elsewhere"))
    s = get_settings()
    assert s.database_url == f"sqlite:///{clean_env / 'elsewhere' / 'omnidata.db'}"
    assert s.storage_url == (clean_env / "elsewhere" / "objects").as_uri()


def test_environment_overrides_and_types(clean_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    digest = hash_token("tok-a")
    monkeypatch.setenv("OMNIDATA_DATABASE_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/omnidata")
    monkeypatch.setenv("OMNIDATA_STORAGE_URL", "s3://bucket/some/prefix")
    monkeypatch.setenv("OMNIDATA_LEASE_S", "42")
    monkeypatch.setenv("OMNIDATA_RENDER_DEVICE", "cuda")
    monkeypatch.setenv("OMNIDATA_API_TOKENS", f'{{"{digest}": "tenant-a"}}')
    s = get_settings()
    assert s.database_url.startswith("postgresql+psycopg://") and not s.is_sqlite
    assert s.storage_url == "s3://bucket/some/prefix"
    assert s.lease_s == 42
    assert s.render_device == "cuda"
    assert s.tenant_for_token("tok-a") == "tenant-a"
    assert s.tenant_for_token("tok-b") is None
    # a fresh instance each call: a changed environment is seen, no cached global
    monkeypatch.setenv("OMNIDATA_LEASE_S", "43")
    assert get_settings().lease_s == 43
    assert get_settings(lease_s=7).lease_s == 7  # keyword overrides win


def test_invalid_values_name_the_field(clean_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMNIDATA_RENDER_DEVICE", "tpu")
    with pytest.raises(ValidationError) as e:
        get_settings()
    assert e.value.errors()[0]["loc"] == ("render_device",)
    monkeypatch.delenv("OMNIDATA_RENDER_DEVICE")
    monkeypatch.setenv("OMNIDATA_LEASE_S", "0")
    with pytest.raises(ValidationError) as e:
        get_settings()
    assert e.value.errors()[0]["loc"] == ("lease_s",)


def test_render_threads_is_a_setting_the_runner_uses(
    clean_env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.core.storage import LocalStore
    from services.worker.run.runner import TaskRunner

    assert get_settings().render_threads is None  # Blender's own choice
    monkeypatch.setenv("OMNIDATA_RENDER_THREADS", "3")
    settings = get_settings()
    assert settings.render_threads == 3
    runner = TaskRunner(None, LocalStore(clean_env), settings, "w:1")  # type: ignore[arg-type]
    assert runner.render_threads == 3
    assert TaskRunner(None, LocalStore(clean_env), settings, "w:1", render_threads=1).render_threads == 1  # type: ignore[arg-type]
    monkeypatch.setenv("OMNIDATA_RENDER_THREADS", "0")
    with pytest.raises(ValidationError) as e:
        get_settings()
    assert e.value.errors()[0]["loc"] == ("render_threads",)


def test_production_refuses_default_and_short_secrets(
    clean_env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OMNIDATA_ENV", "production")
    with pytest.raises(ValidationError, match="OMNIDATA_SECRET_KEY"):
        get_settings()
    with pytest.raises(ValidationError, match="at least 32 characters"):
        get_settings(secret_key="short-but-not-default")
    s = get_settings(secret_key="x" * 40)
    assert s.env == "production"
    assert "x" * 40 not in repr(s)  # SecretStr hides it
    # development accepts the default, so a laptop needs no configuration
    assert get_settings(env="development").secret_key.get_secret_value() == DEFAULT_SECRET_KEY


def test_hash_token_and_tokens_stored_hashed(clean_env: Path) -> None:
    assert hash_token("abc") == hashlib.sha256(b"abc").hexdigest()
    assert len(hash_token("")) == 64
    with pytest.raises(ValidationError, match="sha256 hex digests"):
        get_settings(api_tokens={"clear-text-token": "tenant"})
    with pytest.raises(ValidationError, match="empty tenant"):
        get_settings(api_tokens={hash_token("t"): ""})


def test_settings_are_immutable(clean_env: Path) -> None:
    s = Settings()
    with pytest.raises(ValidationError):
        s.lease_s = 1  # type: ignore[misc]
