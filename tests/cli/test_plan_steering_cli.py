"""`omnidata plan --report / --compare / --fit-to`: distributions written, overlaid on the same bins, and a
spec fitted to a target; job.json records each space's distributions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from services.cli import main
from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import plan_from_json
from services.core.domain.steering import DEFAULT_BINS, DISTRIBUTIONS, view_distributions
from tests.fixtures import scenes

SPEC = {"cameras": {"max_count": 30, "min_spacing_m": 0.5},
        "points": {"count": 30, "min_views": 2, "max_views": 6}, "views": {"resolution": 64}}


@pytest.fixture
def room(tmp_path: Path) -> Path:
    path = tmp_path / "in" / "room.ply"
    path.parent.mkdir()
    scenes.l_room().export(path)
    return path


def _spec(tmp_path: Path, name: str, data: dict) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_report_and_job_json_distributions(tmp_path: Path, room: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["plan", str(room), "--out", str(out), "--spec", str(_spec(tmp_path, "a.yaml", SPEC)),
                 "--report"]) == 0, capsys.readouterr().err
    report = json.loads((out / "report" / "room.json").read_text())
    job = json.loads((out / "job.json").read_text())
    plan = plan_from_json((out / job["spaces"]["room"]["plan"]).read_text())
    values = view_distributions(plan, floor_z=report["floor_z"])
    assert report["floor_z"] == pytest.approx(0.0, abs=1e-6)  # the L room's floor
    assert report["summary"]["pitch_deg"]["q50"] == pytest.approx(np.quantile(values["pitch_deg"], 0.5))
    assert report["histograms"]["fov_deg"]["edges"] == DEFAULT_BINS["fov_deg"].tolist()
    assert sum(report["histograms"]["fov_deg"]["counts"]) == len(plan.views)
    recorded = job["spaces"]["room"]["distributions"]
    assert sorted(recorded["summary"]) == sorted(DISTRIBUTIONS)
    assert recorded["histograms"]["height_m"] == report["histograms"]["height_m"]
    # job.json's quantiles come from the histograms: within one bin of the exact ones
    assert abs(recorded["summary"]["pitch_deg"]["q50"] - report["summary"]["pitch_deg"]["q50"]) <= 2.5
    assert Image.open(out / "report" / "room.png").size[0] > 500


def test_compare_overlays_two_specs_on_the_same_bins(tmp_path: Path, room: Path, capsys) -> None:
    narrow = {**SPEC, "views": {"resolution": 64, "fov_mean_deg": 45.0, "fov_std_deg": 2.0}}
    out = tmp_path / "out"
    assert main(["plan", str(room), "--out", str(out), "--compare", str(_spec(tmp_path, "wide.yaml", SPEC)),
                 str(_spec(tmp_path, "narrow.yaml", narrow))]) == 0, capsys.readouterr().err
    record = json.loads((out / "compare" / "room.json").read_text())
    edges = [record[label]["histograms"]["fov_deg"]["edges"] for label in ("wide", "narrow")]
    assert edges[0] == edges[1]
    assert record["ks"]["fov_deg"] > 0.8 and record["ks"]["pitch_deg"] < 0.1  # only the fov differs
    assert (out / "compare" / "room.png").is_file() and not (out / "job.json").exists()
    assert "KS wide vs narrow" in capsys.readouterr().out


def test_fit_to_a_csv_target_writes_a_spec_that_matches_it(tmp_path: Path, room: Path, capsys) -> None:
    rng = np.random.default_rng(0)
    csv = tmp_path / "target.csv"
    rows = zip(rng.normal(50, 3, 200), rng.normal(-20, 5, 200), rng.normal(1.2, 0.1, 200), strict=True)
    csv.write_text("fov_deg,pitch_deg,height_m\n" + "".join(f"{a},{b},{c}\n" for a, b, c in rows))
    out, fitted = tmp_path / "out", tmp_path / "fitted.yaml"
    assert main(["plan", str(room), "--out", str(out), "--spec", str(_spec(tmp_path, "a.yaml", SPEC)),
                 "--fit-to", str(csv), "--out-spec", str(fitted)]) == 0, capsys.readouterr().err
    spec = JobSpec.model_validate(yaml.safe_load(fitted.read_text()))
    assert spec.views.fov_quantiles_deg is not None and spec.cameras.height_quantiles_m is not None
    report = json.loads((out / "report" / "room.json").read_text())
    assert max(report["ks_to_target"][n] for n in ("fov_deg", "pitch_deg", "height_m")) < 0.2
    captured = capsys.readouterr()
    assert "pitch_deg KS to the target" in captured.out and "wrote the fitted spec" in captured.out
    assert "to match more closely, plan more" in captured.err  # a small plan: its KS is mostly noise
    job = json.loads((out / "job.json").read_text())
    assert job["spec"]["views"]["pitch_quantiles_deg"] == list(spec.views.pitch_quantiles_deg or ())


def test_fit_to_refuses_what_it_cannot_fit(tmp_path: Path, room: Path, capsys) -> None:
    csv = tmp_path / "target.csv"
    csv.write_text("pitch_deg\n-10\n-20\n")
    spec = _spec(tmp_path, "object.yaml", {"cameras": {"mode": "object"}})
    out = str(tmp_path / "o")
    assert main(["plan", str(room), "--out", out, "--spec", str(spec), "--fit-to", str(csv)]) == 2
    assert "fits generated cameras" in capsys.readouterr().err
    assert main(["plan", str(room), "--out", out, "--fit-to", str(tmp_path / "none.csv")]) == 2
    assert "--fit-to" in capsys.readouterr().err and not (tmp_path / "o").exists()
