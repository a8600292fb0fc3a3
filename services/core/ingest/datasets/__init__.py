"""The public scan datasets as downloaded: one reader module per dataset, one line each in LAYOUTS.

A reader has `NAME`, `scene_mesh(folder)` (the mesh to render when `folder` is one of its scenes, else None)
and `read(mesh)` (the DatasetScene of that mesh when the files around it are its dataset's, else None;
DatasetError when the dataset's files cannot be used as they are). `find_scenes` turns a dataset root
(`ScanNet/scans/`, `hm3d/train/`, ...) into its scenes, each named by its scene id.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from services.core.ingest.datasets import gibson, hm3d, matterport, replica, rscan, scannet, scannetpp
from services.core.ingest.datasets.base import DatasetError, DatasetScene, SceneLabels

LAYOUTS: tuple[ModuleType, ...] = (
    scannet,
    scannetpp,
    hm3d,
    matterport,
    replica,
    rscan,
    gibson,
)

MAX_ROOT_DEPTH = 3  # ScanNet/scans/<scene>, hm3d/train/<scene>, Matterport v1/scans/<house>

__all__ = [
    "DatasetError", "DatasetScene", "SceneLabels", "ScenePath", "expand_roots", "find_scenes",
    "scene_mesh_in", "scene_of",
]


def scene_mesh_in(folder: Path) -> Path | None:
    """The mesh to render when `folder` is one scene of a known dataset, else None."""
    for layout in LAYOUTS:
        mesh = layout.scene_mesh(folder)
        if mesh is not None:
            return mesh
    return None


def scene_of(mesh: Path) -> DatasetScene | None:
    """The dataset scene a mesh file belongs to (by its name and the files beside it), or None.

    DatasetError for a file of a dataset release that cannot be rendered (HM3D's Basis textures).
    """
    if (why := hm3d.basis_refusal(mesh)) is not None:
        raise DatasetError(why)
    for layout in LAYOUTS:
        scene = layout.read(mesh)
        if scene is not None:
            return scene
    return None


@dataclass(frozen=True)
class ScenePath:
    """One scene found under a dataset root: its id (its folder's name, as the datasets name their scene
    folders: scene0000_00, 00800-TEEsavR23oF, room_0), folder, and why it cannot be used (None: it can)."""

    scene_id: str
    folder: Path
    dataset: str | None
    refused: str | None = None


def _scene_at(folder: Path) -> ScenePath | None:
    mesh = scene_mesh_in(folder)
    if mesh is None:
        return None
    try:
        scene = scene_of(mesh)
    except DatasetError as e:
        return ScenePath(folder.name, folder, None, str(e))
    if scene is None:
        return None
    return ScenePath(folder.name, folder, scene.dataset)


def find_scenes(root: Path) -> list[ScenePath]:
    """The scenes below a dataset root (not the root itself), sorted by folder; [] when there are none."""
    found: list[ScenePath] = []
    level = [root]
    for _ in range(MAX_ROOT_DEPTH):
        below: list[Path] = []
        for folder in level:
            for child in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
                scene = _scene_at(child)
                if scene is not None:
                    found.append(scene)
                else:
                    below.append(child)
        level = below
    return found


def is_dataset_root(path: Path) -> bool:
    """A folder that is no scene itself but holds scenes of a known dataset below it."""
    return path.is_dir() and scene_mesh_in(path) is None and bool(find_scenes(path))


def expand_roots(paths: list[Path]) -> list[ScenePath]:
    """Each path as a space: a dataset root becomes its scenes (named by scene id, refused ones kept with
    the reason); anything else stays one space named by its own file or folder (dataset None)."""
    out: list[ScenePath] = []
    for path in paths:
        if is_dataset_root(path):
            out.extend(find_scenes(path))
        else:
            out.append(ScenePath(path.name, path, None))
    return out
