"""Real-corpus figures of bench/ingest/ingest.py (a library it imports): levelling of real reconstructions in
any rotation and unit, refusals, and each evidence term's contribution (ablation).

Corpus: the 7-Scenes redkitchen TSDF mesh at full resolution (../shared/scenes, 192k faces) and the ICL-NUIM
living room, plus the decimated real scans of tests/fixtures/real_scans: six partial kitchen scans meshed
from 15 neighbouring 7-Scenes depth frames each (no ceiling, holes, walls as large as the visible floor) and
the BundleFusion copy room. Each as stored, in random rotations and the 24 axis-aligned ones, cycling through
mm, cm, inches and metres; the scans with capture poses also with their mean camera up (`capture_up`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from services.core.ingest.frame.gravity import estimate_up, floor_evidence, up_candidate_facts
from services.core.ingest.frame.unit_evidence import (
    ScanMeasures,
    UnitError,
    choose_units,
    decide_units,
    measure,
)
from services.core.ingest.frame.up_evidence import WEIGHTS, decide
from tests.fixtures import rotation_corpus as corpus
from tests.fixtures.real_corpus import RealCase, real_cases, real_rooms


def shared_rooms(scenes: Path) -> list[tuple[corpus.Room, np.ndarray | None]]:
    """The full-resolution real meshes of ../shared/scenes with their measured up (and mean camera up)."""
    kitchen = scenes / "7scenes_redkitchen"
    mesh = trimesh.load(kitchen / "mesh_tsdf_2cm_from_1000frames.ply", process=False)
    up = -np.loadtxt(kitchen / "gravity-direction.txt").ravel()
    poses = [np.loadtxt(p) for p in sorted((kitchen / "frames").glob("frame-*.pose.txt"))]
    capture = np.mean([-p[:3, 1] for p in poses], axis=0)
    icl = corpus.icl_room(scenes)
    return [(corpus.Room("7scenes_redkitchen_full", mesh, up / np.linalg.norm(up)), capture), (icl, None)]


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Up error (degrees) over the levelled cases, share refused as ambiguous, share levelled wrong."""
    levelled = [r["error"] for r in rows if not r["refused"]]
    e = np.asarray(levelled) if levelled else np.asarray([np.nan])
    refused = [r for r in rows if r["refused"]]
    return {
        "cases": len(rows),
        "up_error_deg_median": round(float(np.median(e)), 4),
        "up_error_deg_p95": round(float(np.percentile(e, 95)), 4),
        "up_error_deg_max": round(float(np.max(e)), 4),
        "share_within_3deg": round(float(np.mean([not r["refused"] and r["error"] < 3.0 for r in rows])), 4),
        "share_refused_ambiguous": round(len(refused) / max(len(rows), 1), 4),
        "share_levelled_wrong_without_refusal": round(
            float(np.mean([not r["refused"] and r["error"] >= 3.0 for r in rows])), 4
        ),
        "share_refusals_naming_the_right_candidate": (
            round(float(np.mean([r["named_right"] for r in refused])), 4) if refused else None
        ),
        "units_correct": round(float(np.mean([r["units_ok"] for r in rows])), 4),
        **({"units": units_shares(rows, "units")} if rows and "units" in rows[0] else {}),
    }


