"""`omnidata generate`: the embedded default end to end (SQLite, a local folder, local worker processes, real
renders), as a user runs it: layout, manifest and job.json, determinism, interrupt and resume, failures, bad
input.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.cli import main
from services.core.domain.cues import CATALOG, default_cues
from services.core.domain.keys import output_key
from tests.conftest import GeneratedRun
from tests.fixtures.cli import REPO, WIDE, done_tasks, omnidata

TINY = WIDE  # the spec of the shared tiny_banana run


def generate(*args: str | Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """Run `omnidata generate` in a fresh interpreter (as the console script does)."""
    return omnidata("generate", *args, "--no-progress", timeout=timeout)


def start_generate(*args: str | Path) -> subprocess.Popen[str]:
    """Start `omnidata generate` in its own process group (so the test can signal or kill all of it)."""
    cmd = [sys.executable, "-m", "services.cli", "generate", *map(str, args), "--no-progress"]
    # A terminal's Ctrl-C reaches a program whose SIGINT is not ignored; a test runner started in the
    # background of a non-interactive shell inherits SIGINT ignored, so give the child the default disposition
    # back.
    return subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def manifest(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]


def wait_for(cond, timeout: float, proc: subprocess.Popen[str], poll_s: float = 0.2) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert proc.poll() is None, f"generate ended early: {proc.communicate()}"
        assert time.monotonic() < deadline, "timed out waiting for progress"
        time.sleep(poll_s)


def stray_temp_files(out: Path) -> list[Path]:
    return [p for p in out.rglob(".*.tmp-*")]


@pytest.fixture(scope="module")
def tiny_spec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("spec") / "job.yaml"
    p.write_text(TINY)
    return p


@pytest.fixture(scope="module")
def banana_run(tiny_banana: GeneratedRun) -> tuple[Path, str]:
    """One full run on the banana: every default cue, 2 points x 2 views, 32 px, seed 7, 2 workers (read
    only)."""
    return tiny_banana.out, tiny_banana.stdout


# ------------------------------------------------------------------------------------------ a full run


def test_a_run_leaves_no_blender_temp_folder_behind(tiny_banana: GeneratedRun, tmp_path):
    """`import bpy` makes $TMPDIR/blender_XXXXXX and only Blender's own exit removes it; workers leave through
    os._exit, so each used to leave one behind. The run's two workers had the run's TMPDIR."""
    probe = "import bpy, os, sys; sys.stdout.write(bpy.app.tempdir); sys.stdout.flush(); os._exit(0)"
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "TMPDIR": str(tmp_path)})
    # bpy's folder follows TMPDIR, kept
    assert Path(res.stdout).parent == tmp_path and Path(res.stdout).is_dir()
    assert tiny_banana.tmpdir is not None
    assert not list(tiny_banana.tmpdir.glob("blender_*"))


@pytest.mark.slow
def test_every_default_cue_is_written_in_the_omnidata_layout(banana_run):
    out, stdout = banana_run
    assert "files for 4 views" in stdout
    lines = manifest(out)
    assert [(e["space"], e["point"], e["view"]) for e in lines] == [
        ("ycb_banana", 0, 0), ("ycb_banana", 0, 1), ("ycb_banana", 1, 0), ("ycb_banana", 1, 1)
    ]
    cues = default_cues(has_semantics=False)
    for e in lines:
        want = [c for c in cues if e["view"] == 0 or not CATALOG[c].per_point]
        assert sorted(e["outputs"]) == sorted(want)
        for cue, o in e["outputs"].items():
            key = output_key(cue, "tiny", "ycb_banana", e["point"], e["view"])
            assert o["key"] == key
            data = (out / key).read_bytes()
            assert len(data) == o["size"] and hashlib.sha256(data).hexdigest() == o["sha256"]
    # the catalog's file names and encodings, checked on a few files
    rgb = np.asarray(Image.open(out / "rgb/tiny/ycb_banana/point_0_view_0_domain_rgb.png"))
    depth = np.asarray(
        Image.open(out / "depth_zbuffer/tiny/ycb_banana/point_0_view_0_domain_depth_zbuffer.png")
    )
    frags = np.load(out / "fragments/tiny/ycb_banana/point_1_view_1_domain_fragments.npy")
    assert rgb.shape == (32, 32, 3) and rgb.dtype == np.uint8
    assert depth.dtype == np.uint16 and (depth < 65535).any() and (depth == 65535).any()
    assert frags.dtype == np.uint32 and frags.shape == (32, 32)
    info = json.loads((out / "point_info/tiny/ycb_banana/point_0_view_1_domain_point_info.json").read_text())
    assert np.asarray(info["K"]).shape == (3, 3) and np.asarray(info["world_to_camera"]).shape == (4, 4)
    assert (out / "nonfixated/tiny/ycb_banana/point_1_domain_nonfixated.json").is_file()
    job = json.loads((out / "job.json").read_text())
    assert job["spec"]["seed"] == 7 and job["spec"]["name"] == "tiny" and job["job"]["state"] == "done"
    assert np.asarray(job["spaces"]["ycb_banana"]["source_to_world"]).shape == (4, 4)
    assert job["conventions"]["camera_axes"].startswith("OpenCV") and job["code_version"]
    # nothing internal or half-written is left behind
    assert not (out / "_cache").exists() and not stray_temp_files(out)
    top = {p.name for p in out.iterdir()}
    assert top - {".omnidata", "_plan", "manifest.jsonl", "job.json"} == set(cues)


@pytest.mark.slow
def test_same_seed_gives_identical_bytes_and_a_rerun_renders_nothing(
    banana_run, scenes_dir, tiny_spec, tmp_path
):
    first, _ = banana_run
    out = tmp_path / "again"
    res = generate(scenes_dir / "ycb_banana", "--out", out, "--spec", tiny_spec, "--seed", 7, "--workers", 1,
                   "--name", "tiny")
    assert res.returncode == 0, res.stderr
    assert (out / "manifest.jsonl").read_bytes() == (first / "manifest.jsonl").read_bytes()
    for key in ("rgb/tiny/ycb_banana/point_0_view_0_domain_rgb.png",
                "normal/tiny/ycb_banana/point_1_view_1_domain_normal.png",
                "segment_unsup25d/tiny/ycb_banana/point_1_view_0_domain_segment_unsup25d.png",
                "position/tiny/ycb_banana/point_0_view_1_domain_position.exr"):
        assert (out / key).read_bytes() == (first / key).read_bytes()
    # The same command again: the same job, already complete: nothing renders, every file stays as it was.
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    res = generate(scenes_dir / "ycb_banana", "--out", out, "--spec", tiny_spec, "--seed", 7, "--workers", 1,
                   "--name", "tiny")
    assert res.returncode == 0, res.stderr
    assert "resuming job 1" in res.stderr and "0 missing" in res.stderr
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.png")} == stamps
    # Its workers, stopped while they load Blender, leave quietly: no leak report of Blender's C++ teardown.
    assert "leak detector" not in res.stderr and "Not freed memory" not in res.stderr, res.stderr


def test_a_folder_whose_sources_were_zipped_by_an_earlier_version_resumes(banana_run, scenes_dir, tiny_spec,
                                                                            tmp_path):
    """Sources are zipped with photos and textures stored since 2026-11, which changed their checksums: a
    folder of a run before that (its space row holds the old zip's checksum) is the same job, not a
    Conflict."""
    from services.core.ingest.registry import legacy_source_checksum, source_checksum

    out = tmp_path / "before"
    shutil.copytree(banana_run[0], out)
    src = scenes_dir / "ycb_banana"
    legacy, current = legacy_source_checksum(src), source_checksum(src)
    assert legacy is not None and legacy != current  # the banana's texture is stored now, deflated before
    with sqlite3.connect(out / ".omnidata" / "state.db") as db:
        assert db.execute("UPDATE space SET checksum = ? WHERE checksum = ?", (legacy, current)).rowcount == 1
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    res = generate(src, "--out", out, "--spec", tiny_spec, "--seed", 7, "--workers", 1, "--name", "tiny")
    assert res.returncode == 0, res.stderr
    assert "resuming job 1" in res.stderr and "0 missing" in res.stderr
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.png")} == stamps


def test_an_embedded_run_never_imports_celery(banana_run, scenes_dir, tiny_spec, tmp_path):
    """Celery, kombu and redis are the cluster's transport: an embedded `generate` (every job's start-up) pays
    ~80 ms to import them for nothing. Its own interpreter runs the whole job, then says what it imported."""
    out = tmp_path / "embedded"
    probe = (
        "import sys\nfrom services.cli.main import main\n"
        f"rc = main(['generate', {str(scenes_dir / 'ycb_banana')!r}, '--out', {str(out)!r}, '--spec', "
        f"{str(tiny_spec)!r}, '--seed', '7', '--workers', '1', '--name', 'tiny', '--no-progress'])\n"
        "print(rc, sorted({m.split('.')[0] for m in sys.modules} & {'celery', 'kombu', "
        "'billiard', 'redis'}))\n"
    )
    res = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split("\n")[-2] == "0 []", res.stdout
    # the whole job
    assert (out / "manifest.jsonl").read_bytes() == (banana_run[0] / "manifest.jsonl").read_bytes()


# ------------------------------------------------------------------------------------------ interrupt, resume


@pytest.mark.slow
def test_ctrl_c_then_kill_then_resume_renders_only_what_is_missing(scenes_dir, tmp_path):
    spec = tmp_path / "job.yaml"
    # big enough that the interrupts below land mid-run however fast the renders are (a whole view is claimed
    # and recorded at once: with 12 points, what step 1 left finished between two polls of the kill below on a
    # fast host)
    points = 30
    spec.write_text(
        "cameras: {mode: object, object_count: 8}\npoints: "
        f"{{count: {points}, min_views: 3, max_views: 3}}\n"
        "views: {resolution: 96}\n"
    )
    out = tmp_path / "out"
    args = (scenes_dir / "ycb_banana", "--out", out, "--spec", spec, "--cues",
            "rgb,normal,depth_zbuffer,edge_texture,point_info", "--workers", 2)
    total = points * 3 * 5

    # 1. Ctrl-C (SIGINT to the whole process group, as a terminal sends it): clean stop, exit 130.
    proc = start_generate(*args)
    wait_for(lambda: done_tasks(out) >= 3, 240, proc)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    with sqlite3.connect(out / ".omnidata" / "state.db") as c:
        states = dict(c.execute("SELECT state, count(*) FROM task GROUP BY state").fetchall())
    assert "running" not in states and "queued" not in states  # handed back for the next run
    assert not stray_temp_files(out) and not (out / "manifest.jsonl").exists()

    # 2. kill -9 of everything mid-run (a crash): leaves running/queued tasks behind.
    proc = start_generate(*args)
    before = done_tasks(out)
    wait_for(lambda: done_tasks(out) >= before + 3, 240, proc, poll_s=0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    time.sleep(0.5)
    with sqlite3.connect(out / ".omnidata" / "state.db") as c:
        finished = dict(c.execute("SELECT id, finished_at FROM task WHERE state = 'done'").fetchall())
        keys = [
            k for (k,) in c.execute("SELECT output_key FROM task WHERE state = 'done' AND cue != 'passes'")
        ]
    assert 0 < len(finished) and done_tasks(out) < total
    files = {out / k: (out / k).stat().st_mtime_ns for k in keys}  # recorded done: must not be made again

    # 3. The same command resumes: the same job; what was done stays untouched; the rest is made.
    res = generate(*args)
    assert res.returncode == 0, res.stderr
    assert "resuming job 1" in res.stderr
    with sqlite3.connect(out / ".omnidata" / "state.db") as c:
        assert c.execute("SELECT count(*) FROM job").fetchone()[0] == 1
        rows = dict(c.execute("SELECT id, finished_at FROM task WHERE state = 'done'").fetchall())
        assert c.execute("SELECT count(*) FROM task WHERE state != 'done'").fetchone()[0] == 0
    assert all(rows[i] == f for i, f in finished.items())  # done before: not run again
    for p, stamp in files.items():
        assert p.stat().st_mtime_ns == stamp, f"{p} was rewritten"
    entries = manifest(out)
    assert len(entries) == points * 3
    assert sum(len(e["outputs"]) for e in entries) == total
    for e in entries:
        for o in e["outputs"].values():
            assert hashlib.sha256((out / o["key"]).read_bytes()).hexdigest() == o["sha256"]
    assert not stray_temp_files(out)

    # 4. A deleted output is made again by the next run, and only it.
    victim = out / "edge_texture/omnidata/ycb_banana/point_2_view_1_domain_edge_texture.png"
    expected = victim.read_bytes()
    victim.unlink()
    others = {p: p.stat().st_mtime_ns for p in out.rglob("*.png") if p != victim}
    res = generate(*args)
    assert res.returncode == 0, res.stderr
    assert "1 missing" in res.stderr
    assert victim.read_bytes() == expected  # pass cache gone: the view is rendered again, same bytes
    assert {p: p.stat().st_mtime_ns for p in others} == others


# ------------------------------------------------------------------------------------------ semantics,
# failures


def write_labelled_ply(path: Path) -> None:
    """Two boxes on a plate (metres, +Z up) with per-face class ids 1..3 and instance ids 11..13."""
    parts = [trimesh.creation.box(extents=[0.8, 0.8, 0.05]), trimesh.creation.box(extents=[0.25, 0.25, 0.3]),
             trimesh.creation.box(extents=[0.2, 0.3, 0.2])]
    parts[0].apply_translation([0, 0, -0.025])
    parts[1].apply_translation([-0.15, 0.1, 0.15])
    parts[2].apply_translation([0.2, -0.1, 0.1])
    verts, faces, cls, inst, off = [], [], [], [], 0
    for k, m in enumerate(parts):
        verts.append(m.vertices)
        faces.append(m.faces + off)
        off += len(m.vertices)
        cls += [k + 1] * len(m.faces)
        inst += [k + 11] * len(m.faces)
    v, f = np.concatenate(verts), np.concatenate(faces)
    head = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x", "property float y",
            "property float z", f"element face {len(f)}", "property list uchar int vertex_indices",
            "property int class_id", "property int instance_id", "end_header"]
    body = [" ".join(f"{c:.6f}" for c in p) for p in v]
    body += [f"3 {a} {b} {c} {k} {i}" for (a, b, c), k, i in zip(f.tolist(), cls, inst, strict=True)]
    path.write_text("\n".join(head + body) + "\n")


@pytest.mark.slow
def test_semantic_cues_of_a_labelled_space(tmp_path):
    ply = tmp_path / "boxes.ply"
    write_labelled_ply(ply)
    spec = tmp_path / "job.yaml"
    spec.write_text(
        "cameras: {mode: object, object_count: 6}\npoints: {count: 1, min_views: 2, max_views: 2}\n"
        "views: {resolution: 32}\nup_axis: '+z'\n"
    )
    out = tmp_path / "out"
    res = generate(ply, "--out", out, "--spec", spec, "--cues",
                   "segment_semantic,segment_instance,segment_panoptic", "--workers", 2)
    assert res.returncode == 0, res.stderr
    seen: set[int] = set()
    for v in (0, 1):
        key = f"{{c}}/omnidata/boxes/point_0_view_{v}_domain_{{c}}.png"
        sem = np.asarray(Image.open(out / key.format(c="segment_semantic")))
        inst = np.asarray(Image.open(out / key.format(c="segment_instance")))
        pan = np.asarray(Image.open(out / key.format(c="segment_panoptic")))
        assert sem.dtype == np.uint8 and inst.dtype == np.uint16 and pan.shape == (32, 32, 3)
        labelled = inst > 0
        assert labelled.any()
        np.testing.assert_array_equal(inst[labelled], sem[labelled].astype(np.uint16) + 10)  # the PLY's pairs
        np.testing.assert_array_equal(pan[..., 0], sem)  # R = class, G*256+B = instance
        np.testing.assert_array_equal(pan[..., 1].astype(np.int64) * 256 + pan[..., 2], inst)
        seen |= set(np.unique(sem[labelled]).tolist())
    assert seen and seen <= {1, 2, 3}


@pytest.mark.slow
def test_failed_outputs_give_exit_1_and_a_summary(scenes_dir, tmp_path):
    out = tmp_path / "out"
    (out / "normal" / "omnidata").mkdir(parents=True)
    (out / "normal" / "omnidata" / "ycb_banana").write_text("a file where the worker needs a folder")
    spec = tmp_path / "job.yaml"
    spec.write_text(TINY + "max_attempts: 1\n")
    res = generate(scenes_dir / "ycb_banana", "--out", out, "--spec", spec, "--cues", "rgb,normal,reshading",
                   "--workers", 2)
    assert res.returncode == 1, res.stderr
    assert "job failed" in res.stderr
    assert "normal: 4 failed; first error: StorageError: cannot write to the object folder" in res.stderr
    assert "reshading: 4 failed; first error: UpstreamFailed" in res.stderr  # the job never hangs on them
    assert len(list((out / "rgb").rglob("*.png"))) == 4


# ------------------------------------------------------------------------------------------ bad input


def run_cli(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str]:
    code = main(["generate", *map(str, args), "--no-progress"])
    return code, capsys.readouterr().err


def test_missing_space_is_refused_and_nothing_is_created(capsys, tmp_path):
    out = tmp_path / "out"
    code, err = run_cli(capsys, tmp_path / "nope.obj", "--out", out)
    assert code == 2 and "omnidata generate: error:" in err and "nope.obj: no such file" in err
    assert not out.exists()


def test_bad_spec_files_and_values_are_refused(capsys, scenes_dir, tmp_path):
    out = tmp_path / "out"
    banana = scenes_dir / "ycb_banana"
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("views: {resolution: [\n")
    code, err = run_cli(capsys, banana, "--out", out, "--spec", bad_yaml)
    assert code == 2 and "not valid YAML" in err
    code, err = run_cli(capsys, banana, "--out", out, "--spec", tmp_path / "missing.yaml")
    assert code == 2 and "no such file" in err
    code, err = run_cli(capsys, banana, "--out", out, "--resolution", "5")
    assert code == 2 and "views.resolution" in err
    typo = tmp_path / "typo.yaml"
    typo.write_text("pionts: {count: 3}\n")
    code, err = run_cli(capsys, banana, "--out", out, "--spec", typo)
    assert code == 2 and "pionts" in err
    code, err = run_cli(capsys, banana, "--out", out, "--workers", "0")
    assert code == 2 and "--workers" in err
    squash = tmp_path / "squash.json"
    squash.write_text(json.dumps([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0.5, 0], [0, 0, 0, 1]]))
    code, err = run_cli(capsys, banana, "--out", out, "--source-to-world", squash)
    assert (
        code == 2
        and "source_to_world" in err
        and "uniform scale" in err
        and len(err.strip().splitlines()) == 1
    )
    code, err = run_cli(capsys, banana, "--out", out, "--unit-scale", "5000")  # a 1 km banana
    assert code == 2 and "unit_scale" in err
    assert not out.exists()


def test_unknown_and_unsupported_cues_are_refused(capsys, scenes_dir, tmp_path):
    out = tmp_path / "out"
    code, err = run_cli(capsys, scenes_dir / "ycb_banana", "--out", out, "--cues", "rgb,depth")
    assert code == 2 and "unknown cue(s): depth" in err and "known cues: rgb" in err
    code, err = run_cli(capsys, scenes_dir / "ycb_banana", "--out", out, "--cues", "rgb,segment_semantic")
    assert code == 2 and "segment_semantic" in err and "semantic labels" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    code, err = run_cli(capsys, empty, "--out", out)
    assert code == 2 and "holds no mesh" in err
    code, err = run_cli(capsys, scenes_dir / "ycb_banana", scenes_dir / "ycb_banana", "--out", out)
    assert code == 2 and "share the name" in err
    assert not out.exists()


def test_helpers_name_spaces_and_fingerprint_requests(scenes_dir):
    from services.core.domain.jobspec import JobSpec
    from services.core.domain.keys import space_name
    from services.embedded.job import job_fingerprint

    assert space_name(scenes_dir / "ycb_banana") == "ycb_banana"
    assert space_name(Path("/x/My Scan (2).ply")) == "My_Scan_2"
    a, b = JobSpec(seed=1), JobSpec(seed=2)
    assert job_fingerprint(a, ["c1"]) == job_fingerprint(JobSpec(seed=1), ["c1"])
    assert job_fingerprint(a, ["c1"]) != job_fingerprint(b, ["c1"]) != job_fingerprint(a, ["c2"])
