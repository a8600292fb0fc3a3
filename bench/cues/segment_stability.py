"""Benchmark: the acceptance rule for a cheaper definition of a segment cue, on real rooms: a definition is
accepted when its labels agree with the previous definition's at least as well as the previous definition
agrees with itself under imperceptible input noise (median and 10th percentile of the per-view ARI, over the
same views, in the same run).

For each room (bench/lib/rooms.py) it takes --views planner views at 512 px (the pass sets
bench/cues/derivations.py renders and caches) and makes each segment cue with the previous definition
(PREVIOUS_DEFINITION: 8-connected Felzenszwalb, its sort in 2^16 levels, at most segment_max_superpixels
regions, eigenvectors in float64, links below 1e-10 absent). Then, on the same views:
- the noise floor: the previous definition on the view with its inputs moved by one level of their stored
  encoding on 1% of the pixels (tests/fixtures/segment_agreement.imperceptibly_perturbed). 2d: one grey level
  of the 8-bit colour. 2.5d: the cue's inputs are geometric, so the equivalent is one level of the stored
  geometry: one step (1/512 m) of the 16-bit depth and one level (2/255) of each 8-bit normal channel. A
  change the dataset's own files cannot show is as imperceptible for depth and normals as one grey level is
  for colour; a relative change of 1e-6 (what this bench used before) moves nothing, and a bound measured on
  it would demand identical labels.
- each candidate definition: cheaper variants of a step and their combinations (CANDIDATES), and one that is
  no cheaper, the eigenvector's sign flipped (dsyevr's sign is arbitrary). The shipped definition
  (segmentation.DEFINITIONS) is the candidate "shipped".
Per room, cue and candidate: ARI against the previous labels (minimum, 10th percentile, median; views whose
previous labels have more than one segment), PASS when median >= the noise floor's median and 10th
percentile >= the noise floor's 10th percentile, and the CPU ms a view saved: the median of the paired
differences of the cue timed alone in a fresh context, previous and candidate alternating on one core (the
occlusion response, an input both share, made first and not counted). Writes
bench/results/segment_stability.json (the previous run kept under "before").
Run: .venv/bin/python bench/cues/segment_stability.py [--views 8] [--repeats 3] [--rooms icl_livingroom,...]
[--candidates shipped,...]
"""

from __future__ import annotations

import os
import sys

if hasattr(os, "sched_setaffinity"):  # one core, one thread, before numpy starts its pools
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
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
from services.worker.cues.segmentation import Definition  # noqa: E402
from services.worker.passes import ViewPasses  # noqa: E402
from services.worker.process.heap import keep_freed_memory  # noqa: E402
from tests.fixtures.segment_agreement import (  # noqa: E402
    PREVIOUS_DEFINITION,
    adjusted_rand_index,
    imperceptibly_perturbed,
    noise_floor_failures,
    previous_definitions,
)

ROOT = Path(__file__).resolve().parents[2]
RESULTS = results_dir() / "segment_stability.json"
NOISE_SHARE = 0.01  # of the pixels each input's perturbation changes
CUES = ("segment_unsup2d", "segment_unsup25d")


_SECOND_EIGENVECTOR = ncuts.second_eigenvector


def _flipped_second_eigenvector(A: np.ndarray, precision: str = "float64") -> np.ndarray:
    return -_SECOND_EIGENVECTOR(A, precision)


