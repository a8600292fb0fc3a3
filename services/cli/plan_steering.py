"""`omnidata plan` steering options: --report, --compare A.yaml B.yaml and --fit-to TARGET.

--report writes, per space, `report/<space>.json` (floor_z; summary: quantiles q05..q95, mean, n per
distribution; histograms on fixed edges, services.core.domain.steering) and `report/<space>.png` (the
histograms and a top-down view of cameras and points).
--compare plans every SPACE with both specs (the flags override both) and writes `compare/<space>.json` (each
spec's summary and histograms on the same edges, and the two-sample KS statistic between them per
distribution) and `compare/<space>.png` (the histograms overlaid); nothing else is written.
--fit-to fits the spec to a target's distributions (services.scheduler.planning.fit: a scan with its capture,
a capture, a folder of point_info JSONs or a CSV), writes the fitted spec to --out-spec (YAML), prints the KS
statistics before and after, and plans with the fitted spec; its report overlays the target.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

from services.cli import CliError
from services.cli.spec_args import build_spec
from services.cli.steering_sheet import draw_sheet
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import PlanError, SpacePlan
from services.core.domain.steering import Histogram, histograms, ks_statistic, summary, view_distributions
from services.core.ingest.errors import SpaceError
from services.core.ingest.loading import LoadedSpace
from services.core.ingest.targets import TargetError
from services.scheduler.plan_space import load_for_job, plan_space, scan_floor_z
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.fit import FITTED, fit_spec, load_target, target_enclosed

FEW_VIEWS = 500


def add_steering_arguments(parser: argparse.ArgumentParser) -> None:
    """--report, --compare, --fit-to and --out-spec."""
    parser.add_argument("--report", action="store_true",
                        help="write each space's view distributions (report/<space>.json and .png)")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A.yaml", "B.yaml"),
                        help="plan with two specs and write their distributions overlaid (compare/<space>.*)")
    parser.add_argument("--fit-to", type=Path, metavar="TARGET",
                        help="fit the spec to a target's camera distributions: a scan with its capture, a "
                             "capture, a folder of point_info JSONs or a CSV (fov_deg, pitch_deg, ...)")
    parser.add_argument("--out-spec", type=Path, metavar="fitted.yaml",
                        help="where --fit-to writes the fitted spec (default: DIR/fitted.yaml)")


def _top_down(plan: SpacePlan) -> tuple[np.ndarray, np.ndarray]:
    cams = np.array([c.position[:2] for c in plan.cameras]).reshape(-1, 2)
    pts = np.array([p.position[:2] for p in plan.points]).reshape(-1, 2)
    return cams, pts


def distributions_record(values: dict[str, np.ndarray], floor_z: float | None) -> dict[str, object]:
    """floor_z, the summary and the histograms of a set of distributions (JSON-ready)."""
    return {"floor_z": floor_z, "summary": summary(values), "histograms": histograms(values)}


def _ks(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    return {n: round(ks_statistic(a[n], b[n]), 4) for n in a if n in b and len(a[n]) and len(b[n])}


def write_report(out: Path, name: str, space: LoadedSpace, plan: SpacePlan,
                 target: dict[str, np.ndarray] | None = None) -> None:
    """report/<name>.json and .png of a plan (with the target's distributions beside it when fitted)."""
    floor = scan_floor_z(space)
    values = view_distributions(plan, floor_z=floor)
    record = {"space": name, **distributions_record(values, floor)}
    series: dict[str, dict[str, Histogram]] = {"plan": histograms(values)}
    if target is not None:
        record["target"] = distributions_record(target, None)
        record["ks_to_target"] = _ks(target, values)
        series = {"target": histograms(target), **series}
    (out / "report").mkdir(parents=True, exist_ok=True)
    (out / "report" / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
    draw_sheet(out / "report" / f"{name}.png", f"{name}: {len(plan.views)} views", series,
               {"plan": _top_down(plan)})


def fit_to(args: argparse.Namespace, spec: JobSpec, given: str, name: str, space: LoadedSpace
           ) -> tuple[JobSpec, dict[str, np.ndarray]]:
    """The spec fitted to --fit-to on this space (written to --out-spec), and the target's distributions."""
    if spec.cameras.mode != "generate":
        raise CliError(f"--fit-to fits generated cameras (cameras.mode generate), not {spec.cameras.mode!r}")
    try:
        target = load_target(args.fit_to, (Path(given), space))
    except (TargetError, SpaceError, OSError) as e:
        raise CliError(f"--fit-to {args.fit_to}: {e}") from None
    floor = scan_floor_z(space)
    if floor is None:
        raise CliError(f"{given}: no floor found, so camera heights cannot be fitted")
    enclosed = target_enclosed(space, target.centres) if target.centres is not None else True
    try:
        before = view_distributions(make_plan(space, spec, space_rng(spec.seed, name), name), floor_z=floor)
        fit = fit_spec(space, spec, target.values, floor_z=floor, enclosed=enclosed, space_name=name)
    except PlanError as e:
        raise CliError(f"{given}: {e}") from None
    ks_before = _ks(target.values, before)
    for n in FITTED:
        if n in fit.ks:
            print(f"{name}: {n} KS to the target {ks_before.get(n, 1.0):.3f} -> {fit.ks[n]:.3f}")
    if len(fit.values["pitch_deg"]) < FEW_VIEWS:  # the KS of a small sample is mostly its noise
        print(f"omnidata plan: note: the fitted plan has {len(fit.values['pitch_deg'])} views; to match more "
              "closely, plan more (lower cameras.min_spacing_m, raise points.count)", file=sys.stderr)
    out_spec: Path = args.out_spec or args.out / "fitted.yaml"
    out_spec.parent.mkdir(parents=True, exist_ok=True)
    out_spec.write_text(yaml.safe_dump(fit.spec.model_dump(mode="json"), sort_keys=False))
    print(f"wrote the fitted spec {out_spec} ({target.source}, {len(next(iter(target.values.values())))} "
          "target views)")
    return fit.spec, target.values


def compare_or_check(args: argparse.Namespace, given_spaces: list[str], names: list[str]) -> int | None:
    """--compare runs on its own: its exit status; None otherwise, once --fit-to has exactly one SPACE."""
    if args.compare:
        specs = [build_spec(argparse.Namespace(**{**vars(args), "spec": str(p)})) for p in args.compare]
        return run_compare(args, given_spaces, names, specs)
    if args.fit_to and len(given_spaces) != 1:
        raise CliError("--fit-to fits one SPACE at a time")
    return None


def run_compare(args: argparse.Namespace, given_spaces: list[str], names: list[str],
                specs: list[JobSpec]) -> int:
    """Plan every space with both specs and write compare/<space>.json and .png."""
    out: Path = args.out
    labels = [p.stem for p in args.compare]
    if labels[0] == labels[1]:
        labels = ["A", "B"]
    for given, name in zip(given_spaces, names, strict=True):
        values: dict[str, dict[str, np.ndarray]] = {}
        tops = {}
        floor = None
        for label, spec in zip(labels, specs, strict=True):
            try:
                space = load_for_job(given, spec)
                plan = plan_space(space, spec, name)
            except (SpaceError, PlanError) as e:
                raise CliError(f"{given}: {e}") from None
            floor = scan_floor_z(space)
            values[label] = view_distributions(plan, floor_z=floor)
            tops[label] = _top_down(plan)
        record = {"space": name, "specs": dict(zip(labels, [str(p) for p in args.compare], strict=True)),
                  **{label: distributions_record(v, floor) for label, v in values.items()},
                  "ks": _ks(values[labels[0]], values[labels[1]])}
        (out / "compare").mkdir(parents=True, exist_ok=True)
        (out / "compare" / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
        draw_sheet(out / "compare" / f"{name}.png", f"{name}: {labels[0]} vs {labels[1]}",
                   {label: histograms(v) for label, v in values.items()}, tops)
        ks = _ks(values[labels[0]], values[labels[1]])
        print(f"{name}: KS {labels[0]} vs {labels[1]}: " + ", ".join(f"{k} {v:.3f}" for k, v in ks.items()))
    print(f"wrote {out / 'compare'}")
    return 0
