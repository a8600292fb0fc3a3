"""What the public Omnidata dataloader (EPFL-VILAB/omnidata, `omnidata_tools/torch/dataloader`) needs besides
the files: its component names, the split CSVs it opens, and where it opens them.

Facts about that loader, read from its source (nothing of it is copied here):
- each component class (`TaskonomyDataset`, `ReplicaDataset`, ...) reads its split CSV from its own package
  folder, `<dataloader>/component_datasets/<component>/train_val_test_<component>.csv`, never from the data
  root, so a new dataset loads 0 items, silently, until that file is installed there;
- `TaskonomyDataset` also reads one CSV per data amount
  (`train_val_test_{debug,tiny,medium,full,fullplus}.csv`) when its module is imported, and picks the spaces
  of `<data_amount>-<split>` from it;
- `HypersimDataset` looks a folder up by the part of its name before the first '-' (`ai_001_001-cam_00`);
- every class caches its file index under `<data_path>/.data_cache/<Class>_<amount>_<split>/`, and a cache
  made before the split was installed keeps 0 items until it is removed.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

TASKONOMY_DATA_AMOUNTS = ("debug", "tiny", "medium", "full", "fullplus")


@dataclass(frozen=True)
class LoaderComponent:
    """One component class of the public loader: its class name and the split CSV names it opens."""

    name: str
    class_name: str
    split_files: tuple[str, ...]

    def split_id(self, space: str) -> str:
        """The id this class looks a space's folder up by in its split CSV."""
        return space.split("-")[0] if self.name == "hypersim" else space


COMPONENTS: dict[str, LoaderComponent] = {
    c.name: c
    for c in (
        LoaderComponent(
            "taskonomy", "TaskonomyDataset",
            ("train_val_test_taskonomy.csv", *(f"train_val_test_{a}.csv" for a in TASKONOMY_DATA_AMOUNTS)),
        ),
        LoaderComponent("replica", "ReplicaDataset", ("train_val_test_replica.csv",)),
        LoaderComponent("replica_gso", "GSOReplicaDataset", ("train_val_test_replica_gso.csv",)),
        LoaderComponent("hypersim", "HypersimDataset", ("train_val_test_hypersim.csv",)),
        LoaderComponent("blended_mvg", "BlendedMVGDataset", ("train_val_test_blended_mvg.csv",)),
    )
}

# cues the loader's default transforms cannot decode as we store them; said once per export
CUE_NOTES = {
    "fragments": "fragments are ours (.npy, HxW uint32 face indices); the loader's transform_fragment "
    "expects an HxWx3 array and fails: pass transform={'fragments': lambda a: "
    "torch.from_numpy(a.astype('int64'))}",
    "segment_unsup2d": "segment_unsup2d has no default transform in the loader: pass "
    "transform={'segment_unsup2d': transform_dense_labels} (from its transforms module)",
    "segment_unsup25d": "segment_unsup25d has no default transform in the loader: pass "
    "transform={'segment_unsup25d': transform_dense_labels} (from its transforms module)",
}


class LoaderDirError(ValueError):
    """A --loader-dir that is not a checkout of the public dataloader."""


def component(name: str) -> LoaderComponent:
    """The loader component of that name, or a ValueError that lists the known ones."""
    try:
        return COMPONENTS[name]
    except KeyError:
        known = ", ".join(f"{c.name} ({c.class_name})" for c in COMPONENTS.values())
        raise ValueError(f"component {name!r} is not one the public Omnidata loader has a class for; "
                         f"known: {known}") from None


def split_rel_paths(comp: LoaderComponent) -> list[str]:
    """The split CSVs of a component, relative to an export root or a dataloader folder."""
    return [f"component_datasets/{comp.name}/{f}" for f in comp.split_files]


def _holds_components(folder: Path) -> bool:
    return any((folder / "component_datasets" / name).is_dir() for name in COMPONENTS)


def find_dataloader(path: Path) -> Path:
    """The folder whose `component_datasets/<component>/` the loader reads: `path` itself, or the dataloader
    package of a repository checkout at `path`."""
    for candidate in (path, path / "omnidata_tools" / "torch" / "dataloader", path / "torch" / "dataloader"):
        if _holds_components(candidate):
            return candidate
    raise LoaderDirError(
        f"{path} is not the public Omnidata dataloader: expected component_datasets/<component>/ "
        "in it or in omnidata_tools/torch/dataloader below it"
    )


def exported_components(export_root: Path) -> list[LoaderComponent]:
    """The components whose split CSVs an omnidata export holds."""
    folder = export_root / "component_datasets"
    names = sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
    if not names:
        raise ValueError(f"{export_root} holds no component_datasets/<component>/ split CSVs: "
                         "is it an `omnidata export --format omnidata` output?")
    return [component(n) for n in names]


def install_splits(export_root: Path, loader_dir: Path) -> list[str]:
    """Copy an export's split CSVs into a dataloader checkout and drop the export's stale loader cache.

    A CSV already there that is not ours is kept once beside it as `<name>.orig` (the released split).
    Returns one line per action, for the user.
    """
    dataloader = find_dataloader(loader_dir)
    done: list[str] = []
    for comp in exported_components(export_root):
        for rel in split_rel_paths(comp):
            source, target = export_root / rel, dataloader / rel
            if not source.is_file():
                raise ValueError(f"{source} is missing: export again with this version")
            target.parent.mkdir(parents=True, exist_ok=True)
            backup = target.with_name(target.name + ".orig")
            if target.is_file() and not backup.exists() and target.read_bytes() != source.read_bytes():
                shutil.copy2(target, backup)
                done.append(f"kept the loader's own {rel} as {backup.name}")
            shutil.copyfile(source, target)
            done.append(f"installed {rel} into {dataloader}")
    cache = export_root / ".data_cache"
    if cache.exists():
        shutil.rmtree(cache)
        done.append(f"removed the loader's stale file index {cache}")
    return done
