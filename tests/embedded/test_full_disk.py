"""`omnidata generate` whose --out fills up mid-run (a real tmpfs and a ballast file): the run's database
lives on that disk too. The run waits, saying "storage full" on its bar, instead of crashing with "database or
disk is full", and finishes once space is back with every output present exactly once."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.fixtures.cli import REPO
from tests.fixtures.small_disk import fill, small_tmpfs

pytestmark = [pytest.mark.slow]

SPEC = """
cameras: {mode: object, object_count: 12}
points: {count: 24, min_views: 3, max_views: 3}
views: {resolution: 128}
cues: [rgb, normal, point_info]
seed: 5
"""


def test_generate_waits_for_a_full_disk_and_finishes_once_space_returns(tmp_path: Path,
                                                                         scenes_dir: Path) -> None:
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    with small_tmpfs(tmp_path / "out", 128) as out:
        log = (tmp_path / "generate.log").open("w")
        args = ["generate", str(scenes_dir / "ycb_banana"), "--out", str(out), "--spec", str(spec),
                "--workers", "2"]
        run = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=REPO, stdout=log,
                               stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 180
            while not any((out / "rgb").rglob("*.png")):
                assert run.poll() is None and time.monotonic() < deadline, \
                    (tmp_path / "generate.log").read_text()
                time.sleep(0.1)
            ballast = fill(out)
            # full for a while: workers, scheduler and the database meet ENOSPC, and the bar says so (on a
            # loaded machine the run may need more than the 10 s to reach a write)
            full_since = time.monotonic()
            while (time.monotonic() - full_since < 10
                   or "waiting: storage full" not in (tmp_path / "generate.log").read_text()):
                assert run.poll() is None and time.monotonic() - full_since < 180, \
                    (tmp_path / "generate.log").read_text()[-3000:]
                time.sleep(0.2)
            ballast.unlink()
            freed = time.monotonic()
            rc = run.wait(timeout=240)
        finally:
            if run.poll() is None:
                run.kill()
            log.close()
        text = (tmp_path / "generate.log").read_text()
        assert rc == 0, text[-3000:]
        assert "waiting: storage full" in text
        manifest = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
        keys = [o["key"] for e in manifest for o in e["outputs"].values()]
        files = {p.relative_to(out).as_posix() for cue in ("rgb", "normal", "point_info")
                 for p in (out / cue).rglob("*") if p.is_file()}
        assert len(keys) == len(set(keys)) and set(keys) == files and len(manifest) > 0
        assert not list(out.rglob(".*.tmp-*"))
        print(f"\ngenerate: space back -> done in {time.monotonic() - freed:.1f} s ({len(manifest)} views)")
