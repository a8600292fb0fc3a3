"""The steering distributions of a plan: each value against its geometric definition, and the histograms."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.domain.camera import look_at
from services.core.domain.plan import CameraPose, PlannedView, PointOfInterest, SpacePlan
from services.core.domain.steering import (
    DEFAULT_BINS,
    DISTRIBUTIONS,
    histograms,
    ks_statistic,
    summary,
    view_distributions,
)


def _plan() -> SpacePlan:
    """Cameras at 1.5 m and 0.5 m; point 0 on the floor (seen by both), point 1 on a wall at 1.5 m."""
    cams = [np.array([0.0, 0.0, 1.5]), np.array([2.0, 0.0, 0.5])]
    points = [(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])),
              (np.array([0.0, 3.0, 1.5]), np.array([0.0, -1.0, 0.0]))]
    views = []
    for p, c, v, roll in [(0, 0, 0, 0.1), (0, 1, 1, -0.05), (1, 0, 0, 0.0)]:
        W = look_at(cams[c], points[p][0], roll)
        d = cams[c] - points[p][0]
        obl = float(np.arccos(points[p][1] @ d / np.linalg.norm(d)))
        views.append(PlannedView(p, v, c, W, np.radians(60 + 10 * c), roll, 256, obl, True))
    return SpacePlan(
        "room", tuple(CameraPose(i, c, "generated", f"c{i}") for i, c in enumerate(cams)),
        tuple(PointOfInterest(i, pos, n, f"p{i}", (0, 1)) for i, (pos, n) in enumerate(points)), tuple(views),
    )


def test_view_distributions_match_their_definitions() -> None:
    values = view_distributions(_plan())
    assert tuple(values) == DISTRIBUTIONS
    np.testing.assert_allclose(values["fov_deg"], [60.0, 70.0, 60.0])
    # camera 0 at 1.5 m looks 1 m away at the floor: 56.3 degrees down; the wall point is level
    np.testing.assert_allclose(values["pitch_deg"], [-np.degrees(np.arctan2(1.5, 1.0)),
                                                     -np.degrees(np.arctan2(0.5, 1.0)), 0.0], atol=1e-9)
    np.testing.assert_allclose(values["roll_deg"], np.degrees([0.1, -0.05, 0.0]), atol=1e-9)
    # no floor given: the lowest point of the plan (z = 0)
    np.testing.assert_allclose(values["height_m"], [1.5, 0.5, 1.5])
    np.testing.assert_allclose(values["distance_m"], [np.hypot(1.0, 1.5), np.hypot(1.0, 0.5), 3.0])
    np.testing.assert_allclose(values["obliqueness_deg"], [np.degrees(np.arctan2(1.0, 1.5)),
                                                           np.degrees(np.arctan2(1.0, 0.5)), 0.0], atol=1e-9)
    np.testing.assert_array_equal(values["views_per_point"], [2, 1])
    np.testing.assert_allclose(view_distributions(_plan(), floor_z=-0.25)["height_m"], [1.75, 0.75, 1.75])


def test_summary_and_histograms_on_fixed_edges() -> None:
    values = {"pitch_deg": np.array([-100.0, -5.0, 0.0, 5.0, np.nan]), "height_m": np.zeros(0)}
    s = summary(values)
    assert s["pitch_deg"]["n"] == 4 and s["pitch_deg"]["q50"] == pytest.approx(-2.5)
    assert s["pitch_deg"]["mean"] == pytest.approx(-25.0)
    assert s["height_m"] == {"n": 0.0}
    h = histograms(values)
    assert h["pitch_deg"]["edges"] == DEFAULT_BINS["pitch_deg"].tolist()
    counts = h["pitch_deg"]["counts"]
    assert sum(counts) == 4 and counts[0] == 1  # -100 beyond the edges counts in the first bin
    other = histograms({"pitch_deg": np.array([10.0])})
    assert other["pitch_deg"]["edges"] == h["pitch_deg"]["edges"]
    with pytest.raises(KeyError, match="no bin edges"):
        histograms({"unknown": np.zeros(1)})


def test_ks_statistic() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=2000), rng.normal(size=2000)
    assert ks_statistic(a, b) < 0.05
    assert ks_statistic(a, b + 1.0) > 0.3
    assert ks_statistic(np.array([0.0, 1.0]), np.array([2.0, 3.0])) == 1.0
    assert ks_statistic(np.array([0.0, 1.0]), np.array([1.0, 0.0])) == 0.0
