"""`omnidata plan`: sample cameras, points and views of spaces and write the plan-stage cues.

Writes, under --out DIR, in the dataset layout `<cue>/<component>/<space>/<file>` (DESIGN.md 5):
point_info and vanishing_points JSON per view, nonfixated JSON per point; plus `plans/<space>.json`
(the full SpacePlan, services.core.plan.plan_to_json) and `job.json` (spec, conventions, code version,
and per space its source_to_world, checksum, counts and shortfall). A space that yields fewer points
than requested is reported (stderr and job.json) but is not an error: exit status 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from services.cli import CliError
from services.core.camera import CONVENTIONS
from services.core.ingest.datasets import expand_roots
from services.core.jobspec import cues_for_space
from services.core.keys import JOB_JSON_KEY, output_key
from services.core.manifest import code_version
from services.core.plan import (
    CLIP_NOTES_IN_SUMMARY,
    PlanError,
    clip_summary,
    encode_json,
    nonfixated,
    plan_to_json,
    point_info,
    vanishing_points,
)
from services.core.spaces import LoadedSpace, SpaceError, load_space
from services.scheduler.planning import make_plan, space_rng
from services.spec_args import add_spec_arguments, build_spec, distinct_space_names

PLAN_CUES = ("point_info", "nonfixated", "vanishing_points")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `omnidata plan`."""
    parser.add_argument("spaces", nargs="+", metavar="SPACE",
                        help="mesh file (.obj/.ply/.glb/.gltf), or a folder or .zip holding one")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    add_spec_arguments(parser)


def _write_json(root: Path, key: str, data: Any) -> None:
    path = root / key
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode_json(data))


def _space_record(given: str, space: LoadedSpace) -> dict[str, Any]:
    return {
        "source": given,
        "mesh_file": space.source_path.name,
        "checksum_sha256": space.checksum,
        "source_to_world": space.source_to_world.tolist(),
        "up_axis": {"source_direction": space.up_source.tolist(), "method": space.up_method},
        **space.frame_record(),
        "bounds_world_m": space.bounds.tolist(),
        "face_count": space.face_count,
        "has_texture": space.has_texture,
        "has_vertex_colors": space.has_vertex_colors,
        "has_semantics": space.has_semantics,
        "warnings": list(space.warnings),
    }


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
    component = spec.name
    spaces: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="omnidata-plan-") as tmp:
        loaded: list[tuple[str, str, LoadedSpace]] = []
        for i, (given, name) in enumerate(zip(given_spaces, names, strict=True)):
            try:
                space = load_space(given, **spec.space_frame(), extract_dir=Path(tmp) / str(i))
                cues_for_space(spec, has_semantics=space.has_semantics)
            except SpaceError as e:
                raise CliError(str(e)) from None
            except ValueError as e:  # cues the space cannot give
                raise CliError(f"{given}: {e}") from None
            loaded.append((given, name, space))
        plans = []
        for given, name, space in loaded:
            try:
                plan = make_plan(space, spec, space_rng(spec.seed, name), name)
            except PlanError as e:
                raise CliError(f"{given}: {e}") from None
            plans.append((given, name, space, plan))

    out.mkdir(parents=True, exist_ok=True)
    for given, name, space, plan in plans:
        for view in plan.views:
            info = point_info(plan, view)
            _write_json(out, output_key("point_info", component, name, view.point_idx, view.v), info)
            _write_json(out, output_key("vanishing_points", component, name, view.point_idx, view.v),
                        vanishing_points(info))
        for point in plan.points:
            _write_json(out, output_key("nonfixated", component, name, point.idx, 0), nonfixated(plan, point.idx))
        plan_key = f"plans/{name}.json"
        (out / "plans").mkdir(parents=True, exist_ok=True)
        (out / plan_key).write_text(plan_to_json(plan))
        record = _space_record(given, space)
        record.update({
            "counts": {"cameras": len(plan.cameras), "points": len(plan.points), "views": len(plan.views)},
            "shortfall": plan.shortfall,
            "valid_fraction": plan.valid_fraction,
            "clips": clip_summary(plan.clip_notes, CLIP_NOTES_IN_SUMMARY),
            "plan": plan_key,
        })
        spaces[name] = record
        print(f"{name}: {len(plan.cameras)} cameras, {len(plan.points)} points, {len(plan.views)} views")
        print(f"{name}: {space.frame_summary()}")
        for note in space.warnings:
            print(f"omnidata plan: warning: {name}: {note}", file=sys.stderr)
        if plan.shortfall:
            print(f"omnidata plan: warning: {name}: {plan.shortfall}", file=sys.stderr)
    job = {
        "format": "omnidata.job/1",
        "command": "plan",
        "code_version": code_version(),
        "spec": spec.model_dump(mode="json"),
        "conventions": dict(CONVENTIONS),
        "component": component,
        "cues_written": list(PLAN_CUES),
        "spaces": spaces,
    }
    (out / JOB_JSON_KEY).write_text(json.dumps(job, indent=2, sort_keys=True) + "\n")
    print(f"wrote {out}")
    return 0
