"""Benchmark: how stable the segment cues' labels are on real rooms, and what cheaper definitions of them
change (issue 20: the two segmentations are most of a view's derivations, and a change to them is held to ARI
>= 0.9 per view, segment counts within 20%, against the current labels:
tests/worker/cues/test_equivalence.py).

For each room (bench/lib/rooms.py) it takes --views planner views at 512 px (the pass sets
bench/cues/derivations.py renders and caches) and makes both segment cues as they are. Then, on the same
views:
- the noise floor: the cues as they are, on the view with an imperceptible change of its input. 2d: one of 255
  added or taken on 1% of the colour pixels (within the 8-bit image's own quantisation); 2.5d: the depth of 1%
  of the pixels scaled by 1 +- 1e-6 (a micrometre a metre). How far the labels move then is how far the
  current definition itself is from "the same labels": no change of definition can be held closer than that.
- each candidate definition, a cheaper variant of one step: Felzenszwalb on the 4-connected grid (half the
  edges), its sort quantised to 4,096 levels instead of 65,536, at most 384 superpixels instead of 512, the
  normalized cuts' eigenvector in float32 (ssyevr); and one that is no cheaper, the eigenvector's sign flipped
  (dsyevr's sign is arbitrary: how much the labels hang on it). Each is timed against the current definition
  on the same view in the same process, the two alternating (CPU seconds of both cues, their inputs made
  once).
Per room, cue and variant: the ARI against the current labels (minimum, 10th percentile, median), the share of
views within the per-view bound, and (candidates) the CPU seconds a view saved: the median of the paired
differences. Writes bench/results/segment_stability.json (the previous run kept under "before").
Run: .venv/bin/python bench/cues/segment_stability.py [--views 8] [--repeats 2] [--rooms icl_livingroom,...]
"""

from __future__ import annotations

import os
import sys

if hasattr(os, "sched_setaffinity"):  # one core, one thread, before numpy starts its pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from contextlib import AbstractContextManager  # noqa: E402
from pathlib import Path  # noqa: E402
from unittest.mock import patch  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.cues.derivations import room_views  # noqa: E402
from bench.lib.results import results_dir  # noqa: E402
from bench.lib.rooms import ROOMS  # noqa: E402
from services.core.domain.jobspec import CueParams  # noqa: E402
from services.worker.context import ViewContext  # noqa: E402
from services.worker.cues import ncuts, segmentation  # noqa: E402
from services.worker.cues.edges import occlusion_response  # noqa: E402
from services.worker.cues.felzenszwalb import Felzenszwalb  # noqa: E402
from services.worker.passes import ViewPasses  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402
from tests.fixtures.segment_agreement import (  # noqa: E402
    adjusted_rand_index,
    equivalence_failures,
    imperceptibly_perturbed,
)

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "segment_stability.json"
NOISE_SHARE = 0.01  # of the pixels changed by the noise floor's perturbation
DEPTH_NOISE = 1e-6  # relative
CUES = ("segment_unsup2d", "segment_unsup25d")


def _f32_second_eigenvector(A: np.ndarray) -> np.ndarray:
    from scipy.linalg.lapack import _compute_lwork, get_lapack_funcs

    syevr, syevr_lwork = get_lapack_funcs(("syevr", "syevr_lwork"), dtype=np.float32)
    lwork, liwork = _compute_lwork(syevr_lwork, n=len(A), lower=True)
    _, vecs, _, _, info = syevr(A.astype(np.float32), compute_v=1, range="I", il=1, iu=2, lower=True,
                                lwork=int(lwork), liwork=int(liwork))
    if info != 0:
        raise np.linalg.LinAlgError(f"ssyevr failed (info {info})")
    return vecs[:, 1].astype(np.float64)


_SUPERPIXELS = segmentation.superpixels


def _capped_superpixels(
    features: np.ndarray, scale: float, sigma: float, min_size: int, max_count: int
) -> np.ndarray:
    return _SUPERPIXELS(features, scale, sigma, min_size, min(max_count, 384))


_SECOND_EIGENVECTOR = ncuts.second_eigenvector


def _flipped_second_eigenvector(A: np.ndarray) -> np.ndarray:
    return -_SECOND_EIGENVECTOR(A)


# name -> what makes the variant current for the duration of a `with`
CANDIDATES: dict[str, Callable[[], AbstractContextManager[object]]] = {
    "connectivity_4": lambda: patch.object(
        segmentation, "Felzenszwalb", functools.partial(Felzenszwalb, connectivity=4)
    ),
    "sort_levels_4096": lambda: patch.object(
        segmentation, "Felzenszwalb", functools.partial(Felzenszwalb, levels=4096)
    ),
    "max_superpixels_384": lambda: patch.object(segmentation, "superpixels", _capped_superpixels),
    "float32_eigenvector": lambda: patch.object(ncuts, "second_eigenvector", _f32_second_eigenvector),
    # not cheaper: how much the labels hang on the eigenvector's sign, which dsyevr leaves arbitrary
    "eigenvector_sign_flipped": lambda: patch.object(
        ncuts, "second_eigenvector", _flipped_second_eigenvector
    ),
}


