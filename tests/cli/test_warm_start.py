"""Warm start of `omnidata generate` (services.cli.warm_start, services.cli.warm_server), as a user meets it:
a real server process, real `generate` commands in fresh interpreters, real renders. A warm run writes what a
cold run writes, fails as it fails, stops on Ctrl-Z and Ctrl-C and dies with a killed client as a cold one
does; the server steps aside when its code changes, its socket goes, it idles or `omnidata warm stop` asks."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from services.cli import warm_start
from tests.fixtures.cli import REPO, WIDE, dataset_files, done_tasks, omnidata
from tests.fixtures.waiting import wait_until

# one xdist group (one process, one test at a time): a test here changes a source's mtime, which retires every
# server started from this checkout, another test's included
pytestmark = [pytest.mark.bpy, pytest.mark.xdist_group("warm-server")]

SERVER_START_S = 60.0  # the server imports what a run imports (a few CPU-seconds, on a loaded 2-core machine)
CLIENT_GONE_S = 2.0  # promised: a run whose client is killed is killed at once (the server sees the hang-up)
RETIRE_S = 7.0  # a server whose socket is removed leaves within its 5 s poll


@dataclass
class Server:
    folder: Path
    env: dict[str, str]  # what a client needs to use this server
    proc: subprocess.Popen[bytes] | None = None

    @property
    def socket(self) -> Path:
        return self.folder / f"{warm_start.server_name()}.sock"

    @property
    def log(self) -> str:
        path = self.folder / "server.log"
        return path.read_text() if path.exists() else ""

    def start(self, **env: str) -> None:
        with open(self.folder / "server.log", "ab") as log:
            name = warm_start.server_name()
            cmd = [sys.executable, "-m", "services.cli.warm_server", str(self.folder), name]
            self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=log, start_new_session=True,
                                         env={**os.environ, **self.env, **env})
        wait_until(self.socket.exists, SERVER_START_S, "the server's socket")

    def runs(self) -> list[str]:
        """The server's "run PID: omnidata ARGS" lines, one per run it forked."""
        return [line for line in self.log.splitlines() if line.startswith("run ") and " ended: " not in line]


