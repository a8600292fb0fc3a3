"""The JobSpec knobs that shape a distribution by its quantiles (a spec fitted to a capture sets them).

A distribution given as quantiles q_0 <= ... <= q_(k-1) at the equally spaced levels 0, 1/(k-1), ..., 1 is the
piecewise-linear inverse CDF through them: a value is drawn as interp(u, levels, q), u ~ U[0, 1). Every knob
defaults to None, which keeps the sampling (and the random draws) of the parametric knobs beside it.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

FOV_LIMITS_DEG = (1.0, 179.0)
MAX_QUANTILES = 101


def _list_as_tuple(v: object) -> object:
    return tuple(v) if isinstance(v, list) else v


Quantiles = Annotated[tuple[float, ...], BeforeValidator(_list_as_tuple)]


def check_quantiles(name: str, q: tuple[float, ...] | None, lo: float, hi: float) -> None:
    """ValueError naming the field unless q has 2..MAX_QUANTILES non-decreasing values in [lo, hi]."""
    if q is None:
        return
    if not 2 <= len(q) <= MAX_QUANTILES:
        raise ValueError(f"{name} needs 2 to {MAX_QUANTILES} quantiles, got {len(q)}")
    if not all(math.isfinite(x) for x in q):
        raise ValueError(f"{name} must be finite numbers")
    if any(b < a for a, b in zip(q, q[1:], strict=False)):
        raise ValueError(f"{name} must be non-decreasing (quantiles at equally spaced levels 0..1)")
    if q[0] < lo or q[-1] > hi:
        raise ValueError(f"{name} must lie in [{lo}, {hi}], got [{q[0]}, {q[-1]}]")


class CameraSteering(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    height_quantiles_m: Quantiles | None = Field(
        None, description="generated cameras: height above the floor drawn from these quantiles (equally "
        "spaced levels 0..1, piecewise-linear inverse CDF) instead of uniform in [height_min_m, "
        "height_max_m]; None: uniform (the default)",
    )
    floors: Literal["all", "lowest"] = Field(
        "all", description="generated cameras stand on every detected floor (each storey), or on the lowest "
        "only (partial scans whose counters or tables are large enough to pass for a floor)",
    )
    enclosed: bool = Field(
        True, description="generated cameras must be enclosed by the mesh (ray parity); false for partial "
        "scans (one side of a room) whose capture stood where the mesh does not enclose",
    )

    @model_validator(mode="after")
    def _check_steering(self) -> CameraSteering:
        check_quantiles("height_quantiles_m", self.height_quantiles_m, 0.0, 100.0)
        return self


class ViewSteering(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    fov_quantiles_deg: Quantiles | None = Field(
        None, description="field of view drawn from these quantiles (equally spaced levels 0..1, "
        "piecewise-linear inverse CDF, within [1, 179] degrees) instead of the truncated normal of "
        "fov_mean/std/min/max_deg; None: the truncated normal (the default)",
    )
    roll_quantiles_deg: Quantiles | None = Field(
        None, description="roll about the optical axis (relative to gravity) drawn from these quantiles "
        "(equally spaced levels 0..1, within [-180, 180] degrees) instead of uniform in [-roll_max_deg, "
        "roll_max_deg]; None: uniform (the default)",
    )
    pitch_quantiles_deg: Quantiles | None = Field(
        None, description="wide_baseline: the views' pitch (optical axis above the horizontal, + up) follows "
        "these quantiles (equally spaced levels 0..1). A fixated view's pitch is set by its camera and "
        "point, so camera-point pairs are thinned: each is kept with a probability proportional to the "
        "target's share of its quantile bin over the pairs' share; points left with fewer than "
        "points.min_views views are dropped. None: every pair (the default)",
    )

    @model_validator(mode="after")
    def _check_steering(self) -> ViewSteering:
        check_quantiles("fov_quantiles_deg", self.fov_quantiles_deg, *FOV_LIMITS_DEG)
        check_quantiles("roll_quantiles_deg", self.roll_quantiles_deg, -180.0, 180.0)
        check_quantiles("pitch_quantiles_deg", self.pitch_quantiles_deg, -90.0, 90.0)
        if self.pitch_quantiles_deg is not None and getattr(self, "mode", None) == "trajectory":
            raise ValueError("pitch_quantiles_deg steers wide_baseline views; a trajectory's pitch follows "
                             "its path")
        return self
