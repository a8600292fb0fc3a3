"""The real-room corpus of bench/ingest/ingest_real.py: every room's file is there with its SOURCE.md, its
true up is a direction, and the held-out rooms are summed apart from the rooms the levelling was tuned on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.lib.results import RESULTS_ENV
from tests.conftest import REPO_ROOT

TRUTH = json.loads((REPO_ROOT / "bench" / "scans" / "rooms" / "truth.json").read_text())
FIELDS = ("file", "up", "truth_from", "source", "kind", "licence", "place")


def test_every_room_has_its_file_source_note_and_a_true_up() -> None:
    for name, room in TRUTH.items():
        assert all(room.get(k) for k in FIELDS), (name, [k for k in FIELDS if not room.get(k)])
        path = REPO_ROOT / room["file"]
        assert path.is_file(), (name, room["file"])
        assert (path.parent / "SOURCE.md").is_file(), (name, "no SOURCE.md beside the file")
        assert abs(np.linalg.norm(room["up"]) - 1.0) < 1e-3, (name, room["up"])


def test_held_out_rooms_are_reported_apart(tmp_path: Path) -> None:
    held = sorted(n for n, room in TRUTH.items() if room.get("held_out") and room.get("single_frame"))
    assert held, "no held-out single frame to run"
    out = tmp_path / "ingest_real.json"
    script = REPO_ROOT / "bench" / "ingest" / "ingest_real.py"
    # one case each: a cloud is meshed anew per case, as uploaded
    subprocess.run([sys.executable, str(script), "--rooms", "copyroom", held[0], "--cases", "delivered",
                    "tilted_x", "--out", str(out)],
                   check=True, cwd=REPO_ROOT, capture_output=True,
                   env={**os.environ, "PYTHONPATH": str(REPO_ROOT), RESULTS_ENV: str(tmp_path),
                        "OMNIDATA_DATA_DIR": str(tmp_path / "data")})
    result = json.loads(out.read_text())["real_rooms"]
    assert result["held_out"]["files"] == [held[0]]
    assert result["held_out"]["single_depth_frames"]["cases"] == 1
    assert result["rooms"]["cases"] == 1  # copyroom alone: the held-out frame is not in the main figure
    assert result["single_depth_frames"]["cases"] == 0
    # the tilted copies are reported apart from the protocol's cases
    tilted = result["tilted_about_a_wall"]
    assert tilted["rooms"]["cases"] == 1 and tilted["single_depth_frames"]["cases"] == 1
    assert {r["case"] for r in tilted["rows"]} == {"tilted_x"}