def units_shares(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """Units right / refused as ambiguous / wrong: over every case (detected up, as the old units_correct),
    over the cases whose up was levelled (what a user gets without any flag), and with the true up given
    (what a user gets after picking up with --up)."""
    def shares(sel: list[dict[str, Any]], k: str) -> dict[str, Any]:
        n = max(len(sel), 1)
        return {
            "cases": len(sel),
            **{s: round(sum(r[k] == s for r in sel) / n, 4) for s in ("right", "refused", "wrong")},
        }

    out = {"detected_up_all": shares(rows, key),
           "detected_up_levelled": shares([r for r in rows if not r["refused"]], key)}
    if key + "_true_up" in rows[0]:
        out["true_up_given"] = shares(rows, key + "_true_up")
    return out


def units_outcome(mesh: trimesh.Trimesh, up: np.ndarray, storey: float | None, scale: float) -> str:
    """right | refused | wrong: the units `load_space` would choose along `up` (auto unit_scale)."""
    try:
        units = choose_units(mesh, up, storey)
    except UnitError:
        return "refused"
    return "refused" if units.ambiguous else "right" if units.scale == scale else "wrong"


def run_case(case: RealCase, posed: bool) -> dict[str, Any]:
    """Estimate up (with the capture's camera up when `posed`) and score it against the truth."""
    est = estimate_up(case.mesh, ".ply", case.capture_up if posed else None)
    units = units_outcome(case.mesh, est.up, est.storey_height, case.scale)
    given = floor_evidence(case.mesh, case.up)
    units_true_up = units_outcome(
        case.mesh, case.up, None if given is None else given.storey_height, case.scale
    )
    named = [est.up] + ([c.up for c in est.decision.shown] if est.decision is not None else [])
    return {"room": case.room, "kind": case.kind, "posed": posed, "refused": est.ambiguous,
            "error": corpus.up_error_deg(est.up, case.up), "units_ok": units == "right", "units": units,
            "units_true_up": units_true_up,
            "named_right": min(corpus.up_error_deg(u, case.up) for u in named) < 5.0,
            "probability": est.confidence}


def calibration(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Stated probability against the observed share of right winners (refused or not), in bins."""
    out = []
    for lo, hi in ((0.5, 0.7), (0.7, 0.9), (0.9, 0.97), (0.97, 1.01)):
        sel = [r for r in rows if r["probability"] is not None and lo <= r["probability"] < hi]
        if sel:
            out.append({"probability": f"{lo:g}-{min(hi, 1.0):g}", "cases": len(sel),
                        "stated_mean": round(float(np.mean([r["probability"] for r in sel])), 4),
                        "observed_right": round(float(np.mean([r["error"] < 3.0 for r in sel])), 4)})
    return out


def ablation(cases: Iterable[tuple[Any, np.ndarray, np.ndarray | None]]) -> dict[str, Any]:
    """Per evidence term: the figures with that term left out (the winner's unrefined direction)."""
    facts = [(up_candidate_facts(mesh), truth, capture) for mesh, truth, capture in cases]
    out: dict[str, Any] = {}
    for left_out in ("none", *WEIGHTS):
        rows = []
        for cands, truth, capture in facts:
            d = decide(cands, capture, disabled=() if left_out == "none" else (left_out,))
            named = [c.up for c in d.shown]
            rows.append(
                {
                    "refused": d.ambiguous, "error": corpus.up_error_deg(d.best.up, truth), "units_ok": True,
                    "named_right": min(corpus.up_error_deg(u, truth) for u in named) < 5.0,
                }
            )
        s = summary(rows)
        out[f"without_{left_out}" if left_out != "none" else "all_terms"] = {
            k: s[k] for k in ("cases", "share_within_3deg", "share_refused_ambiguous",
                              "share_levelled_wrong_without_refusal")}
    return out


UNIT_TERMS = ("storey", "camera", "furniture", "spacing")


def unit_ablation(measured: list[tuple[ScanMeasures, float]]) -> dict[str, Any]:
    """Per unit evidence term: units right / refused / wrong with that term left out (the true up given,
    cases where some unit makes the storey plausible)."""
    out: dict[str, Any] = {}
    for left_out in ("none", *UNIT_TERMS):
        outcomes = []
        for m, scale in measured:
            d = decide_units(m, () if left_out == "none" else (left_out,))
            if d.ranked:
                outcomes.append(
                    "refused" if d.ambiguous else "right" if d.ranked[0].scale == scale else "wrong"
                )
        n = max(len(outcomes), 1)
        out["all_terms" if left_out == "none" else f"without_{left_out}"] = {
            "cases": len(outcomes),
            **{k: round(outcomes.count(k) / n, 4) for k in ("right", "refused", "wrong")},
        }
    return out


def real_figures(scenes: Path, n_random: int, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    """The real-corpus section of bench/results/ingest.json."""
    rooms = shared_rooms(scenes) + real_rooms()
    rows: list[dict[str, Any]] = []
    ablation_cases: list[tuple[Any, np.ndarray, np.ndarray | None]] = []
    posed_cases: list[tuple[Any, np.ndarray, np.ndarray | None]] = []
    unit_cases: list[tuple[ScanMeasures, float]] = []
    for case in real_cases(rooms, n_random, seed=seed):
        rows.append(run_case(case, posed=False))
        unit_cases.append((measure(case.mesh, case.up), case.scale))
        if case.capture_up is not None:
            rows.append(run_case(case, posed=True))
        if case.kind != "axis":
            ablation_cases.append((case.mesh, case.up, None))
            if case.capture_up is not None:
                posed_cases.append((case.mesh, case.up, case.capture_up))
    log(f"real corpus: {len(rows)} cases")

    def pick(**kw: object) -> list[dict[str, Any]]:
        return [r for r in rows if all(r[k] == v for k, v in kw.items())]

    names = [room.name for room, _ in rooms]
    return {
        "corpus": {"rooms": names, "random_rotations_per_room": n_random, "axis_rotations_per_room": 24,
                   "stored_frame_per_room": 1, "scales_m_per_unit": list(corpus.SCALES), "seed": seed,
                   "posed": [room.name for room, cap in rooms if cap is not None]},
        "without_poses": summary(pick(posed=False)),
        "without_poses_as_stored": summary(pick(posed=False, kind="stored")),
        "with_capture_poses": summary(pick(posed=True)),
        "per_room_without_poses": {n: summary(pick(posed=False, room=n)) for n in names},
        "calibration_without_poses": calibration(pick(posed=False)),
        "ablation_without_poses": ablation(ablation_cases),
        "ablation_with_capture_poses": ablation(posed_cases),
        "unit_ablation_true_up": unit_ablation(unit_cases),
    }
