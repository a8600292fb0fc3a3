"""`omnidata migrate`, `omnidata token create`, and the services' refusal to start on an unmigrated database
or bad settings: one line naming the fix, exit 2, no traceback (real subprocesses where the line is the
contract)."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import main
from services.cli.main import build_parser
from services.core.db.engine import make_engine, schema_problem
from services.core.settings import Settings, get_settings, hash_token
from tests.conftest import REPO_ROOT


def omnidata(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run `omnidata ARGS` in a subprocess with OMNIDATA_* overrides."""
    full = {k: v for k, v in os.environ.items() if not k.startswith("OMNIDATA_")} | env
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT, env=full,
                          capture_output=True, text=True, timeout=120)


def test_services_refuse_an_unmigrated_database_until_omnidata_migrate(
    empty_pg_url: str, tmp_path: Path
) -> None:
    env = {"OMNIDATA_DATABASE_URL": empty_pg_url, "OMNIDATA_DATA_DIR": str(tmp_path),
           "OMNIDATA_BROKER_URL": "redis://127.0.0.1:1/0"}  # never reached: the refusal comes first
    for command in ("serve", "scheduler", "worker"):
        res = omnidata(command, **env)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2, res.stderr
        assert lines[-1].startswith(f"omnidata {command}: error: the database is not migrated"), res.stderr
        assert "omnidata migrate" in lines[-1] and "Traceback" not in res.stderr

    check = omnidata("migrate", "--check", **env)
    assert check.returncode == 1 and "not migrated" in check.stderr
    res = omnidata("migrate", **env)
    assert res.returncode == 0 and "upgraded to revision" in res.stdout, res.stderr
    engine = make_engine(empty_pg_url)
    try:
        assert schema_problem(engine) is None
    finally:
        engine.dispose()
    assert omnidata("migrate", "--check", **env).returncode == 0
    again = omnidata("migrate", **env)
    assert again.returncode == 0 and "at the head" in again.stdout


def test_unreachable_database_is_waited_for_then_one_line(tmp_path: Path) -> None:
    """Nothing listens: the worker waits OMNIDATA_DB_WAIT_S (a Postgres restarting refuses connections too),
    saying so once, then exits with one line."""
    res = omnidata("worker", OMNIDATA_DATABASE_URL="postgresql+psycopg://postgres@127.0.0.1:1/none",
                   OMNIDATA_DATA_DIR=str(tmp_path), OMNIDATA_DB_WAIT_S="1")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert len(lines) == 2 and lines[0].startswith("waiting up to 1 s for the database ("), res.stderr
    assert lines[1].startswith("omnidata worker: error: cannot reach the database (")


@pytest.mark.parametrize(
    "url, reason",
    [
        ("postgresql+psycopg://no_such_role@127.0.0.1:5432/test", 'role "no_such_role" does not exist'),
        (
            "postgresql+psycopg://postgres@127.0.0.1:5432/no_such_database",
            'database "no_such_database" does not exist',
        ),
    ],
)
def test_a_refusal_no_wait_fixes_is_one_line_at_once(url: str, reason: str, tmp_path: Path) -> None:
    """A wrong user or database name is not waited for (the default wait is 60 s; the call's limit is 120
    s)."""
    res = omnidata(
        "scheduler", OMNIDATA_DATABASE_URL=url, OMNIDATA_DATA_DIR=str(tmp_path), OMNIDATA_DB_WAIT_S="100"
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert (
        lines[0].startswith("omnidata scheduler: error: cannot reach the database (") and reason in lines[0]
    )


@pytest.mark.parametrize("value, expected", [
    ("{not json", "OMNIDATA_API_TOKENS is not valid JSON"),
    ('["a list"]', "OMNIDATA_API_TOKENS: Input should be a valid dictionary"),
    ('{"abc": "tenant"}', "OMNIDATA_API_TOKENS: api_tokens keys must be sha256 hex digests"),
])
def test_malformed_api_tokens_is_one_line_not_a_traceback(value: str, expected: str, tmp_path: Path) -> None:
    res = omnidata("serve", OMNIDATA_API_TOKENS=value, OMNIDATA_DATA_DIR=str(tmp_path))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert res.stderr.startswith("omnidata serve: error: invalid settings: ") and expected in res.stderr
    assert "omnidata token create --tenant NAME" in res.stderr


def _env_line(line: str) -> tuple[str, str]:
    name, _, quoted = line.partition("=")
    return name, shlex.split(quoted)[0]


def test_token_create_prints_a_token_and_the_entry_that_enables_it(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path))
    existing = {hash_token("old-token"): "old-tenant"}
    monkeypatch.setenv("OMNIDATA_API_TOKENS", json.dumps(existing))
    assert main(["token", "create", "--tenant", "alice"]) == 0
    out = capsys.readouterr()
    token, entry = out.out.strip().splitlines()
    assert len(token) >= 40 and "shown only this once" in out.err
    name, value = _env_line(entry)
    assert name == "OMNIDATA_API_TOKENS"
    monkeypatch.setenv(name, value)
    settings = get_settings()  # the printed entry is valid settings, keeps the old tenant, and maps the token
    assert (
        settings.tenant_for_token(token) == "alice" and settings.tenant_for_token("old-token") == "old-tenant"
    )
    assert token not in value  # only its digest is stored

    assert main(["token", "create", "--tenant", "alice"]) == 0
    assert capsys.readouterr().out.split()[0] != token  # random every time

    assert main(["token", "create", "--operator"]) == 0
    op_token, op_entry = capsys.readouterr().out.strip().splitlines()
    name, value = _env_line(op_entry)
    assert name == "OMNIDATA_OPERATOR_TOKENS"
    assert Settings(operator_tokens=json.loads(value)).is_operator_token(op_token)

    assert main(["token", "create", "--tenant", "bad name!"]) == 2
    assert "--tenant 'bad name!'" in capsys.readouterr().err


def test_a_database_from_newer_code_is_refused_not_downgraded(
    empty_pg_url: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from sqlalchemy import text

    from services.core.db.engine import migrate

    migrate(empty_pg_url)
    engine = make_engine(empty_pg_url)
    try:
        with engine.begin() as conn:
            conn.execute(text("UPDATE alembic_version SET version_num = 'f00dcafe'"))
    finally:
        engine.dispose()
    monkeypatch.setenv("OMNIDATA_DATABASE_URL", empty_pg_url)
    monkeypatch.setenv("OMNIDATA_DATA_DIR", str(tmp_path))
    assert main(["migrate", "--check"]) == 1
    assert "revision f00dcafe, which this code does not know" in capsys.readouterr().err
    assert main(["migrate"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("omnidata migrate: error: cannot migrate the database: ") and "\n" not in err


def test_a_new_token_never_starts_with_a_dash(monkeypatch: pytest.MonkeyPatch) -> None:
    # `--token -x...` reads as an option (argparse: "expected one argument"): a token drawn so is drawn again
    from services.cli import token_create

    draws = iter(["-starts-with-a-dash", "_fine-token"])
    monkeypatch.setattr(token_create.secrets, "token_urlsafe", lambda _n: next(draws))
    assert token_create.new_token() == "_fine-token"
    monkeypatch.undo()
    token = token_create.new_token()
    argv = ["submit", "--spec", "job.yaml", "--token", "-" + token, "space.obj"]
    with pytest.raises(SystemExit):  # what a token starting with '-' did
        build_parser(argv).parse_args(argv)
    argv[4] = token
    assert build_parser(argv).parse_args(argv).token == token
