"""`omnidata plan`: sample cameras, points and views of spaces and write the plan-stage cues.

Writes, under --out DIR, in the dataset layout `<cue>/<component>/<space>/<file>`:
point_info and vanishing_points JSON per view, nonfixated JSON per point; plus `plans/<space>.json`
(the full SpacePlan, services.core.domain.plan.plan_to_json) and `job.json` in the one schema
(services.core.domain.job_document, stage "plan"). A space that yields fewer points
than requested is reported (stderr and job.json) but is not an error: exit status 0.
--report, --compare and --fit-to: services/cli/plan_steering.py.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from services.cli import CliError
from services.cli.plan_steering import add_steering_arguments, compare_or_check, fit_to, write_report
from services.cli.spec_args import add_spec_arguments, build_spec, distinct_space_names
from services.core.domain.job_document import JobDocument, SpaceRecord, job_document, job_json_bytes
from services.core.domain.jobspec import JobSpec, cues_for_space
from services.core.domain.keys import JOB_JSON_KEY, output_key
from services.core.domain.plan import PlanError, SpacePlan, plan_to_json
from services.core.domain.plan_cues import encode_json, nonfixated, point_info, vanishing_points
from services.core.ingest.datasets import expand_roots
from services.core.ingest.errors import SpaceError
from services.core.ingest.loading import LoadedSpace
from services.scheduler.plan_space import load_for_job, plan_record, plan_space

PLAN_CUES = ("point_info", "nonfixated", "vanishing_points")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `omnidata plan`."""
    parser.add_argument("spaces", nargs="+", metavar="SPACE",
                        help="mesh file (.obj/.ply/.glb/.gltf), or a folder or .zip holding one")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    add_spec_arguments(parser)
    add_steering_arguments(parser)


def _write_json(root: Path, key: str, data: object) -> None:
    path = root / key
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode_json(data))


def _write_plan_cues(out: Path, component: str, name: str, plan: SpacePlan) -> None:
    """point_info and vanishing_points per view, nonfixated per point, in the dataset layout."""
    for view in plan.views:
        info = point_info(plan, view)
        _write_json(out, output_key("point_info", component, name, view.point_idx, view.v), info)
        _write_json(out, output_key("vanishing_points", component, name, view.point_idx, view.v),
                    vanishing_points(info))
    for point in plan.points:
        _write_json(out, output_key("nonfixated", component, name, point.idx, 0), nonfixated(plan, point.idx))


def _plan_document(spec: JobSpec, component: str, spaces: dict[str, SpaceRecord],
                   plans: list[SpacePlan]) -> JobDocument:
    """job.json of a plan (stage "plan"): no job row, counts of the files written."""
    views = sum(len(plan.views) for plan in plans)
    points = sum(len(plan.points) for plan in plans)
    return job_document(
        stage="plan",
        job={
            "id": None, "name": component, "owner": None, "state": "planned", "error": None,
            "output_root": None, "created_at": None, "started_at": None, "finished_at": None,
            "total_tasks": 0,
        },
        component=component, spec=spec.model_dump(mode="json"), cues=PLAN_CUES, spaces=spaces,
        plan_summary={"shortfall": any(rec["shortfall"] for rec in spaces.values())},
        counts={
            "point_info": {"done": views}, "vanishing_points": {"done": views},
            "nonfixated": {"done": points},
        },
    )


def run(args: argparse.Namespace) -> int:
    """Plan every SPACE and write the plan-stage cues; see the module docstring."""
    spec = build_spec(args)
    scenes = expand_roots([Path(s) for s in args.spaces])  # a dataset root: its scenes, named by scene id
    for scene in scenes:
        if scene.refused is not None:
            print(f"omnidata plan: refused scene {scene.scene_id}: {scene.refused}", file=sys.stderr)
    given_spaces = [str(s.folder) for s in scenes if s.refused is None]
    if not given_spaces:
        raise CliError("every scene was refused")
    names = distinct_space_names([Path(s) for s in given_spaces])
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out}: exists and is not a folder")
    if (rc := compare_or_check(args, given_spaces, names)) is not None:
        return rc
    target = None
    component = spec.name
    spaces: dict[str, SpaceRecord] = {}
    with tempfile.TemporaryDirectory(prefix="omnidata-plan-") as tmp:
        loaded: list[tuple[str, str, LoadedSpace]] = []
        for i, (given, name) in enumerate(zip(given_spaces, names, strict=True)):
            try:
                space = load_for_job(given, spec, extract_dir=Path(tmp) / str(i))
                cues_for_space(spec, has_semantics=space.has_semantics)
            except SpaceError as e:
                raise CliError(str(e)) from None
            except ValueError as e:  # cues the space cannot give
                raise CliError(f"{given}: {e}") from None
            if args.fit_to:
                spec, target = fit_to(args, spec, given, name, space)
            loaded.append((given, name, space))
        plans = []
        for given, name, space in loaded:
            try:
                plan = plan_space(space, spec, name)
            except PlanError as e:
                raise CliError(f"{given}: {e}") from None
            plans.append((given, name, space, plan))

    out.mkdir(parents=True, exist_ok=True)
    for position, (_given, name, space, plan) in enumerate(plans):
        _write_plan_cues(out, component, name, plan)
        plan_key = f"plans/{name}.json"
        (out / "plans").mkdir(parents=True, exist_ok=True)
        (out / plan_key).write_text(plan_to_json(plan))
        spaces[name] = plan_record(space, plan, spec, position=position, cues=list(PLAN_CUES),
                                   plan_key=plan_key)
        print(f"{name}: {len(plan.cameras)} cameras, {len(plan.points)} points, {len(plan.views)} views")
        print(f"{name}: {space.frame_summary()}")
        if args.report or args.fit_to:
            write_report(out, name, space, plan, target)
        for note in space.warnings:
            print(f"omnidata plan: warning: {name}: {note}", file=sys.stderr)
        if plan.shortfall:
            print(f"omnidata plan: warning: {name}: {plan.shortfall}", file=sys.stderr)
    document = _plan_document(spec, component, spaces, [p for *_, p in plans])
    (out / JOB_JSON_KEY).write_bytes(job_json_bytes(document))
    print(f"wrote {out}")
    return 0