def both_cues(p: ViewPasses, params: CueParams) -> tuple[list[np.ndarray], float]:
    """The two segment cues of a view (labels) and their CPU seconds; the occlusion response, an input both
    definitions share, made first and not counted."""
    ctx = ViewContext(None, params, passes=p)
    occlusion_response(ctx)
    c0 = time.process_time()
    labels = [segmentation.segment_unsup2d(ctx), segmentation.segment_unsup25d(ctx)]
    return labels, time.process_time() - c0


def agreement(current: list[np.ndarray], other: list[np.ndarray]) -> list[dict]:
    """Per cue: ARI, and whether the view is within the per-view bound
    (tests/worker/cues/test_equivalence.py)."""
    return [{"ari": adjusted_rand_index(a, b), "within": not equivalence_failures(a, b),
             "identical": bool(np.array_equal(a, b)), "segments": [int(a.max()), int(b.max())]}
            for a, b in zip(current, other, strict=True)]


def summary(rows: list[dict]) -> dict:
    """ARI distribution over views whose current labels have more than one segment (ICL's grey colour image
    has one)."""
    rows = [r for r in rows if r["segments"][0] > 1]
    if not rows:
        return {"views": 0}
    ari = np.array([r["ari"] for r in rows])
    return {
        "views": len(rows), "ari_min": round(float(ari.min()), 3),
        "ari_p10": round(float(np.quantile(ari, 0.1)), 3), "ari_median": round(float(np.median(ari)), 3),
        "within_bound": round(float(np.mean([r["within"] for r in rows])), 3),
        "identical": round(float(np.mean([r["identical"] for r in rows])), 3),
    }


def run_room(room: str, n_views: int, repeats: int, cache: Path) -> dict:
    passes, _, _ = room_views(room, n_views, 512, cache)
    params = CueParams()
    both_cues(passes[0], params)  # kernels loaded
    current = [both_cues(p, params)[0] for p in passes]
    noise = [agreement(c, both_cues(imperceptibly_perturbed(p, i, NOISE_SHARE, DEPTH_NOISE), params)[0])
             for i, (c, p) in enumerate(zip(current, passes, strict=True))]
    result: dict = {"views": len(passes), "noise_floor": {cue: summary([n[k] for n in noise])
                                                         for k, cue in enumerate(CUES)}, "candidates": {}}
    for name, make in CANDIDATES.items():
        with make():
            both_cues(passes[0], params)  # a variant's kernels compiled outside the timing
        rows, saved, current_s = [], [], []
        for _ in range(repeats):
            for c, p in zip(current, passes, strict=True):
                _, t_current = both_cues(p, params)
                with make():
                    labels, t_variant = both_cues(p, params)
                saved.append(t_current - t_variant)
                current_s.append(t_current)
                if len(rows) < len(passes):
                    rows.append(agreement(c, labels))
        result["candidates"][name] = {
            "cpu_s_saved_per_view_median": round(float(np.median(saved)), 4),
            "cpu_s_current_per_view_median": round(float(np.median(current_s)), 4),
            **{cue: summary([r[k] for r in rows]) for k, cue in enumerate(CUES)}}
        print(room, name, json.dumps(result["candidates"][name]), flush=True)
    print(room, "noise floor", json.dumps(result["noise_floor"]), flush=True)
    return result


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--rooms", default=",".join(ROOMS))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    t0, load_before = time.perf_counter(), os.getloadavg()
    rooms = {r: run_room(r, args.views, args.repeats, args.cache) for r in args.rooms.split(",")}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    run = {
        "commit": commit, "resolution": 512, "clock": "process CPU seconds, one core",
        "noise": f"2d: +-1/255 on {NOISE_SHARE:.0%} of the colour pixels; 2.5d: depth x (1 +- "
        f"{DEPTH_NOISE}) on {NOISE_SHARE:.0%} of the pixels",
        "bound": "per view: ARI >= 0.9, segment count within 20%, the same 'no surface' pixels",
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()], "wall_s": round(time.perf_counter() - t0, 1),
        "rooms": rooms,
    }
    data = (json.loads(RESULTS.read_text()) if RESULTS.exists()
            else {"benchmark": "bench/cues/segment_stability.py"})
    if "after" in data:
        data["before"] = data["after"]
    data["after"] = run
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
