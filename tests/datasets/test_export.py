"""`omnidata export`: WebDataset shards (every view a sample, every cue a member) and the public Omnidata
loader's tree (its path, file name and split CSV rules, re-stated here from its source), from a folder or
S3."""

from __future__ import annotations

import csv
import hashlib
import json
import re
import shutil
import tarfile
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from services.cli import main
from services.core.domain.cues import CATALOG
from services.core.storage import open_store
from services.datasets import OmnidataDataset
from services.datasets.decode import decode_cue
from tests.conftest import S3Server
from tests.datasets.test_dataset import _upload

# WebDataset's rule: a member's key is its path up to the first '.' of the file name, the rest its extension
WDS_MEMBER = re.compile(r"^((?:.*/|)[^./]+)\.([^/]*)$")
# the public Omnidata loader:
# <data_path>/<task>/<component>/<building>/point_<p>_view_<v>_domain_<task>.<ext>, building = the parent
# folder, split CSV id,train,val,test with 1 = member
OMNIDATA_NAME = re.compile(r".*point_(?P<point>\d+)_view_(?P<view>\d+)_domain_(?P<domain>\w+)")


def manifest(job: Path) -> list[dict]:
    return [json.loads(x) for x in (job / "manifest.jsonl").read_text().splitlines()]


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main(["export", *map(str, args), "--no-progress"])
    out = capsys.readouterr()
    return code, out.out, out.err


def read_shards(folder: Path) -> dict[str, dict[str, bytes]]:
    samples: dict[str, dict[str, bytes]] = defaultdict(dict)
    for shard in sorted(folder.glob("*.tar")):
        with tarfile.open(shard) as tar:
            for m in tar.getmembers():
                key, ext = WDS_MEMBER.match(m.name).groups()  # type: ignore[union-attr]
                f = tar.extractfile(m)
                assert f is not None
                samples[key][ext] = f.read()
    return dict(samples)


