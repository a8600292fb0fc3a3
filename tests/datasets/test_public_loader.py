"""The export against the public Omnidata loader's own published code: the `omnidata-tools` package on PyPI
(a dev dependency) ships the starter dataset's component modules, which read their split CSVs from their own
package folder exactly as the dataloader's component classes do (`component_datasets/<component>/
train_val_test_*.csv`, read by its `get_splits`). The export installs its splits into a copy of that package
(`--loader-dir`), and the package's modules, imported from there in a fresh interpreter, list our spaces."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import main
from services.cli.export import _split_warnings
from services.datasets.public_loader import COMPONENTS, TASKONOMY_DATA_AMOUNTS, component

omnidata_tools = pytest.importorskip("omnidata_tools", reason="dev dependency omnidata-tools")

READ_SPLITS = """
import json
from omnidata_tools.dataset.starter_dataset.component_datasets import taskonomy, replica, hypersim
print(json.dumps({"taskonomy": taskonomy.taskonomy_split_to_buildings, "replica": replica.split_to_spaces,
                  "hypersim": hypersim.split_to_spaces, "file": taskonomy.__file__}))
"""


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main(["export", *map(str, args), "--no-progress"])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def package_copy(tmp_path: Path) -> Path:
    """A private copy of the installed omnidata_tools package (the test must not change the venv's)."""
    root = tmp_path / "pkg"
    shutil.copytree(Path(omnidata_tools.__file__).parent, root / "omnidata_tools")
    return root


def published_splits(package_root: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(package_root)}
    done = subprocess.run(
        [sys.executable, "-c", READ_SPLITS], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["file"].startswith(str(package_root))  # the copy was imported, not the installed package
    return result


def test_taskonomy_export_is_read_by_the_published_modules_for_every_data_amount(
    small_job: Path, package_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    starter = package_copy / "omnidata_tools/dataset/starter_dataset"
    released = (starter / "component_datasets/taskonomy/train_val_test_tiny.csv").read_text()
    before = published_splits(package_copy)
    assert "ycb_banana" not in json.dumps(before["taskonomy"])
    out = tmp_path / "omni"
    code, text, err = run(capsys, small_job, "--format", "omnidata", "--out", out, "--component", "taskonomy",
                          "--split-ratios", "1,0,0", "--loader-dir", starter)
    assert code == 0, err
    assert f"installed component_datasets/taskonomy/train_val_test_tiny.csv into {starter}" in text
    after = published_splits(package_copy)
    for amount in TASKONOMY_DATA_AMOUNTS:  # TaskonomyDataset picks '<data_amount>-<split>' from these
        assert after["taskonomy"][amount] == {"train": ["ycb_banana"], "val": [], "test": []}
    # the released split is kept beside ours, and a single space warns that val and test are empty
    assert (starter / "component_datasets/taskonomy/train_val_test_tiny.csv.orig").read_text() == released
    assert "the val and test split(s) hold no space" in err
    assert after["replica"] == before["replica"]  # other components untouched


def test_without_loader_dir_one_command_remains_and_it_also_drops_a_stale_cache(
    small_job: Path, package_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "omni"
    code, text, err = run(capsys, small_job, "--format", "omnidata", "--out", out, "--component", "replica",
                          "--split-ratios", "0,1,0")
    assert code == 0, err
    command = text.split("one command remains: ")[1].strip()
    assert command == f"omnidata export {out} --loader-dir PATH_TO_YOUR_OMNIDATA_CHECKOUT"
    # the loader was run before the split was installed: its index of 0 files is cached in the data root
    stale = out / ".data_cache" / "ReplicaDataset_tiny_val"
    stale.mkdir(parents=True)
    (stale / "rgb_urls.pkl").write_bytes(pickle.dumps([]))
    # the printed command, with a checkout given as the repository root (dataloader found below it)
    checkout = tmp_path / "checkout"
    (checkout / "omnidata_tools/torch").mkdir(parents=True)
    shutil.copytree(package_copy / "omnidata_tools/dataset/starter_dataset",
                    checkout / "omnidata_tools/torch/dataloader")
    code, text, err = run(capsys, out, "--loader-dir", checkout)
    assert code == 0, err
    assert "removed the loader's stale file index" in text and not (out / ".data_cache").exists()
    installed = (
        checkout / "omnidata_tools/torch/dataloader/component_datasets/replica/train_val_test_replica.csv"
    )
    assert (
        installed.read_text() == (out / "component_datasets/replica/train_val_test_replica.csv").read_text()
    )
    code, _, err = run(capsys, tmp_path / "checkout", "--loader-dir", checkout)
    assert code == 2 and "holds no component_datasets" in err


def test_hypersim_splits_by_the_scene_the_class_looks_up() -> None:
    hypersim = component("hypersim")
    assert (
        hypersim.split_id("ai_001_001-cam_00") == "ai_001_001"
        and component("replica").split_id("a-b") == "a-b"
    )
    with pytest.raises(ValueError, match="known: taskonomy .*replica_gso .*blended_mvg"):
        component("gso")
    assert set(COMPONENTS) == {"taskonomy", "replica", "replica_gso", "hypersim", "blended_mvg"}
    assert _split_warnings({"a": "train", "b": "val", "c": "test"}) == []
    assert "test split(s) hold no space" in _split_warnings({"a": "train", "b": "val"})[0]