@contextlib.contextmanager
def variant(max_superpixels: int | None = None,
            eigenvector: Callable[[np.ndarray, str], np.ndarray] | None = None,
            **changes: object) -> Iterator[None]:
    """Both cues with PREVIOUS_DEFINITION changed by `changes` (Definition fields), at most max_superpixels
    regions and `eigenvector` solving the cuts' eigenproblems, for the duration of the `with`."""
    definition = dataclasses.replace(PREVIOUS_DEFINITION, **changes)  # type: ignore[arg-type]
    superpixels = segmentation.superpixels

    def capped(features: np.ndarray, scale: float, sigma: float, min_size: int, max_count: int,
               d: Definition = definition) -> np.ndarray:
        return superpixels(features, scale, sigma, min_size, min(max_count, max_superpixels or max_count), d)

    with contextlib.ExitStack() as stack:
        stack.enter_context(patch.dict(segmentation.DEFINITIONS, dict.fromkeys(CUES, definition)))
        if max_superpixels:
            stack.enter_context(patch.object(segmentation, "superpixels", capped))
        if eigenvector:
            stack.enter_context(patch.object(ncuts, "second_eigenvector", eigenvector))
        yield


# name -> what makes the candidate current for the duration of a `with`
CANDIDATES: dict[str, Callable[[], contextlib.AbstractContextManager[object]]] = {
    "shipped": contextlib.nullcontext,  # segmentation.DEFINITIONS as they are
    "connectivity_4": lambda: variant(connectivity=4),
    "sort_levels_4096": lambda: variant(sort_levels=4096),
    "max_superpixels_384": lambda: variant(max_superpixels=384),
    "max_superpixels_256": lambda: variant(max_superpixels=256),
    "float32_eigenvector": lambda: variant(eigenvectors="float32"),
    "link_eps_1e-3": lambda: variant(link_eps=1e-3),
    "link_eps_1e-4+float32_eigenvector": lambda: variant(link_eps=1e-4, eigenvectors="float32"),
    "link_eps_1e-2+float32_eigenvector": lambda: variant(link_eps=1e-2, eigenvectors="float32"),
    "connectivity_4+max_superpixels_384": lambda: variant(connectivity=4, max_superpixels=384),
    "connectivity_4+float32_eigenvector+link_eps_1e-3": lambda: variant(
        connectivity=4, eigenvectors="float32", link_eps=1e-3
    ),
    # not cheaper: how much the labels hang on the eigenvector's sign, which dsyevr leaves arbitrary
    "eigenvector_sign_flipped": lambda: variant(eigenvector=_flipped_second_eigenvector),
}


def one_cue(p: ViewPasses, params: CueParams, cue: str) -> tuple[np.ndarray, float]:
    """The cue's labels on a fresh context and its CPU seconds; the occlusion response (an input of the 2.5d
    cue every definition shares) made first and not counted."""
    ctx = ViewContext(None, params, passes=p)
    occlusion_response(ctx)
    c0 = time.process_time()
    labels = getattr(segmentation, cue)(ctx)
    return labels, time.process_time() - c0


def summary(prev: list[np.ndarray], other: list[np.ndarray]) -> dict:
    """ARI distribution over the views whose previous labels have more than one segment (ICL's grey colour
    image has one: every definition gives it one segment)."""
    pairs = [(a, b) for a, b in zip(prev, other, strict=True) if a.max() > 1]
    if not pairs:
        return {"views": 0}
    ari = np.array([adjusted_rand_index(a, b) for a, b in pairs])
    return {
        "ari_per_view": [round(float(x), 4) for x in ari],
        "views": len(pairs), "ari_min": round(float(ari.min()), 4),
        "ari_p10": round(float(np.quantile(ari, 0.1)), 4), "ari_median": round(float(np.median(ari)), 4),
        "identical": round(float(np.mean([np.array_equal(a, b) for a, b in pairs])), 3),
        "segments_ratio_median": round(float(np.median([int(b.max()) / int(a.max()) for a, b in pairs])), 3),
    }


def decision(noise: dict, cand: dict) -> str:
    """PASS when the candidate's median and 10th-percentile ARI reach the noise floor's; n/a without views."""
    if not noise.get("views"):
        return "n/a"
    return "FAIL" if noise_floor_failures(cand["ari_per_view"], noise["ari_per_view"]) else "PASS"


