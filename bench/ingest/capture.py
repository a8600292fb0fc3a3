"""Benchmark: posed captures (issue 18) on the real 7-Scenes capture of ../shared/scenes/7scenes_redkitchen.

- import: seconds per 1000 frames to detect and read a capture, every frame checked (pose, image header): the
  100 real frames copied ten times (7-Scenes layout, 1000 frames; --import-copies), and COLMAP text and
  nerfstudio transforms.json captures of as many small photos;
- capture views: Cycles render + cue cost of a view at a capture camera with the photo as rgb vs the same view
  with mesh rgb (the pass set, rgb and mask_photo), CPU seconds of this process;
- photo texturing: seconds per novel view and the share of its surface pixels some photo covers, for views
  0.3 m beside capture cameras (passes from an embree ray cast, so Blender is not timed);
- alignment: score distribution of the raw depth-camera poses and of SOURCE.md's fitted colour camera, all
  frames;
- big photos (issue 51): `omnidata generate` end to end, as a user runs it, of the banana with two
  48-megapixel photos (8000 x 6000; PNG in a transforms.json capture, JPEG in a COLMAP one), two exact capture
  views at 128 px with every default cue: wall seconds and the peak RSS of the largest process
  (/usr/bin/time -v), beside the same capture with its 200 x 150 photos.
Run: `.venv/bin/python bench/ingest/capture.py` (about 4 minutes on a shared 2-core machine); `--only
big_photos` runs the last alone and updates its key. Writes bench/results/capture.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.lib.results import results_dir  # noqa: E402
from services.core.ingest.capture import find_capture  # noqa: E402
from services.core.ingest.capture.photos import Photo, load_photo  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from tests.fixtures.captures import toy_frames, write_colmap, write_transforms  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
KITCHEN = REPO.parent / "shared" / "scenes" / "7scenes_redkitchen"
BANANA = REPO.parent / "shared" / "scenes" / "ycb_banana" / "textured_simple_reoriented.obj"
BIG_UPSCALE = 40  # the fixture's 200 x 150 photos made 8000 x 6000: 48 Mpx, a phone's full-resolution photo
BIG_NOTE = ("wall: the whole generate (Blender start-up included) on a shared 2-core machine; peak RSS: the "
            "largest process of the run (/usr/bin/time -v); *_baseline: the same captures, the code before "
            "(--baseline-code)")


def import_figures(tmp: Path, copies: int = 10) -> dict[str, float]:
    """Seconds per 1000 frames to find and read a capture, per format (`copies` of the kitchen's 100 frames,
    as many toy frames)."""
    out = {}
    n = 100 * copies
    seven = tmp / "seven"
    (seven).mkdir()
    shutil.copy(KITCHEN / "camera-intrinsics.txt", seven)
    for s in range(copies):
        d = seven / f"seq-{s:02d}"
        d.mkdir()
        for f in (KITCHEN / "frames").glob("frame-*"):
            if not f.name.endswith(".depth.png"):
                shutil.copy(f, d / f.name)
    frames = toy_frames(n, size=(160, 120))
    write_colmap(tmp / "colmap", frames)
    write_transforms(tmp / "transforms", frames)
    for name, root in (("7scenes_real_640x480", seven), ("colmap_text", tmp / "colmap"),
                       ("transforms_json", tmp / "transforms")):
        t0 = time.perf_counter()
        cap = find_capture(root)
        dt = time.perf_counter() - t0
        assert cap is not None and len(cap.frames) == n, (name, cap and cap.problems[:3])
        out[f"{name}_s_per_1000_frames"] = round(dt * 1000 / n, 3)
    return out


def view_cost(space, n_views: int, resolution: int) -> dict[str, float]:
    """CPU seconds per capture view (photo rgb) and per the same view with mesh rgb."""
    from services.core.domain.jobspec import JobSpec
    from services.scheduler.planning import make_plan, space_rng
    from services.worker.executor import make_context, produce
    from services.worker.inputs.photos import PhotoPainter
    from services.worker.inputs.space_cache import SpaceContext

    spec = JobSpec.model_validate({"cameras": {"mode": "capture"}, "views": {"resolution": resolution}})
    plan = make_plan(space, spec, space_rng(0, "kitchen"), "kitchen")
    views = plan.views[:: max(1, len(plan.views) // n_views)][:n_views]
    out = {}
    for label, photos, cues in (("mesh_rgb", None, ["passes", "rgb"]),
                                ("photo_rgb", PhotoPainter(space.capture), ["passes", "rgb", "mask_photo"])):
        ctx_space = SpaceContext(key=label, mesh=space.mesh, photos=photos)
        ctx_space.scene()  # build the Blender scene outside the timing
        produce("rgb", make_context(ctx_space, views[0], cues, plan=plan))  # warm up
        t0 = time.process_time()
        for v in views:
            ctx = make_context(ctx_space, v, cues, plan=plan)
            for c in cues:
                produce(c, ctx)
        out[f"{label}_cpu_s_per_view"] = round((time.process_time() - t0) / len(views), 4)
        ctx_space.close()
    out["views"] = len(views)
    out["resolution"] = resolution
    out["photo_over_mesh"] = round(out["photo_rgb_cpu_s_per_view"] / out["mesh_rgb_cpu_s_per_view"], 3)
    return out


def texture_figures(space, n_views: int, resolution: int) -> dict[str, float]:
    """Seconds per photo-textured novel view and the covered share of its surface pixels."""
    from services.worker.inputs.phototexture import PhotoTexturer
    from services.worker.passes import ViewGeometry
    from tests.fixtures.raycast import raycast_passes

    cap = space.capture
    tex = PhotoTexturer(space.mesh, cap, k=3)
    photos: dict[int, Photo] = {}
    focal = resolution / 2 / np.tan(np.radians(60.0) / 2)

    def photo(i: int) -> Photo:
        if i not in photos:
            photos[i] = load_photo(str(cap.image_path(cap.frames[i])), cap.frames[i], focal)
        return photos[i]

    times, shares = [], []
    for f in cap.frames[:: max(1, len(cap.frames) // n_views)][:n_views]:
        W = f.world_to_camera.copy()
        W[:3, 3] -= np.array([0.3, 0.0, 0.0])  # the camera moved 0.3 m along its own x axis
        g = ViewGeometry(W, np.radians(60.0), resolution)
        passes = raycast_passes(space.mesh, g)
        t0 = time.perf_counter()
        _, covered = tex.paint(g, passes, photo)
        times.append(time.perf_counter() - t0)
        hit = passes.hit
        shares.append(float(covered[hit].mean()) if hit.any() else 0.0)
    return {
        "views": len(times), "resolution": resolution, "k": 3,
        "s_per_view_median": round(float(np.median(times)), 3),
        "covered_share_median": round(float(np.median(shares)), 3),
        "covered_share_min": round(float(np.min(shares)), 3),
    }


def alignment_figures(space, frames: int = 0) -> dict[str, object]:
    """Alignment score quantiles of the raw depth-camera poses and the fitted colour camera (SOURCE.md), over
    the first `frames` frames (0: all)."""
    from services.core.ingest.capture.model import CaptureFrame
    from services.scheduler.planning.alignment import alignment_score
    from services.scheduler.planning.visibility import MeshQueries

    K = np.array([[526.0, 0.0, 324.5], [0.0, 526.0, 235.5], [0.0, 0.0, 1.0]])
    shift = np.eye(4)
    shift[:3, 3] = [0.035, -0.010, 0.0]
    q = MeshQueries(space.mesh)
    raw, colour = [], []
    t0 = time.perf_counter()
    for f in space.capture.frames[:frames or None]:
        img = load_photo(str(space.capture.image_path(f)), f)
        raw.append(alignment_score(q, img, f, f.world_to_camera, f.inscribed_fov()))
        c = CaptureFrame(f.name, f.image, f.width, f.height, K, "none", (), f.camera_to_world @ shift)
        colour.append(alignment_score(q, img, c, c.world_to_camera, c.inscribed_fov()))
    seconds = (time.perf_counter() - t0) / (2 * len(raw))
    r, c = np.array(raw, dtype=float), np.array(colour, dtype=float)

    def quantiles(x: np.ndarray) -> dict[str, float]:
        return {k: round(float(v), 3) for k, v in zip(("min", "p25", "median", "p75", "max"),
                                                      np.quantile(x, [0, 0.25, 0.5, 0.75, 1]), strict=True)}

    return {"frames": len(r), "raw_depth_camera": quantiles(r), "fitted_colour_camera": quantiles(c),
            "colour_beats_raw_share": round(float(np.mean(c > r)), 3), "s_per_score": round(seconds, 3)}


def timed_generate(folder: Path, out: Path, spec: Path, code: Path = REPO) -> dict[str, float]:
    """Wall seconds and peak RSS (MB, the largest process of the run) of `omnidata generate` under
    /usr/bin/time, run from the checkout `code`."""
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "services.cli", "generate", str(folder),
           "--out", str(out), "--spec", str(spec), "--workers", "1", "--no-progress"]
    t0 = time.perf_counter()
    run = subprocess.run(cmd, cwd=code, capture_output=True, text=True, timeout=1800,
                         env={**os.environ, "PYTHONPATH": str(code)})
    wall = time.perf_counter() - t0
    if run.returncode != 0:
        raise RuntimeError(f"generate failed ({run.returncode}): {run.stderr[-2000:]}")
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", run.stderr)
    assert peak is not None, run.stderr[-2000:]
    peak_kb = int(peak.group(1))
    views = len(list((out / "rgb").rglob("*.png")))
    return {"wall_s": round(wall, 1), "peak_rss_mb": round(peak_kb / 1024), "views": views}


def big_photo_figures(tmp: Path, baseline: Path | None = None) -> dict[str, object]:
    """The big-photo cases of the module docstring: one generate each, two views at 128 px, every default
    cue; with `baseline` (another checkout), its generate of the same 48-megapixel captures as well."""
    from tests.fixtures.photo_capture import banana_capture

    spec = tmp / "capture.yaml"
    spec.write_text("cameras: {mode: capture}\nviews: {resolution: 128}\n")
    out: dict[str, object] = {"views": 2, "resolution": 128, "cues": "every default cue",
                              "photos": f"2 x {200 * BIG_UPSCALE} x {150 * BIG_UPSCALE}", "note": BIG_NOTE}
    for label, upscale, writer in (("small_photos_200x150_jpeg_colmap", 1, write_colmap),
                                   ("48mp_png_transforms", BIG_UPSCALE, write_transforms),
                                   ("48mp_jpeg_colmap", BIG_UPSCALE, write_colmap)):
        folder = tmp / label / "banana_capture"
        banana_capture(BANANA, folder, n=2, upscale=upscale, writer=writer)
        photo_mb = sum(p.stat().st_size for p in folder.rglob("*") if p.suffix in (".png", ".jpg") and
                       "images" in p.parts) / 2**20
        figures = timed_generate(folder, tmp / label / "out", spec)
        out[label] = {**figures, "photo_files_mb": round(photo_mb, 1)}
        print(label, json.dumps(out[label]), flush=True)
        if baseline is not None and upscale > 1:
            key = f"{label}_baseline"
            out[key] = {**timed_generate(folder, tmp / label / "out_baseline", spec, baseline),
                        "code": _revision(baseline)}
            print(key, json.dumps(out[key]), flush=True)
    return out


def _revision(code: Path) -> str:
    """The commit a checkout is at (its short hash and subject)."""
    return subprocess.run(["git", "-C", str(code), "log", "-1", "--format=%h %s"], capture_output=True,
                          text=True).stdout.strip()[:100]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--out", type=Path, default=results_dir() / "capture.json")
    parser.add_argument("--only", choices=["big_photos"], help="run this scenario alone and update its key")
    parser.add_argument("--baseline-code", type=Path, help="big photos: also generate with this checkout")
    parser.add_argument(
        "--alignment-frames", type=int, default=0, help="frames the alignment scores (0: all)"
    )
    parser.add_argument("--import-copies", type=int, default=10,
                        help="the import figures read the kitchen's 100 frames this many times over")
    parser.add_argument("--no-big-photos", dest="big_photos", action="store_false",
                        help="leave out the big-photo generates (minutes; a smoke run)")
    args = parser.parse_args()
    if args.only == "big_photos":
        kept = json.loads(args.out.read_text()) if args.out.exists() else {}
        with tempfile.TemporaryDirectory(prefix="bench-capture-") as tmp:
            kept["big_photos"] = big_photo_figures(Path(tmp), args.baseline_code)
        args.out.write_text(json.dumps(kept, indent=2) + "\n")
        print(f"wrote {args.out}")
        return
    result: dict[str, object] = {"machine": f"{platform.machine()} {platform.node()}",
                                 "note": "shared machine: 2 cores, loaded by other developers' work"}
    with tempfile.TemporaryDirectory(prefix="bench-capture-") as tmp:
        result["import"] = import_figures(Path(tmp), args.import_copies)
    print(json.dumps(result["import"]))
    space = load_space(KITCHEN)
    result["alignment"] = alignment_figures(space, args.alignment_frames)
    print(json.dumps(result["alignment"]))
    result["texture"] = texture_figures(space, args.views, args.resolution)
    print(json.dumps(result["texture"]))
    result["capture_view_cost"] = view_cost(space, args.views, args.resolution)
    print(json.dumps(result["capture_view_cost"]))
    if args.big_photos:
        with tempfile.TemporaryDirectory(prefix="bench-capture-") as tmp:
            result["big_photos"] = big_photo_figures(Path(tmp), args.baseline_code)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
