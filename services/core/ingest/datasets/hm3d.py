"""Habitat-Matterport 3D (HM3D, `<split>/<index>-<scene>/`) as downloaded.

- `<scene>.basis.glb` (the habitat release): textures compressed as Basis Universal / KTX2
  (`KHR_texture_basisu`), which neither Blender nor trimesh decodes and no package on PyPI transcodes for
  us, so it is refused, naming the releases that work: the plain `.glb` (hm3d-*-glb-v0.2) or the OBJ release
  (hm3d-*-obj-v0.2). When a plain `<scene>.glb` or `<scene>.obj` sits beside it, that is rendered.
- `<scene>.semantic.glb`: the same surfaces coloured per object (vertex colours, `COLOR_0`), and
  `<scene>.semantic.txt`: a header line, then `id,HEX,"name",region` per object. Instance id = that id; class
  id = 1.. over the scene's own sorted category names (HM3D names categories, it does not number them).
- glTF is +Y up, metres.
"""

from __future__ import annotations

import csv
import io
import json
import struct
from pathlib import Path

import numpy as np
import trimesh

from services.core.ingest.datasets.base import (
    DatasetError,
    DatasetScene,
    LabelledSurface,
    SceneLabels,
    first_existing,
    names_from_labels,
    transfer,
)

NAME = "hm3d"
BASIS_EXTENSION = "KHR_texture_basisu"


def scene_mesh(folder: Path) -> Path | None:
    """The mesh to render in an HM3D scene folder: the plain .glb, else the .obj, else the .basis.glb
    (refused)."""
    marks = sorted(folder.glob("*.semantic.glb")) or sorted(folder.glob("*.basis.glb"))
    if len(marks) != 1:
        return None
    scene = marks[0].name.removesuffix(".semantic.glb").removesuffix(".basis.glb")
    return first_existing(folder / f"{scene}.glb", folder / f"{scene}.obj", folder / f"{scene}.basis.glb")


def glb_uses_basis(path: Path) -> bool:
    """Whether a .glb's JSON chunk asks for Basis Universal textures."""
    try:
        with open(path, "rb") as f:
            header = f.read(20)
            if len(header) < 20 or header[:4] != b"glTF":
                return False
            length, kind = struct.unpack("<II", header[12:20])
            if kind != 0x4E4F534A:  # 'JSON'
                return False
            doc = json.loads(f.read(min(length, 64 << 20)))
    except (OSError, ValueError):
        return False
    used = set(doc.get("extensionsUsed", [])) | set(doc.get("extensionsRequired", []))
    return BASIS_EXTENSION in used


def basis_refusal(path: Path) -> str | None:
    """Why a mesh with Basis-compressed textures cannot be rendered, or None."""
    if path.suffix.lower() != ".glb" or not (path.name.endswith(".basis.glb") or glb_uses_basis(path)):
        return None
    scene = path.name.removesuffix(".basis.glb").removesuffix(".glb")
    return (
        f"{path.name}: its textures are Basis Universal / KTX2 compressed ({BASIS_EXTENSION}), which Blender "
        f"and trimesh cannot decode; use the plain release of the same scene instead: {scene}.glb "
        f"(HM3D's hm3d-*-glb-v0.2) or {scene}.obj with its textures (hm3d-*-obj-v0.2)"
    )


def read_semantic_txt(path: Path) -> dict[int, tuple[int, str]]:
    """Object id and category name per 24-bit colour of `<scene>.semantic.txt`."""
    rows = list(csv.reader(io.StringIO(path.read_text(errors="replace"))))
    out: dict[int, tuple[int, str]] = {}
    for n, row in enumerate(rows[1:], start=2):  # line 1: "HM3D Semantic Annotations"
        if not row:
            continue
        try:
            object_id, colour, name = int(row[0]), int(row[1], 16), row[2]
        except (ValueError, IndexError):
            raise DatasetError(f"{path.name} line {n}: expected id,HEX,\"name\",region") from None
        out[colour] = (object_id, name)
    return out


def read(mesh: Path) -> DatasetScene | None:
    folder = mesh.parent
    scene = mesh.name.removesuffix(".basis.glb").removesuffix(".glb").removesuffix(".obj")
    semantic_glb, semantic_txt = folder / f"{scene}.semantic.glb", folder / f"{scene}.semantic.txt"
    if mesh.name.endswith(".semantic.glb") or not (
        semantic_glb.is_file() or mesh.name.endswith(".basis.glb")
    ):
        return None
    if (why := basis_refusal(mesh)) is not None:
        raise DatasetError(why)

    def label(loaded: trimesh.Trimesh) -> SceneLabels:
        objects = read_semantic_txt(semantic_txt)
        try:
            semantic = trimesh.load(semantic_glb, force="mesh", process=False)
        except Exception as e:  # trimesh raises many kinds on corrupt input
            raise DatasetError(f"{semantic_glb.name}: could not read it ({type(e).__name__}: {e})") from None
        if not isinstance(semantic, trimesh.Trimesh):
            raise DatasetError(f"{semantic_glb.name}: holds no triangle mesh")
        visual, points = semantic.visual, np.asarray(semantic.vertices)
        if not isinstance(visual, trimesh.visual.ColorVisuals) or visual.kind != "vertex":
            raise DatasetError(f"{semantic_glb.name}: has no vertex colours (COLOR_0) to identify objects by")
        rgb = np.asarray(visual.vertex_colors)[:, :3].astype(np.int64)
        colour = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        class_of_name = names_from_labels([name for _, name in objects.values()])
        instance = np.array([objects.get(int(c), (0, ""))[0] for c in colour], dtype=np.int64)
        cls = np.array(
            [class_of_name.get(objects.get(int(c), (0, ""))[1], 0) for c in colour], dtype=np.int64
        )
        unknown = int((instance == 0).sum())
        notes = (
            (f"{unknown} semantic vertices have a colour {semantic_txt.name} does not list",)
            if unknown
            else ()
        )
        face_class, face_instance = transfer(
            loaded, LabelledSurface.from_vertices(points, np.asarray(semantic.faces), cls, instance))
        return SceneLabels(face_class, face_instance, {i: n for n, i in class_of_name.items()}, notes)

    labelled = semantic_glb.is_file() and semantic_txt.is_file()
    files = [p for p in (mesh, semantic_glb, semantic_txt) if p.is_file()]
    return DatasetScene(
        NAME, folder.name, mesh, tuple(files), up_axis="+y" if mesh.suffix == ".glb" else None,
        unit_scale=1.0, labeller=label if labelled else None,
    )