def run_room(room: str, n_views: int, repeats: int, cache: Path, names: list[str]) -> dict:
    passes, _, _ = room_views(room, n_views, 512, cache)
    params = CueParams()
    with previous_definitions():
        prev = {cue: [one_cue(p, params, cue)[0] for p in passes] for cue in CUES}  # kernels loaded first
        prev = {cue: [one_cue(p, params, cue)[0] for p in passes] for cue in CUES}
        noisy = [imperceptibly_perturbed(p, i, NOISE_SHARE) for i, p in enumerate(passes)]
        floor = {cue: summary(prev[cue], [one_cue(p, params, cue)[0] for p in noisy]) for cue in CUES}
    result: dict = {"views": len(passes), "noise_floor": floor, "candidates": {}}
    for name in names:
        make, out = CANDIDATES[name], {}
        for cue in CUES:
            with make():
                one_cue(passes[0], params, cue)  # a variant's kernels compiled outside the timing
                labels = [one_cue(p, params, cue)[0] for p in passes]
            saved, prev_s = [], []
            for _ in range(repeats):
                for p in passes:
                    with previous_definitions():
                        t_prev = one_cue(p, params, cue)[1]
                    with make():
                        t_cand = one_cue(p, params, cue)[1]
                    saved.append(t_prev - t_cand)
                    prev_s.append(t_prev)
            agree = summary(prev[cue], labels)
            out[cue] = {**agree, "decision": decision(floor[cue], agree),
                        "ms_saved_per_view_median": round(1e3 * float(np.median(saved)), 2),
                        "ms_previous_per_view_median": round(1e3 * float(np.median(prev_s)), 2)}
        result["candidates"][name] = out
        print(room, name, json.dumps(out), flush=True)
    print(room, "noise floor", json.dumps(floor), flush=True)
    return result


def decisions(rooms: dict, names: list[str]) -> dict:
    """Per cue and candidate: PASS when it passes in every room with views, and the ms saved per room."""
    out: dict = {}
    for cue in CUES:
        for name in names:
            per_room = {r: res["candidates"][name][cue] for r, res in rooms.items()}
            verdicts = [v["decision"] for v in per_room.values() if v["decision"] != "n/a"]
            out.setdefault(cue, {})[name] = {
                "decision": "FAIL" if "FAIL" in verdicts else "PASS",
                "ms_saved": {r: v["ms_saved_per_view_median"] for r, v in per_room.items()},
            }
    return out


def main() -> int:
    keep_freed_memory()  # the worker's heap settings (services.worker.process.heap): timings as a worker's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rooms", default=",".join(ROOMS))
    ap.add_argument("--candidates", default=",".join(CANDIDATES), help="names from CANDIDATES")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/omnidata-derivations-passes"))
    args = ap.parse_args()
    t0, load_before = time.perf_counter(), os.getloadavg()
    names = args.candidates.split(",")
    rooms = {r: run_room(r, args.views, args.repeats, args.cache, names) for r in args.rooms.split(",")}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    run = {
        "commit": commit, "resolution": 512, "clock": "process CPU seconds, one core",
        "noise": f"one level of each stored encoding on {NOISE_SHARE:.0%} of the pixels (each input its "
                 "own): colour +-1/255 per channel, depth +-1/512 m, camera normal +-2/255 per axis",
        "rule": "PASS: candidate-vs-previous ARI median >= noise-floor median and p10 >= noise-floor p10",
        "shipped": {cue: str(d) for cue, d in segmentation.DEFINITIONS.items()},
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()], "wall_s": round(time.perf_counter() - t0, 1),
        "decisions": decisions(rooms, names), "rooms": rooms,
    }
    print(json.dumps(run["decisions"], indent=1))
    data = (json.loads(RESULTS.read_text()) if RESULTS.exists()
            else {"benchmark": "bench/cues/segment_stability.py"})
    data["benchmark"] = "bench/cues/segment_stability.py"
    if "after" in data:
        data["before"] = data["after"]
    data["after"] = run
    RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