def state(pid: int) -> str:
    """The process's state letter (R, S, T stopped, Z exited unreaped), "" when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0]
    except OSError:
        return ""


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:120]
    except OSError:
        return ""


def wchan(pid: int) -> str:
    """The kernel function the process waits in ("kernel_clone": a vfork's parent, until its child execs)."""
    try:
        return Path(f"/proc/{pid}/wchan").read_text()
    except OSError:
        return ""


def stopped(pid: int) -> bool:
    """The process is stopped (T), or blocked in a vfork whose child the same Ctrl-Z stopped before its exec
    (Blender looks up xdg-user-dir through popen): that parent waits uninterruptibly (D, in kernel_clone)
    and runs again only when its child is continued, with the rest."""
    s = state(pid)
    return s == "T" or (s == "D" and any(state(c) == "T" for c in children(pid)))


def alive(pid: int) -> bool:
    return state(pid) not in ("", "Z")


@pytest.fixture
def server() -> Iterator[Server]:
    """A warm-start folder of the test's own (short: a Unix socket's path is at most 107 bytes), no server
    started yet; any server left is stopped."""
    folder = Path(tempfile.mkdtemp(prefix="ow-"))
    s = Server(folder, {"OMNIDATA_WARM_START": "1", "OMNIDATA_WARM_DIR": str(folder)})
    yield s
    lock = folder / f"{warm_start.server_name()}.lock"
    pid = lock.read_text().strip() if lock.exists() else ""
    if pid and alive(int(pid)):
        os.kill(int(pid), signal.SIGKILL)
    if s.proc is not None:
        s.proc.kill()
        s.proc.wait()
    shutil.rmtree(folder, ignore_errors=True)


def wide_spec(folder: Path) -> Path:
    """The small banana job's spec (WIDE: 4 views at 32 px)."""
    spec = folder / "spec.yaml"
    spec.write_text(WIDE)
    return spec


def generate(server: Server, scene: Path, out: Path, spec: Path, *extra: str, warm: bool = True
             ) -> subprocess.CompletedProcess[str]:
    env = server.env if warm else {"OMNIDATA_WARM_START": "0"}
    return omnidata("generate", scene, "--out", out, "--spec", spec, "--seed", 3, "--workers", 1,
                    "--no-progress", *extra, env=env)


def start_generate(server: Server, *args: str | Path) -> subprocess.Popen[str]:
    """A warm `generate` in its own session, SIGINT at its default (as a terminal's program has it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "generate", *map(str, args), "--no-progress"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, **server.env}, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def test_a_warm_run_writes_what_a_cold_run_writes_and_fails_as_it_fails(
    server: Server, scenes_dir: Path, tmp_path: Path
) -> None:
    server.start()
    spec = wide_spec(tmp_path)
    banana = scenes_dir / "ycb_banana"
    cold = generate(server, banana, tmp_path / "cold", spec, warm=False)
    warm = generate(server, banana, tmp_path / "warm", spec)
    assert cold.returncode == warm.returncode == 0, (cold.stderr, warm.stderr)
    assert [r for r in server.runs() if str(tmp_path / "warm") in r], server.log  # the server ran it
    assert warm.stdout.replace(str(tmp_path / "warm"), str(tmp_path / "cold")) == cold.stdout
    assert dataset_files(tmp_path / "warm") == dataset_files(tmp_path / "cold")

    # bad input: the same one-line error and exit status, and the server serves on
    missing = tmp_path / "no-such-scan.ply"
    bad_cold = generate(server, missing, tmp_path / "bad", spec, warm=False)
    bad_warm = generate(server, missing, tmp_path / "bad", spec)
    assert bad_warm.returncode == bad_cold.returncode == 2
    assert bad_warm.stderr == bad_cold.stderr and "no-such-scan.ply" in bad_warm.stderr
    assert len(server.runs()) == 2 and server.proc is not None and server.proc.poll() is None

    # `plan` runs warm too
    planned = {}
    for mode, env in (("cold", {"OMNIDATA_WARM_START": "0"}), ("warm", server.env)):
        out = tmp_path / mode / "plan"
        res = omnidata("plan", banana, "--out", out, "--spec", spec, "--seed", 3, env=env)
        assert res.returncode == 0, res.stderr
        planned[mode] = (res.stdout.replace(str(out), "OUT"), dataset_files(out))
    assert planned["warm"] == planned["cold"] and planned["cold"]
    assert len(server.runs()) == 3 and "omnidata plan" in server.runs()[-1]


def room_job(tmp_path: Path, scenes_dir: Path) -> list[str | Path]:
    spec = tmp_path / "room.yaml"
    spec.write_text("points: {count: 3, max_views: 60}\nviews: {resolution: 256}\n")
    return [scenes_dir / "icl_livingroom", "--out", tmp_path / "room", "--spec", spec, "--seed", "1",
            "--workers", "2"]


def children(pid: int) -> list[int]:
    try:
        return [int(p) for t in os.listdir(f"/proc/{pid}/task")
                for p in open(f"/proc/{pid}/task/{t}/children").read().split()]
    except OSError:
        return []


def run_pid(server: Server, out: Path) -> int:
    line = [r for r in server.runs() if str(out) in r][-1]
    return int(line.split()[1].rstrip(":"))


def test_ctrl_c_stops_a_warm_run_and_a_killed_client_takes_its_run_along(
    server: Server, scenes_dir: Path, tmp_path: Path
) -> None:
    server.start()
    job = room_job(tmp_path, scenes_dir)
    out = tmp_path / "room"

    # Ctrl-Z: the client, the run and its workers stop; continued, they go on
    proc = start_generate(server, *job)
    wait_until(lambda: done_tasks(out) > 0, 120, "the first derived task")
    pid = run_pid(server, out)
    proc.send_signal(signal.SIGTSTP)
    group = [proc.pid, pid, *children(pid)]
    # a process stops when it leaves the kernel: a worker in a disk flush (state D) on a loaded machine later
    try:
        wait_until(lambda: all(stopped(p) for p in group), 30, "every process of the run to stop")
    except AssertionError as e:  # which did not, and what it waits in
        seen = [(p, state(p), wchan(p), cmdline(p), [(c, state(c)) for c in children(p)]) for p in group]
        raise AssertionError(f"{e}: {seen}") from None
    stopped_at = done_tasks(out)
    time.sleep(1.0)
    assert done_tasks(out) == stopped_at
    proc.send_signal(signal.SIGCONT)
    wait_until(lambda: done_tasks(out) > stopped_at, 60, "the continued run's progress")

    # Ctrl-C: the run stops its workers and says how to resume, exit 130, as a cold run does
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "run the same command again to resume" in err

    # kill -9 of the client: its run and the run's workers end at once
    proc = start_generate(server, *job)
    wait_until(lambda: len(server.runs()) == 2, 30, "the second run")
    pid = run_pid(server, out)
    wait_until(lambda: len(children(pid)) >= 2, 30, "the run's two workers")
    workers = children(pid)
    before = done_tasks(out)
    wait_until(lambda: done_tasks(out) > before, 120, "the resumed run's progress")
    proc.kill()
    proc.wait()
    took = wait_until(lambda: not alive(pid), CLIENT_GONE_S, "the run of a killed client to end")
    wait_until(lambda: not any(alive(w) for w in workers), 10, "the killed run's workers to leave")
    assert took < CLIENT_GONE_S

    # resumed warm, the job completes
    done = omnidata("generate", *job, "--no-progress", env=server.env, timeout=600)
    assert done.returncode == 0, done.stderr
    assert len(server.runs()) == 3
    counts = json.loads((out / "job.json").read_text())["counts"]
    assert counts["by_state"] == {"done": counts["total"]}
    assert (out / "manifest.jsonl").read_text().count("\n") == counts["by_cue"]["passes"]["done"] > 0


def test_a_changed_source_sends_the_next_run_cold_and_retires_the_server(
    server: Server, scenes_dir: Path, tmp_path: Path
) -> None:
    server.start()
    spec = wide_spec(tmp_path)
    source = REPO / "services" / "cli" / "warm_start.py"
    st = source.stat()
    os.utime(source, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    try:
        res = generate(server, scenes_dir / "ycb_banana", tmp_path / "out", spec)
    finally:
        os.utime(source, ns=(st.st_atime_ns, st.st_mtime_ns))  # the checkout as it was
    assert res.returncode == 0, res.stderr
    assert server.runs() == [] and "a run refused" in server.log  # refused: the command ran cold
    assert server.proc is not None
    server.proc.wait(timeout=RETIRE_S)
    # ... and started a server of the code now on disk
    lock = server.folder / f"{warm_start.server_name()}.lock"
    wait_until(lambda: server.socket.exists(), SERVER_START_S, "the new server")
    assert int(lock.read_text()) != server.proc.pid


def test_a_server_leaves_when_its_socket_is_removed_or_it_idles(server: Server) -> None:
    server.start()
    assert server.proc is not None
    server.socket.unlink()
    t0 = time.monotonic()
    server.proc.wait(timeout=RETIRE_S)
    assert time.monotonic() - t0 < RETIRE_S
    server.start(OMNIDATA_WARM_IDLE_S="1")
    server.proc.wait(timeout=5)
    assert not server.socket.exists()


def test_warm_status_and_stop(server: Server) -> None:
    """`omnidata warm` says whether a server runs and `omnidata warm stop` retires it."""
    assert omnidata("warm", env=server.env).returncode == 1  # none yet
    server.start()
    assert server.proc is not None
    status = omnidata("warm", "status", env=server.env)
    assert status.returncode == 0 and f"server {server.proc.pid}:" in status.stdout, status
    stop = omnidata("warm", "stop", env=server.env)
    assert stop.returncode == 0 and "stopped" in stop.stdout, stop
    assert server.proc.poll() is not None and not server.socket.exists()
    assert omnidata("warm", env=server.env).returncode == 1


def test_no_warm_start_from_a_folder_others_can_reach(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    monkeypatch.setenv("OMNIDATA_WARM_DIR", str(shared))
    monkeypatch.setenv("OMNIDATA_WARM_START", "1")
    assert warm_start.runtime_dir() is None
    assert warm_start.run_warm(["generate", "x", "--out", "y"]) is None
    shared.chmod(0o700)
    assert warm_start.runtime_dir() == shared
    assert warm_start.wanted(["generate", "x"]) and not warm_start.wanted(["generate", "--help"])
    assert warm_start.wanted(["plan", "x"])
    assert not warm_start.wanted(["sheet", "x"]) and not warm_start.wanted([])
    monkeypatch.setenv("OMNIDATA_WARM_START", "0")
    assert not warm_start.wanted(["generate", "x"])
