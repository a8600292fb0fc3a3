"""Service settings: one pydantic-settings class (validated once, at start-up), env prefix `OMNIDATA_`.

Defaults are the embedded setup (SQLite file and a local object folder under `data_dir`), so nothing has
to be configured on a laptop. There is no global settings object: call `get_settings()` where needed.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict, SettingsError

DEFAULT_SECRET_KEY = "dev-secret-change-me"
MIN_SECRET_KEY_LEN = 32  # characters of a production secret
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
TOKENS_HINT = (
    'a JSON object {"<sha256 hex of a token>": "<tenant>"}; `omnidata token create --tenant NAME` prints one'
)


def hash_token(token: str) -> str:
    """sha256 hex digest of an API token: what `api_tokens` stores instead of the token itself."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def _check_digest(digest: str, what: str) -> None:
    if not _HEX64.match(digest):
        raise ValueError(f"{what} must be sha256 hex digests of tokens (64 lowercase hex characters)")


class Settings(BaseSettings):
    """Every knob of the service processes; read from `OMNIDATA_*` environment variables (and `.env`)."""

    model_config = SettingsConfigDict(
        env_prefix="OMNIDATA_", env_file=".env", env_file_encoding="utf-8", extra="ignore", frozen=True
    )

    env: Literal["development", "production"] = "development"
    data_dir: Path = Field(default_factory=lambda: Path.home() / ".omnidata")
    user_cache_mb: int = Field(
        2048, ge=0,
        description="`generate`'s caches of a scan that outlive a run ($OMNIDATA_DATA_DIR/meshed, /packed, "
        "/parsed and /curvature, services.core.user_cache): each folder is pruned to this size after a "
        "run, the entries used longest ago first (0: nothing is kept for the next run)",
    )
    database_url: str = Field("", description="SQLAlchemy URL; default sqlite:///{data_dir}/omnidata.db")
    db_wait_s: float = Field(
        60.0, ge=0,
        description="a worker, scheduler or API starting while the database does not answer (a restart, "
        "a failover) waits this long for it before it exits, s",
    )
    broker_url: str = "redis://127.0.0.1:6379/0"
    storage_url: str = Field(
        "", description="file:///abs/path or s3://bucket/prefix; default {data_dir}/objects"
    )
    s3_endpoint_url: str | None = None
    s3_region: str = "us-east-1"
    aws_access_key_id: SecretStr | None = None
    aws_secret_access_key: SecretStr | None = None
    secret_key: SecretStr = SecretStr(DEFAULT_SECRET_KEY)
    api_tokens: dict[str, str] = Field(
        default_factory=dict, description="sha256-hex(token) -> tenant; tokens are never stored in clear"
    )
    operator_tokens: list[str] = Field(
        default_factory=list, description="sha256-hex of operator tokens: service-wide /metrics (Prometheus)"
    )
    worker_expiry_s: int = Field(3600, gt=0, description="rows of workers silent this long are removed")
    upload_max_bytes: int = Field(2 * 1024**3, gt=0)
    upload_max_faces: int = Field(20_000_000, gt=0, description="an uploaded mesh with more faces is refused")
    upload_parse_memory_mb: int = Field(
        4096, ge=512, description="memory the process reading an uploaded mesh may map on top of its own, MiB"
    )
    upload_parse_timeout_s: float = Field(
        300.0, gt=0, description="time limit for reading an uploaded mesh, s"
    )
    request_max_bytes: int = Field(
        8 * 1024**2, gt=0, description="largest request body other than an upload (JSON job specs), bytes"
    )
    presign_expiry_s: int = Field(3600, gt=0, le=7 * 24 * 3600)
    public_base_url: str | None = Field(
        None,
        description="the URL clients reach the API at (https://omnidata.example.org); signed links start "
        "with it, never with a request's Host header. Unset: links are root-relative (/blobs/...)",
    )
    lease_s: int = Field(300, gt=0, description="seconds a running task holds its lease")
    heartbeat_timeout_s: int = Field(
        30, gt=0, description="a worker without a heartbeat this long is dead: its running tasks are requeued"
    )
    max_attempts: int = Field(3, ge=1)
    dispatch_window: int = Field(2000, ge=1, description="queued tasks per job at most")
    compact_views: bool = Field(
        True, description="the scheduler replaces the task rows of finished views by one packed row per view "
        "(view_output), so a finished job's database holds ~1.2 KB a view instead of ~6 KB",
    )
    compact_after_s: float = Field(
        60.0, ge=0, description="a view is compacted once its last task finished this long ago"
    )
    compact_pass_s: float = Field(
        0.25, gt=0, description="time one compaction pass of the scheduler may take, s"
    )
    worker_max_tasks: int = Field(
        500, ge=1,
        description="a worker process recycles after running this many task messages (a view batch is one)",
    )
    worker_batch_views: bool = Field(
        True,
        description="the worker that rendered a view claims the rest of its tasks, pending or queued, in one "
        "statement, derives them from the pass set it holds and records them in one statement (a "
        "derived cue's task claims its view's queued tasks alike); false: one task per message",
    )
    worker_max_memory_mb: int = Field(4096, ge=64, description="a worker recycles above this resident size")
    worker_start: Literal["auto", "spawn"] = Field(
        "auto",
        description="how `generate` starts its local workers: auto forks the first ones from its own "
        "process when that is safe (Linux, one thread, numeric libraries pinned, Blender not "
        "loaded), so they "
        "inherit its imports (~1 CPU-s each), and spawns the rest and any replacement; spawn: always spawn",
    )
    plan_memory_mb: int = Field(
        4096, ge=256,
        description="memory one job's planning may use (its process's limit); bigger specs are refused",
    )
    plan_chunk_views: int = Field(
        20000, ge=1,
        description="views planned and written at a time: a planner's memory beyond the sampled points",
    )
    plan_processes: int = Field(
        2, ge=1, le=64, description="jobs one scheduler plans at once, each in its own process"
    )
    plan_timeout_s: int = Field(
        900, ge=10,
        description="time one job's planning may take; its process is ended after it, bigger specs refused",
    )
    upload_parse_concurrency: int = Field(
        2, ge=1, description="scans the API reads at once, each in a child process (upload checks, up "
        "choices and their side views); more wait, the API stays responsive"
    )
    preview_concurrency: int = Field(
        2, ge=1, description="output previews the API draws at once (each decodes a cue file); more wait"
    )
    bulk_read_threads: int = Field(
        2, ge=1, description="threads all tenants' bulk reads (views, tasks, plan pages) share; more wait"
    )
    tenant_scan_concurrency: int = Field(
        2, ge=1, description="a tenant's requests that read a scan (uploads, registers, up choices, side "
        "views) at once, waiting or running; one more gets 429 with Retry-After"
    )
    tenant_bulk_concurrency: int = Field(
        4, ge=1, description="a tenant's bulk reads (views, tasks, plan, manifest, job.json) at once, a "
        "stream until its last byte is sent; one more gets 429 with Retry-After"
    )
    tenant_bulk_rate: float = Field(20.0, gt=0, description="bulk reads a tenant may start a second, average")
    tenant_bulk_burst: int = Field(
        100, ge=1, description="bulk reads a tenant may start in a burst above its rate (a fast pager)"
    )
    designer_processes: int = Field(
        2, ge=1, le=16,
        description="warm processes the dashboard's designer plans and renders previews in (~0.5 GB each "
        "with a room loaded), one at a time per tenant; more wait",
    )
    designer_timeout_s: float = Field(
        30.0, gt=0, le=600,
        description="time one designer plan or preview may take; its process is ended after it",
    )
    tenant_design_concurrency: int = Field(
        2, ge=1,
        description="a tenant's designer plans and previews at once; one more gets 429 with Retry-After",
    )
    sse_max_per_tenant: int = Field(20, ge=1, description="open event streams per tenant; one more gets 429")
    sse_poll_threads: int = Field(4, ge=1, description="threads the event streams' database polls share")
    sse_poll_s: float = Field(0.5, gt=0, le=60, description="seconds between an event stream's counter polls")
    sse_heartbeat_s: float = Field(15.0, gt=0, le=300, description="seconds between a stream's heartbeats")
    worker_prefetch: int = Field(
        1, ge=1, le=64,
        description="messages a worker process reserves (running included); more suits tiny tasks",
    )
    render_threads: int | None = Field(
        None, ge=1, description="CPU threads per render (default: Blender's choice)"
    )
    render_device: Literal["auto", "cpu", "cuda", "optix"] = "auto"
    render_workers: int | None = Field(
        None, ge=1,
        description="`omnidata generate`: how many of its local workers render (each holds Blender and, "
        "on a GPU, its own device context); the others only derive, from the pass sets the "
        "renderers store, and "
        "never load Blender. A renderer derives while no view waits for a render, or once it is "
        "its budget of pass sets ahead of the derivers. Unset: on a machine with an NVIDIA GPU "
        "one worker in 8 renders (at least one); on CPU cores every worker renders and derives its "
        "own views (view batches)",
    )
    queue_render: str = Field("render", min_length=1, description="heavy queue: tasks that render")
    queue_derive: str = Field("derive", min_length=1, description="light queue: derived cues, plan cues")

    @field_validator("data_dir")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        return v.expanduser().resolve()

    @field_validator("public_base_url")
    @classmethod
    def _base_url(cls, v: str | None) -> str | None:
        if v is None or v == "":
            return None
        if not re.match(r"^https?://[^/?#\s]+(/[^?#\s]*)?$", v):
            raise ValueError(f"public_base_url must be an http(s) URL without query or fragment, got {v!r}")
        return v.rstrip("/")

    @field_validator("api_tokens")
    @classmethod
    def _hashed(cls, v: dict[str, str]) -> dict[str, str]:
        for digest, tenant in v.items():
            _check_digest(digest, "api_tokens keys")
            if not tenant:
                raise ValueError(f"api_tokens entry {digest[:8]}... has an empty tenant")
        return v

    @field_validator("operator_tokens")
    @classmethod
    def _hashed_operators(cls, v: list[str]) -> list[str]:
        for digest in v:
            _check_digest(digest, "operator_tokens entries")
        return v

    @model_validator(mode="before")
    @classmethod
    def _fill_defaults(cls, data: object) -> object:
        # database_url and storage_url default to paths under data_dir, so derive them after data_dir is
        # known.
        if not isinstance(data, dict):
            return data
        data_dir = Path(data.get("data_dir") or Path.home() / ".omnidata").expanduser().resolve()
        if not data.get("database_url"):
            data["database_url"] = f"sqlite:///{data_dir / 'omnidata.db'}"
        if not data.get("storage_url"):
            data["storage_url"] = (data_dir / "objects").as_uri()
        return data

    @model_validator(mode="after")
    def _refuse_default_secret(self) -> Settings:
        if self.env == "production":
            secret = self.secret_key.get_secret_value()
            if secret == DEFAULT_SECRET_KEY or len(secret) < MIN_SECRET_KEY_LEN:
                raise ValueError(
                    "OMNIDATA_SECRET_KEY must be set to a random value of at least "
                    f"{MIN_SECRET_KEY_LEN} characters when OMNIDATA_ENV=production "
                    "(the development default is refused); e.g. `python -c 'import secrets; "
                    "print(secrets.token_urlsafe(48))'`"
                )
        return self

    @property
    def is_sqlite(self) -> bool:
        """True for the embedded database (SQLite)."""
        return self.database_url.startswith("sqlite")

    def is_operator_token(self, token: str) -> bool:
        """True when `token` is one of the operator tokens (constant-time comparison of digests)."""
        digest = hash_token(token)
        return any([hmac.compare_digest(known, digest) for known in self.operator_tokens])

    def tenant_for_token(self, token: str) -> str | None:
        """The tenant a clear-text API token belongs to, or None (constant-time comparison of digests)."""
        digest = hash_token(token)
        found = None
        for known, tenant in self.api_tokens.items():
            if hmac.compare_digest(known, digest):
                found = tenant
        return found


