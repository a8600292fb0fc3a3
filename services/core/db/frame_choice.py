"""A space's up direction when detection could not decide: held as "needs frame" until someone picks one.

A space registered with an ambiguous up (`validation["up"]["ambiguous"]`) keeps both candidates in its
validation record. A job over it is refused (ValueError naming both candidates and the `up` that picks
one) unless its spec sets the frame (`up`, `up_axis`, `source_to_world`), accepts the guess
(`accept_up_guess`), or the space carries a chosen up (`validation["up_choice"]`, stored by
`choose_up`). Ambiguous units (`validation["units"]["ambiguous"]`) are held the same way until the spec
sets `unit_scale`, accepts the guess, or a pick stores one. The planner loads such a space with the chosen
up and units (`space_frame_for`); its workers load it with the source_to_world the planner recorded.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from services.core.db.models import Space
from services.core.domain.frame_words import ambiguity_line, units_ambiguity_line
from services.core.domain.jobspec import JobSpec, SpaceFrame


def chosen_up(space: Space) -> list[float] | None:
    """The up a person picked for this space (source coordinates), or None."""
    choice = (space.validation or {}).get("up_choice")
    return None if not choice else [float(x) for x in choice["up"]]


def chosen_unit_scale(space: Space) -> float | None:
    """The metres per unit stored with a person's pick (up and/or units), or None."""
    choice = (space.validation or {}).get("up_choice")
    return None if not choice or choice.get("unit_scale") is None else float(choice["unit_scale"])


def _up_ambiguous(space: Space) -> bool:
    up = (space.validation or {}).get("up") or {}
    return bool(up.get("ambiguous")) and chosen_up(space) is None


def _units_ambiguous(space: Space) -> bool:
    units = (space.validation or {}).get("units") or {}
    return bool(units.get("ambiguous")) and chosen_up(space) is None


def needs_frame(space: Space) -> bool:
    """True when detection could not decide the space's up or units and nobody has picked them yet."""
    return _up_ambiguous(space) or _units_ambiguous(space)


def _spec_sets_frame(spec: JobSpec) -> bool:
    return spec.up is not None or spec.up_axis != "auto" or spec.source_to_world is not None


def _spec_sets_units(spec: JobSpec) -> bool:
    return spec.unit_scale != "auto" or spec.source_to_world is not None


def space_frame_for(spec: JobSpec, space: Space) -> SpaceFrame:
    """`load_space` keyword arguments for this space under this spec: the spec's frame, else the chosen
    one."""
    frame = spec.space_frame()
    choice = chosen_up(space)
    if choice is not None and not _spec_sets_frame(spec):
        frame["up"] = choice
    scale = chosen_unit_scale(space)
    if scale is not None and not _spec_sets_units(spec):
        frame["unit_scale"] = scale
    return frame


def check_frame_decided(spec: JobSpec, space: Space) -> None:
    """ValueError (one line naming the candidates) when a job would plan this space on a guess."""
    if spec.accept_up_guess or spec.source_to_world is not None:
        return
    if _up_ambiguous(space) and not _spec_sets_frame(spec):
        up = (space.validation or {}).get("up") or {}
        candidates = up.get("candidates") or []
        if len(candidates) < 2:
            raise ValueError(
                f"space {space.name!r}: up is ambiguous; pick one (PUT /spaces/{space.id}/up) or set up"
            )
        raise ValueError(ambiguity_line(f"space {space.name!r}", candidates, up.get("margin"))
                         + f"; or pick one for the space: PUT /spaces/{space.id}/up")
    # units detected under the detected up: a spec that sets its own up has them chosen again when planned
    if _units_ambiguous(space) and not _spec_sets_units(spec) and not _spec_sets_frame(spec):
        units = (space.validation or {}).get("units") or {}
        raise ValueError(units_ambiguity_line(f"space {space.name!r}", units.get("candidates") or [])
                         + f"; or pick them for the space: PUT /spaces/{space.id}/up with unit_scale")


def record_choice(space: Space, up: np.ndarray, source_to_world: np.ndarray, bounds: np.ndarray,
                  unit_scale: float, by: str) -> None:
    """Store a picked up with the space (its validation record and frame columns); the caller commits."""
    validation = dict(space.validation or {})
    validation["up_choice"] = {"up": [float(x) for x in up], "unit_scale": float(unit_scale), "by": by,
                               "at": datetime.now(UTC).isoformat(timespec="seconds")}
    space.validation = validation  # a new dict: the JSON column sees the change
    space.up_axis = "vector"
    space.source_to_world = np.asarray(source_to_world, dtype=float).tolist()
    space.bounds = np.asarray(bounds, dtype=float).tolist()
    space.unit_scale = float(unit_scale)
