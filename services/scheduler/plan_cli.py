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
import re
import sys
import tempfile
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from services.cli import CliError
from services.core.camera import CONVENTIONS
from services.core.jobspec import JobSpec, cues_for_space
from services.core.keys import JOB_JSON_KEY, check_name, output_key
from services.core.plan import (
    CLIP_NOTES_IN_SUMMARY,
    PlanError,
    clip_summary,
    nonfixated,
    plan_to_json,
    point_info,
    vanishing_points,
)
from services.core.spaces import LoadedSpace, SpaceError, load_space
from services.frame_args import add_frame_arguments
from services.scheduler.planning import make_plan, space_rng

PLAN_CUES = ("point_info", "nonfixated", "vanishing_points")

# command-line flag -> (JobSpec field path, flag name shown in errors)
_OVERRIDES: dict[str, tuple[tuple[str, ...], str]] = {
    "points": (("points", "count"), "--points"),
    "min_views": (("points", "min_views"), "--min-views"),
    "seed": (("seed",), "--seed"),
    "name": (("name",), "--name"),
    "resolution": (("views", "resolution"), "--resolution"),
    "up_axis": (("up_axis",), "--up-axis"),
    "unit_scale": (("unit_scale",), "--unit-scale"),
    "up": (("up",), "--up"),
    "source_to_world": (("source_to_world",), "--source-to-world"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `omnidata plan`."""
    parser.add_argument("spaces", nargs="+", metavar="SPACE",
                        help="mesh file (.obj/.ply/.glb/.gltf), or a folder or .zip holding one")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    parser.add_argument("--spec", type=Path, metavar="job.yaml", help="JobSpec as YAML or JSON")
    parser.add_argument("--points", type=int, metavar="N", help="points of interest per space")
    parser.add_argument("--min-views", type=int, metavar="K", help="cameras that must see each point")
    parser.add_argument("--seed", type=int, metavar="S", help="random seed (same seed, same plan)")
    parser.add_argument("--name", metavar="COMPONENT", help="component name in the output layout")
    parser.add_argument("--resolution", type=int, metavar="R", help="square image size in pixels")
    add_frame_arguments(parser)


def _read_spec_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except OSError as e:
        raise CliError(f"--spec {path}: cannot read it ({e.strerror or e})") from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as e:
        raise CliError(f"--spec {path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: {e}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise CliError(f"--spec {path}: expected a mapping of JobSpec fields, got {type(data).__name__}")
    return data


def build_spec(args: argparse.Namespace) -> JobSpec:
    """The JobSpec from --spec plus flag overrides; errors name the field (and the flag)."""
    data = _read_spec_file(args.spec) if args.spec else {}
    flags: dict[str, str] = {}
    for attr, (path, flag) in _OVERRIDES.items():
        value = getattr(args, attr, None)
        if value is None:
            continue
        node = data
        for key in path[:-1]:
            sub = node.get(key)
            if sub is None:
                sub = node[key] = {}
            elif not isinstance(sub, dict):
                raise CliError(f"{'.'.join(path[:-1])}: expected a mapping in the spec file")
            node = sub
        node[path[-1]] = value
        flags[".".join(path)] = flag
    try:
        return JobSpec.model_validate(data)
    except ValidationError as e:
        msgs = []
        for err in e.errors():
            loc = ".".join(str(x) for x in err["loc"]) or "spec"
            flag = f" ({flags[loc]})" if loc in flags else ""
            msgs.append(f"{loc}{flag}: {err['msg']}")
        raise CliError("invalid job spec: " + "; ".join(msgs)) from None


def space_name_for(path: str | Path) -> str:
    """Output name of a space: its file or folder stem, unsafe characters replaced by '_'."""
    p = Path(path)
    stem = p.name if p.is_dir() else p.stem
    name = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip("._-")[:128] or "space"
    return check_name("space", name)


def code_version() -> str:
    """Package version, plus the git commit when run from a checkout."""
    try:
        version = metadata.version("omnidata-service")
    except metadata.PackageNotFoundError:
        version = "unknown"
    git = Path(__file__).resolve().parents[2] / ".git"
    try:
        head = (git / "HEAD").read_text().strip()
        if head.startswith("ref: "):
            ref = git / head[5:]
            head = ref.read_text().strip() if ref.is_file() else head
        return f"{version}+g{head[:12]}"
    except OSError:
        return version


def _write_json(root: Path, key: str, data: Any) -> None:
    path = root / key
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, sort_keys=True, allow_nan=False))


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
    names = [space_name_for(s) for s in args.spaces]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise CliError(f"several spaces would be named {', '.join(dupes)}: rename the files or plan them separately")
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out}: exists and is not a folder")
    component = spec.name
    spaces: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="omnidata-plan-") as tmp:
        loaded: list[tuple[str, str, LoadedSpace]] = []
        for i, (given, name) in enumerate(zip(args.spaces, names, strict=True)):
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
