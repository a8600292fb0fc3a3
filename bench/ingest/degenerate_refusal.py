"""Time to refuse a big OBJ of varied degenerate faces (issue 19 section 4): 10M faces, no two lines alike.

Each face is three distinct points on a line, or names a vertex twice; the lines vary, so the compression rule
(`archive_rules`) passes them, and before `services.core.ingest.guard.degenerate` the full parse ran (45 s for
10M faces in the issue). Measures `load_space` (what upload, register, plan and generate run) refusing the
file: process CPU and wall time, and the load average. Writes bench/results/degenerate_refusal.json.
Run: .venv/bin/python bench/ingest/degenerate_refusal.py [faces]
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.ingest.errors import SpaceError  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from tests.fixtures.hostile_corpus import varied_degenerate_obj  # noqa: E402

OUT = results_dir() / "degenerate_refusal.json"


def main() -> None:
    faces = int(sys.argv[1]) if len(sys.argv) > 1 else 10_000_000
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for collinear in (True, False):
            path = Path(tmp) / "scan.obj"
            path.write_bytes(varied_degenerate_obj(faces, collinear=collinear))
            cpu, wall = time.process_time(), time.perf_counter()
            try:
                load_space(path)
                refusal = None
            except SpaceError as e:
                refusal = str(e)
            rows.append(
                {
                    "faces": faces, "kind": "collinear" if collinear else "repeated vertex",
                    "file_mb": round(path.stat().st_size / 2**20, 1), "refused": refusal,
                    "cpu_s": round(time.process_time() - cpu, 2),
                    "wall_s": round(time.perf_counter() - wall, 2),
                    "load_avg_1m": round(os.getloadavg()[0], 2),
                }
            )
            print(rows[-1], flush=True)
    OUT.write_text(json.dumps({"machine": f"{os.cpu_count()} cores, shared", "runs": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