def get_settings(**overrides: Any) -> Settings:  # any Settings field (pydantic-settings checks them)
    """Build a fresh Settings from the environment; keyword overrides win over the environment."""
    return Settings(**overrides)


class ConfigurationError(ValueError):
    """The service is not set up right (settings, database schema); the message is one line naming the fix.

    The command line prints it as `omnidata CMD: error: ...` (exit 2) instead of a traceback.
    """


class InvalidSettings(ConfigurationError):
    """OMNIDATA_* settings that cannot be used; the message names each bad variable."""


def load_settings(**overrides: Any) -> Settings:  # as get_settings
    """get_settings() for the command line: a bad OMNIDATA_* value raises InvalidSettings with one clear
    line."""
    try:
        return get_settings(**overrides)
    except ValidationError as e:
        parts = []
        for err in e.errors():
            # empty for checks of the whole model (secret key)
            field = str(err["loc"][0]) if err["loc"] else ""
            where = f"OMNIDATA_{field.upper()}: " if field else ""
            hint = f" ({TOKENS_HINT})" if field in ("api_tokens", "operator_tokens") else ""
            parts.append(f"{where}{err['msg'].removeprefix('Value error, ')}{hint}")
        raise InvalidSettings("invalid settings: " + "; ".join(parts)) from None
    except SettingsError as e:
        # pydantic-settings could not decode a complex value (JSON) from the environment
        found = re.search(r'field "(\w+)"', str(e))
        bad = found.group(1) if found else ""
        name = f"OMNIDATA_{bad.upper()}" if bad else "an OMNIDATA_* variable"
        hint = TOKENS_HINT if bad in ("api_tokens", "operator_tokens") else "expected JSON"
        raise InvalidSettings(f"invalid settings: {name} is not valid JSON ({hint})") from None
