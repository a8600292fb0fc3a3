"""Command-line flags that set a space's frame, shared by `omnidata plan`, `generate` and `submit`.

`--up-axis NAME`, `--up X,Y,Z` (source coordinates), `--unit-scale M|auto` and `--source-to-world FILE`
(a 4x4 matrix as JSON, a JSON object with a `source_to_world` key such as a job.json space record, or
4 lines of 4 numbers) map to the JobSpec fields of the same names, which validate them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.core.domain.frame_values import UP_AXES


def add_frame_arguments(parser: argparse.ArgumentParser) -> None:
    """--up-axis, --up, --unit-scale, --source-to-world: the space frame flags of plan, generate and
    submit."""
    parser.add_argument("--up-axis", choices=UP_AXES,
                        help="source axis pointing up (default: auto); write negative axes as --up-axis=-y")
    parser.add_argument("--up", type=_vector, metavar="X,Y,Z", help="up direction in source coordinates")
    parser.add_argument("--unit-scale", type=_unit_scale, metavar="M",
                        help="metres per source unit, or auto (default: from the storey height of rooms)")
    parser.add_argument(
        "--source-to-world", type=_matrix_file, metavar="FILE",
        help="4x4 source -> world matrix (JSON, or 4 lines of 4 numbers): rotation, "
        "uniform scale, translation; overrides detection",
    )
    parser.add_argument(
        "--accept-up-guess", action="store_true", default=None,
        help="plan on the better up candidate (and unit) even when detection cannot "
        "tell two apart (default: stop, naming them and the --up / --unit-scale that picks one)",
    )


def _vector(text: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    return v


def _unit_scale(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number of metres per unit or auto, got {text!r}"
        ) from None


def _matrix_file(text: str) -> list[list[float]]:
    path = Path(text)
    try:
        raw = path.read_text()
    except OSError as e:
        raise argparse.ArgumentTypeError(f"cannot read {text} ({e.strerror or e})") from None
    try:
        data = json.loads(raw)
    except json.JSONDecodeError:
        try:
            data = [
                [float(x) for x in line.replace(",", " ").split()]
                for line in raw.splitlines()
                if line.strip()
            ]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text}: expected a 4x4 matrix as JSON or 4 lines of 4 numbers"
            ) from None
    if isinstance(data, dict):
        data = data.get("source_to_world", data)
    if not (
        isinstance(data, list) and len(data) == 4 and all(isinstance(r, list) and len(r) == 4 for r in data)
    ):
        raise argparse.ArgumentTypeError(f"{text}: expected a 4x4 matrix as JSON or 4 lines of 4 numbers")
    return data