def test_webdataset_round_trip(small_job: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(
        capsys, small_job, "--format", "webdataset", "--out", tmp_path / "wds", "--shard-size", 3
    )
    assert code == 0, err
    assert "4 samples in 2 shard(s)" in out
    assert sorted(p.name for p in (tmp_path / "wds").iterdir()) == ["shard-000000.tar", "shard-000001.tar"]
    samples = read_shards(tmp_path / "wds")
    lines = manifest(small_job)
    assert sorted(samples) == sorted(f"{e['space']}/point_{e['point']}_view_{e['view']}" for e in lines)
    per_point = {(e["space"], e["point"]): e["outputs"] for e in lines if e["view"] == 0}
    for e in lines:
        sample = samples[f"{e['space']}/point_{e['point']}_view_{e['view']}"]
        outputs = {**per_point[(e["space"], e["point"])], **e["outputs"]}
        assert set(sample) == {f"{cue}.{CATALOG[cue].ext}" for cue in outputs} | {"json"}
        for cue, o in outputs.items():  # every file byte-exact
            assert hashlib.sha256(sample[f"{cue}.{CATALOG[cue].ext}"]).hexdigest() == o["sha256"]
        meta = json.loads(sample["json"])
        assert (meta["space"], meta["point"], meta["view"], meta["component"]) == (
            e["space"], e["point"], e["view"], "tiny",
        )
        assert meta["point_info"]["view_id"] == e["view"] and "K" in meta["point_info"]
    # members decode to what the dataset gives
    item = OmnidataDataset(small_job, ["depth_zbuffer"])[1]
    np.testing.assert_array_equal(
        decode_cue("depth_zbuffer", samples["ycb_banana/point_0_view_1"]["depth_zbuffer.png"]),
        item["depth_zbuffer"],
    )
    # identical input, identical shards; flat keys have no '/'
    code, _, _ = run(
        capsys, small_job, "--format", "webdataset", "--out", tmp_path / "again", "--shard-size", 3
    )
    assert code == 0
    for shard in ("shard-000000.tar", "shard-000001.tar"):
        assert (tmp_path / "wds" / shard).read_bytes() == (tmp_path / "again" / shard).read_bytes()
    code, _, _ = run(capsys, small_job, "--format", "webdataset", "--out", tmp_path / "flat", "--flat-keys",
                     "--cues", "rgb,depth_zbuffer")
    flat = read_shards(tmp_path / "flat")
    assert code == 0 and sorted(flat)[0] == "ycb_banana__point_0_view_0"
    assert set(flat["ycb_banana__point_0_view_0"]) == {"rgb.png", "depth_zbuffer.png", "json"}


def test_omnidata_tree_follows_the_public_loaders_rules(
    small_job: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "omni"
    code, text, err = run(capsys, small_job, "--format", "omnidata", "--out", out, "--component", "replica")
    assert code == 0, err
    assert "split CSV component_datasets/replica/train_val_test_replica.csv" in text
    split_file = out / "component_datasets" / "replica" / "train_val_test_replica.csv"
    rows = list(csv.reader(split_file.read_text().splitlines()))
    assert rows[0] == ["id", "train", "val", "test"]
    in_split = {r[0]: dict(zip(rows[0][1:], r[1:], strict=True)) for r in rows[1:]}
    assert set(in_split) == {"ycb_banana"} and sum(v == "1" for v in in_split["ycb_banana"].values()) == 1
    split = next(s for s, v in in_split["ycb_banana"].items() if v == "1")
    # the loader's make_task_dataset: folders of the split under <task>/<component>, every file parsed
    cues = [c for c in CATALOG if (out / c).is_dir()]
    assert set(cues) == {c for e in manifest(small_job) for c in e["outputs"]}
    bpv: dict[str, set[tuple[str, int, int]]] = {}
    for task in cues:
        folders = [
            p for p in (out / task / "replica").iterdir() if in_split.get(p.name, {}).get(split) == "1"
        ]
        paths = [str(f) for folder in folders for f in folder.iterdir()]
        parsed = set()
        for path in paths:
            m = OMNIDATA_NAME.match(Path(path).name)
            assert m is not None and m["domain"] == task, path
            parsed.add((path.split("/")[-2], int(m["point"]), int(m["view"])))
        bpv[task] = parsed
    everything = {(e["space"], e["point"], e["view"]) for e in manifest(small_job)}
    # every view has every task (their intersection)
    assert all(views == everything for views in bpv.values())
    src = small_job / "depth_zbuffer/tiny/ycb_banana/point_1_view_0_domain_depth_zbuffer.png"
    assert (
        out / "depth_zbuffer/replica/ycb_banana/point_1_view_0_domain_depth_zbuffer.png"
    ).read_bytes() == src.read_bytes()
    assert json.loads((out / "job.json").read_text())["job"]["name"] == "tiny"


def test_export_from_s3(
    small_job: Path, s3_server: S3Server, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    settings = s3_server.settings(prefix="exports/jobs/7")
    store = open_store(settings.storage_url, settings)
    _upload(small_job, store)
    for k, v in s3_server.env.items():
        monkeypatch.setenv(k, v)
    code, out, err = run(
        capsys, settings.storage_url, "--format", "webdataset", "--out", tmp_path / "wds", "--verify"
    )
    assert code == 0, err
    assert len(read_shards(tmp_path / "wds")) == 4
    # a service job by id: its root jobs/<id> in the service's store
    monkeypatch.setenv("OMNIDATA_STORAGE_URL", f"s3://{s3_server.bucket}/exports")
    code, out, err = run(
        capsys, "job:7", "--format", "omnidata", "--out", tmp_path / "omni", "--component", "replica"
    )
    assert code == 0, err
    assert (tmp_path / "omni/rgb/replica/ycb_banana/point_1_view_1_domain_rgb.png").read_bytes() == (
        small_job / "rgb/tiny/ycb_banana/point_1_view_1_domain_rgb.png").read_bytes()
    code, out, err = run(capsys, "8", "--format", "omnidata", "--out", tmp_path / "none")
    assert code == 2 and "manifest" in err and not (tmp_path / "none").exists()
    store.delete_prefix("")


def test_bad_exports_are_refused_and_leave_nothing(
    small_job: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "x").write_text("mine")
    cases = [
        ((small_job, "--format", "webdataset", "--out", taken), "exists and is not an empty folder"),
        (
            (small_job, "--format", "webdataset", "--out", tmp_path / "a", "--cues", "rgb,bogus"),
            "unknown cue",
        ),
        (
            (small_job, "--format", "webdataset", "--out", tmp_path / "b", "--cues", "segment_semantic"),
            "not in this dataset",
        ),
        ((small_job, "--format", "webdataset", "--out", tmp_path / "c", "--shard-size", 0), "--shard-size"),
        (
            (
                small_job, "--format", "omnidata", "--out", tmp_path / "d", "--component", "replica",
                "--split-ratios", "0.5,0.6,0",
            ),
            "--split-ratios",
        ),
        (
            (small_job, "--format", "omnidata", "--out", tmp_path / "e", "--component", "../up"),
            "not a valid name",
        ),
        ((tmp_path / "missing", "--format", "omnidata", "--out", tmp_path / "f"), "is not a folder"),
        # a component no loader class reads: named, and the known ones listed (the job's name 'tiny' too)
        (
            (small_job, "--format", "omnidata", "--out", tmp_path / "h", "--component", "gso"),
            "known: taskonomy",
        ),
        (
            (small_job, "--format", "omnidata", "--out", tmp_path / "i"),
            "'tiny' is not one the public Omnidata loader",
        ),
        (
            (
                small_job, "--format", "omnidata", "--out", tmp_path / "j", "--component", "replica",
                "--loader-dir", tmp_path / "taken",
            ),
            "is not the public Omnidata dataloader",
        ),
    ]
    for args, message in cases:
        code, _, err = run(capsys, *args)
        assert code == 2 and message in err, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"] and (taken / "x").read_text() == "mine"
    # a corrupt file (sha256 differs from the manifest) fails a verified export, which leaves no output
    bad = tmp_path / "bad"
    shutil.copytree(small_job, bad)
    (bad / "rgb/tiny/ycb_banana/point_1_view_1_domain_rgb.png").write_bytes(b"changed")
    code, _, err = run(capsys, bad, "--format", "webdataset", "--out", tmp_path / "g", "--verify")
    assert code == 2 and "sha256" in err and not (tmp_path / "g").exists()
    assert not list(tmp_path.glob(".g.partial-*"))


def test_a_listed_file_gone_missing_is_one_line_not_a_traceback(
    small_job: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    holes = tmp_path / "holes"
    shutil.copytree(small_job, holes)
    gone = "rgb/tiny/ycb_banana/point_1_view_1_domain_rgb.png"
    (holes / gone).unlink()
    commands = [
        ["export", str(holes), "--format", "webdataset", "--out", str(tmp_path / "shards"), "--no-progress"],
        ["preview", str(holes), "--cues", "rgb", "--no-progress"],
        ["sheet", str(holes), "--views", "4", "--out", str(tmp_path / "sheet.png")],
    ]
    for argv in commands:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"{gone}: listed in manifest.jsonl but missing" in err and "Traceback" not in err, (argv, err)
    assert not (tmp_path / "shards").exists() and not (tmp_path / "sheet.png").exists()
