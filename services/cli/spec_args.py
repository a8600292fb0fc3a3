"""Command-line SPACE arguments and JobSpec flags, shared by `omnidata plan`, `generate` and `submit`.

`--spec FILE` (YAML or JSON) gives the JobSpec; `--cues`, `--points`, `--min-views`, `--resolution`, `--seed`,
`--name` and the frame flags (services/cli/frame_args.py) override its fields. Errors are CliError naming the
field and the flag that set it.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import yaml
from pydantic import ValidationError

from services.cli import CliError
from services.cli.frame_args import add_frame_arguments
from services.core.domain.jobspec import JobSpec
from services.core.domain.keys import space_name
from services.core.ingest.datasets import expand_roots
from services.core.ingest.errors import SpaceError
from services.core.ingest.registry import Source, source_checksum

# argparse dest -> (JobSpec field path, flag shown in errors)
SPEC_FLAGS: dict[str, tuple[tuple[str, ...], str]] = {
    "cues": (("cues",), "--cues"),
    "points": (("points", "count"), "--points"),
    "min_views": (("points", "min_views"), "--min-views"),
    "resolution": (("views", "resolution"), "--resolution"),
    "seed": (("seed",), "--seed"),
    "name": (("name",), "--name"),
    "up_axis": (("up_axis",), "--up-axis"),
    "up": (("up",), "--up"),
    "unit_scale": (("unit_scale",), "--unit-scale"),
    "source_to_world": (("source_to_world",), "--source-to-world"),
    "accept_up_guess": (("accept_up_guess",), "--accept-up-guess"),
}


def _cue_list(text: str) -> list[str]:
    return [c.strip() for c in text.split(",") if c.strip()]


def add_spec_arguments(parser: argparse.ArgumentParser) -> None:
    """--spec (optional: the JobSpec defaults without it) and the flags that override its fields."""
    parser.add_argument("--spec", metavar="job.yaml",
                        help="JobSpec as YAML or JSON; the options below override it")
    parser.add_argument(
        "--cues", type=_cue_list, metavar="a,b,...", help="cues to produce (default: all the spaces support)"
    )
    parser.add_argument("--points", type=int, metavar="N", help="points of interest per space (points.count)")
    parser.add_argument("--min-views", type=int, metavar="K", help="views a point needs (points.min_views)")
    parser.add_argument("--resolution", type=int, metavar="R", help="square image size in pixels")
    parser.add_argument(
        "--seed", type=int, metavar="S", help="random seed (same seed, same inputs: same outputs)"
    )
    parser.add_argument("--name", metavar="COMPONENT", help="component name in the output layout (spec name)")
    add_frame_arguments(parser)


def read_spec_file(raw: str | Path) -> dict[str, object]:
    """The mapping of JobSpec fields in a YAML or JSON file (JSON is YAML); CliError naming the problem."""
    path = Path(raw)
    if not path.is_file():
        raise CliError(f"--spec {raw}: no such file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise CliError(f"--spec {raw}: cannot read it ({e.strerror or e})") from None
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise CliError(f"--spec {raw}: not valid YAML/JSON ({e})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise CliError(f"--spec {raw}: expected a mapping of JobSpec fields, got {type(data).__name__}")
    return data


def build_spec(args: argparse.Namespace) -> JobSpec:
    """The JobSpec from --spec and the flags given; CliError naming the field (and the flag)."""
    data = read_spec_file(args.spec) if getattr(args, "spec", None) else {}
    flags: dict[str, str] = {}
    for dest, (path, flag) in SPEC_FLAGS.items():
        value = getattr(args, dest, None)
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
            loc = ".".join(str(x) for x in err.get("loc", ()) if x != "__root__")
            msg = str(err.get("msg", "")).removeprefix("Value error, ")
            where = f"{loc} ({flags[loc]})" if loc in flags else loc
            msgs.append(f"{where}: {msg}" if where else msg)
        raise CliError("invalid job spec: " + "; ".join(msgs)) from None


def distinct_space_names(paths: list[Path]) -> list[str]:
    """The output-layout name of each SPACE (core.keys.space_name); CliError when two would share one."""
    names = [space_name(p) for p in paths]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CliError(f"two spaces would share the name {dup[0]!r} in the output layout; rename one")
    return names


def check_sources(paths: Sequence[str]) -> list[Source]:
    """Each SPACE exists and has a distinct name; a dataset root (e.g. ScanNet/scans/) becomes one space per
    scene, named by its scene id, its unusable scenes marked refused; anything else must hold exactly one
    mesh. CliError otherwise."""
    for raw in paths:
        if not Path(raw).expanduser().exists():
            raise CliError(f"{raw}: no such file or folder")
    scenes = expand_roots([Path(raw).expanduser() for raw in paths])
    roots = {Path(raw).expanduser() for raw in paths}
    names = distinct_space_names([s.folder for s in scenes])
    sources = []
    for scene, name in zip(scenes, names, strict=True):
        from_root = scene.folder not in roots
        if scene.refused is not None:
            sources.append(Source(scene.folder.resolve(), name, "", from_root=True, refused=scene.refused))
            continue
        try:
            sources.append(Source(scene.folder.resolve(), name, source_checksum(scene.folder.resolve()),
                                  from_root=from_root))
        except SpaceError as e:
            if not from_root:
                raise CliError(str(e)) from None
            sources.append(Source(scene.folder.resolve(), name, "", from_root=True, refused=str(e)))
    return sources


def usable(sources: list[Source]) -> list[Source]:
    """The sources that are not refused; CliError when none is left."""
    ok = [s for s in sources if s.refused is None]
    if not ok:
        raise CliError("every scene was refused:\n" + refused_summary(sources))
    return ok


def refused_summary(sources: list[Source]) -> str:
    """One line per refused scene of a dataset root ('' when none)."""
    refused = [s for s in sources if s.refused is not None]
    return "\n".join(f"  {s.name}: {s.refused}" for s in refused)
