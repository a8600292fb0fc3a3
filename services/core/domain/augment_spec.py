"""Knobs of the 3D augmentation cues (rgb_refocus, rgb_fog, rgb_motion_blur, rgb_flash): each a distribution
that one value per view is drawn from, with the view's own generator (seeded by the job's seed through the
plan), and recorded in that view's `augment_params` file.

A distribution is written as a number (that value, every view) or `{dist: uniform | log_uniform, low, high}`.
Units: metres, 1/m, the f-number, millimetres of sensor width, pixels; [0, 1] for light levels.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_COC_PX = 64.0  # the disc blur of refocus grows with its radius: bounded like the other blurs


class Dist(BaseModel):
    """A distribution of one augmentation parameter."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    dist: Literal["constant", "uniform", "log_uniform"] = "uniform"
    low: float
    high: float

    @model_validator(mode="before")
    @classmethod
    def _number_is_constant(cls, v: object) -> object:
        if isinstance(v, int | float) and not isinstance(v, bool):
            return {"dist": "constant", "low": float(v), "high": float(v)}
        return v

    @model_validator(mode="after")
    def _ordered(self) -> Dist:
        if not (math.isfinite(self.low) and math.isfinite(self.high)) or self.low > self.high:
            raise ValueError(f"low ({self.low}) must be finite and at most high ({self.high})")
        if self.dist == "log_uniform" and self.low <= 0:
            raise ValueError("a log_uniform distribution needs low > 0")
        return self

    def sample(self, rng: np.random.Generator) -> float:
        """One value (the generator advances by one draw whatever the kind, so the draws stay aligned)."""
        u = float(rng.random())
        if self.dist == "constant" or self.low == self.high:
            return self.low
        if self.dist == "log_uniform":
            return float(math.exp(math.log(self.low) + u * (math.log(self.high) - math.log(self.low))))
        return self.low + u * (self.high - self.low)


def _bounded(name: str, dist: Dist, lo: float, hi: float) -> None:
    if dist.low < lo or dist.high > hi:
        raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}], got [{dist.low:g}, {dist.high:g}]")


def _d(low: float, high: float, dist: Literal["constant", "uniform", "log_uniform"] = "uniform") -> Dist:
    return Dist(dist=dist, low=low, high=high)


class AugmentParams(BaseModel):
    """Distributions of the augmentation parameters (one draw per view and parameter)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    refocus_focus_quantile: Dist = Field(
        _d(0.05, 0.95), description="focus distance = this quantile of the view's depths"
    )
    refocus_f_number: Dist = Field(
        _d(1.4, 8.0, "log_uniform"), description="aperture: focal length / diameter"
    )
    refocus_sensor_width_mm: float = Field(
        36.0, gt=0, le=100, description="sensor width; the focal length follows the fov"
    )
    refocus_max_coc_px: float = Field(
        16.0, gt=0, le=MAX_COC_PX, description="circles of confusion are clipped to this radius"
    )
    fog_beta_per_m: Dist = Field(
        _d(0.05, 0.5, "log_uniform"), description="extinction coefficient: t = exp(-beta d)"
    )
    fog_airlight: Dist = Field(
        _d(0.6, 0.95), description="grey level of the fog (atmospheric light) in [0, 1]"
    )
    motion_x_m: Dist = Field(
        _d(-0.03, 0.03), description="camera translation along its x (right) during the exposure"
    )
    motion_y_m: Dist = Field(_d(-0.03, 0.03), description="camera translation along its y (down)")
    motion_z_m: Dist = Field(
        _d(-0.05, 0.05), description="camera translation along its optical axis (forward)"
    )
    motion_max_samples: int = Field(32, ge=2, le=128, description="poses averaged along the path, at most")
    flash_ambient: Dist = Field(_d(0.1, 0.6), description="share of the scan's own (baked) light kept")
    flash_power_m2: Dist = Field(_d(0.5, 2.0), description="flash gain: colour x power x shading / d^2")

    @model_validator(mode="after")
    def _ranges(self) -> AugmentParams:
        _bounded("refocus_focus_quantile", self.refocus_focus_quantile, 0.0, 1.0)
        _bounded("refocus_f_number", self.refocus_f_number, 0.5, 64.0)
        _bounded("fog_beta_per_m", self.fog_beta_per_m, 0.0, 100.0)
        _bounded("fog_airlight", self.fog_airlight, 0.0, 1.0)
        for axis in ("x", "y", "z"):
            _bounded(f"motion_{axis}_m", getattr(self, f"motion_{axis}_m"), -1.0, 1.0)
        _bounded("flash_ambient", self.flash_ambient, 0.0, 1.0)
        _bounded("flash_power_m2", self.flash_power_m2, 0.0, 100.0)
        return self
