"""Benchmark: reading a job's output as a dataset, previews and export, on real 512x512 renders.

Renders a small job of the banana (every default cue) with `omnidata generate`, then measures:
- OmnidataDataset items/s (one process, no DataLoader workers) for all cues and for rgb+depth+normal;
- preview time per cue (made from the file, then read back from the cache);
- `omnidata export --format webdataset` views/s.

Writes bench/results/datasets.json.
Run: .venv/bin/python bench/output/datasets.py [--resolution 512] [--views 4]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.cli import main  # noqa: E402
from services.core.domain.cues import default_cues  # noqa: E402
from services.core.storage import LocalStore  # noqa: E402
from services.datasets import OmnidataDataset  # noqa: E402
from services.datasets.previews import cached_preview  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _timed(fn: Any, repeat: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def run(resolution: int, views: int) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-datasets-"))
    try:
        spec = tmp / "job.yaml"
        spec.write_text(f"cameras: {{mode: object, object_count: 6}}\n"
                        f"points: {{count: {max(1, views // 2)}, min_views: 2, max_views: 2}}\n"
                        f"views: {{resolution: {resolution}}}\n")
        out = tmp / "job"
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable, "-m", "services.cli", "generate",
                str(REPO.parent / "shared/scenes/ycb_banana"), "--out", str(out), "--spec", str(spec),
                "--workers", "1", "--no-progress",
            ],
            cwd=REPO, check=True, capture_output=True,
        )
        render_s = time.perf_counter() - t0
        cues = default_cues(has_semantics=False)
        full = OmnidataDataset(out, cues)
        core = OmnidataDataset(out, ["rgb", "depth_zbuffer", "normal"])
        n = len(full)
        full_s = _timed(lambda: [full[i] for i in range(n)], 2) / n
        core_s = _timed(lambda: [core[i] for i in range(n)], 2) / n
        store = LocalStore(out, fsync=False)
        record = full.views[0]
        made: dict[str, float] = {}
        cached: dict[str, float] = {}
        for cue in cues:
            key = record.files[cue].key
            t0 = time.perf_counter()
            cached_preview(store, key, cue, point=record.point, view=record.view, resolution=resolution)
            made[cue] = time.perf_counter() - t0
            cached[cue] = _timed(lambda cue=cue, key=key: cached_preview(
                store, key, cue, point=record.point, view=record.view), 5)
        t0 = time.perf_counter()
        main(["export", str(out), "--format", "webdataset", "--out", str(tmp / "wds"), "--no-progress"])
        export_s = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in (tmp / "wds").glob("*.tar"))
        return {
            "resolution": resolution,
            "views": n,
            "render_s": round(render_s, 2),
            "dataset_item_ms_all_cues": round(1000 * full_s, 2),
            "dataset_items_per_s_all_cues": round(1 / full_s, 1),
            "dataset_item_ms_rgb_depth_normal": round(1000 * core_s, 2),
            "dataset_items_per_s_rgb_depth_normal": round(1 / core_s, 1),
            "preview_made_ms": {c: round(1000 * t, 2) for c, t in made.items()},
            "preview_made_ms_total_per_view": round(1000 * sum(made.values()), 1),
            "preview_cached_ms_total_per_view": round(1000 * sum(cached.values()), 2),
            "export_webdataset_views_per_s": round(n / export_s, 1),
            "export_webdataset_mb": round(size / 1e6, 2),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def cli() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=512)
    p.add_argument("--views", type=int, default=4)
    args = p.parse_args()
    result = run(args.resolution, args.views)
    result["machine"] = {
        "python": platform.python_version(), "cpu": platform.processor() or platform.machine(),
    }
    print(json.dumps(result, indent=2))
    out = results_dir() / "datasets.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    cli()
