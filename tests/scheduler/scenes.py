"""Analytic test scenes (world metres, +Z up) and brute-force geometry used as ground truth in tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from services.core.spaces import LoadedSpace


def _quad(a, b, c, d) -> list[list[float]]:
    return [a, b, c, d]


def _mesh_from_quads(quads: list[list[list[float]]], tris: list[list[list[float]]] | None = None) -> trimesh.Trimesh:
    """Triangles (0,1,2), (0,2,3) of each quad; normals follow the right-hand rule of the corner order."""
    faces_xyz = []
    for q in quads:
        faces_xyz.append([q[0], q[1], q[2]])
        faces_xyz.append([q[0], q[2], q[3]])
    faces_xyz.extend(tris or [])
    v = np.array(faces_xyz, dtype=np.float64).reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    m = trimesh.Trimesh(v, f, process=True)
    return m


def box_room(size=(6.0, 4.0, 2.7), origin=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    """Closed box room, floor at z = origin z, every face normal pointing into the room."""
    box = trimesh.creation.box(extents=size)
    box.apply_translation(np.array(origin) + np.array(size) / 2.0)
    # rebuild rather than box.invert(): trimesh 4 keeps stale cached face normals after invert()
    return trimesh.Trimesh(box.vertices, np.fliplr(box.faces), process=False)


def pillar(center_xy=(4.0, 2.0), half=0.3, z0=0.0, z1=2.7) -> trimesh.Trimesh:
    """Four outward-facing side walls of a square pillar (no caps: they would lie in the floor/ceiling)."""
    x0, x1 = center_xy[0] - half, center_xy[0] + half
    y0, y1 = center_xy[1] - half, center_xy[1] + half
    quads = [
        _quad([x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]),  # -y face, normal -y
        _quad([x1, y0, z0], [x1, y1, z0], [x1, y1, z1], [x1, y0, z1]),  # +x
        _quad([x1, y1, z0], [x0, y1, z0], [x0, y1, z1], [x1, y1, z1]),  # +y
        _quad([x0, y1, z0], [x0, y0, z0], [x0, y0, z1], [x0, y1, z1]),  # -x
    ]
    return _mesh_from_quads(quads)


def pillar_room() -> trimesh.Trimesh:
    """6 x 4 x 2.7 m room with a 0.6 m square floor-to-ceiling pillar centred at (4, 2)."""
    return trimesh.util.concatenate([box_room(), pillar()])


L_POLYGON = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 3.0], [3.0, 3.0], [3.0, 6.0], [0.0, 6.0]])


def prism_room(polygon: np.ndarray, height: float = 2.7) -> trimesh.Trimesh:
    """Room over a counter-clockwise polygon (floor at z=0), walls and caps facing inwards."""
    quads = []
    n = len(polygon)
    for i in range(n):
        a, b = polygon[i], polygon[(i + 1) % n]
        # going ccw, the interior is on the left; inward normal = z x (b - a)
        quads.append(_quad([*b, 0.0], [*a, 0.0], [*a, height], [*b, height]))
    tris = []
    for t in _ear_clip(polygon):
        p0, p1, p2 = polygon[t[0]], polygon[t[1]], polygon[t[2]]
        tris.append([[*p0, 0.0], [*p1, 0.0], [*p2, 0.0]])  # ccw seen from above: normal +z
        tris.append([[*p0, height], [*p2, height], [*p1, height]])  # ceiling: normal -z
    m = _mesh_from_quads(quads, tris)
    return m


def _ear_clip(poly: np.ndarray) -> list[tuple[int, int, int]]:
    idx = list(range(len(poly)))
    out = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 0:
                continue
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = poly[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                out.append((i0, i1, i2))
                idx.pop(k)
                break
    out.append((idx[0], idx[1], idx[2]))
    return out


def l_room() -> trimesh.Trimesh:
    """L-shaped room: a 6 x 6 m square without its 3 x 3 m corner at (3..6, 3..6), 2.7 m high."""
    return prism_room(L_POLYGON)


def in_l(points: np.ndarray) -> np.ndarray:
    """Analytic inside test of the L room's floor plan (open set)."""
    x, y = points[:, 0], points[:, 1]
    in_box = (x > 0) & (x < 6) & (y > 0) & (y < 6)
    return in_box & ~((x >= 3) & (y >= 3))


def table(center_xy=(1.5, 1.5), size=(1.2, 0.8), height=0.75, thickness=0.05) -> trimesh.Trimesh:
    """A table top slab without a bottom face (furniture scans are not seen from below)."""
    box = trimesh.creation.box(extents=(size[0], size[1], thickness))
    box.apply_translation([center_xy[0], center_xy[1], height - thickness / 2])
    keep = box.face_normals[:, 2] > -0.5
    box.update_faces(keep)
    return box


def furnished_room() -> trimesh.Trimesh:
    """Box room with a table: upward-facing area exceeds downward-facing area (breaks floor/ceiling ties)."""
    return trimesh.util.concatenate([box_room(), table()])


def random_furnished_room(rng: np.random.Generator) -> trimesh.Trimesh:
    """A closed box room (4-7 x 3-6 x 2.5-3 m) with 3-6 closed furniture blocks (0.4-1.8 m wide,
    0.4-2 m high, without bottoms) standing on the floor, inside the walls, and a pillar in half of them."""
    size = rng.uniform([4.0, 3.0, 2.5], [7.0, 6.0, 3.0])
    parts = [box_room(tuple(size))]
    for _ in range(int(rng.integers(3, 7))):
        ext = rng.uniform([0.4, 0.4, 0.4], [1.8, 1.2, 2.0])
        lo = rng.uniform([0.0, 0.0], size[:2] - ext[:2])
        block = trimesh.creation.box(extents=ext)
        block.apply_translation([lo[0] + ext[0] / 2, lo[1] + ext[1] / 2, ext[2] / 2])
        block.update_faces(block.face_normals[:, 2] > -0.5)
        parts.append(block)
    if rng.random() < 0.5:
        parts.append(pillar(tuple(rng.uniform([1.5, 1.5], size[:2] - 1.5)), 0.2, 0.0, float(size[2])))
    return trimesh.util.concatenate(parts)


def as_space(mesh: trimesh.Trimesh) -> LoadedSpace:
    """Wrap an in-memory world-frame mesh as a LoadedSpace (identity source_to_world)."""
    return LoadedSpace(
        mesh=mesh, source_path=Path("memory.ply"), source_to_world=np.eye(4), has_texture=False,
        has_vertex_colors=False, face_class=None, face_instance=None, has_semantics=False,
        bounds=np.array(mesh.bounds), checksum="0" * 64, face_count=len(mesh.faces),
    )


def brute_force_visible(mesh: trimesh.Trimesh, origins: np.ndarray, targets: np.ndarray, tol: float) -> np.ndarray:
    """Line of sight by Moller-Trumbore against every triangle in float64 (no Embree): clear when no
    triangle is hit strictly before the target minus tol."""
    tri = mesh.triangles
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.ones(len(origins), dtype=bool)
    for i in range(len(origins)):
        d = targets[i] - origins[i]
        dist = np.linalg.norm(d)
        d = d / dist
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origins[i] - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        qv = np.cross(s, e1)
        v = (qv @ d) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < dist - tol)
        out[i] = not hit.any()
    return out


def write_ply_with_labels(path: Path, vertices: np.ndarray, polygons: list[list[int]], class_id, inst_id,
                          instance_name: str = "instance_id", binary: bool = False,
                          class_name: str = "class_id") -> None:
    """A PLY with per-face class/instance properties (polygons may mix triangles and quads)."""
    lines = [
        "ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"element vertex {len(vertices)}", "property float x", "property float y", "property float z",
        f"element face {len(polygons)}", "property list uchar int vertex_indices",
    ]
    if class_id is not None:
        lines.append(f"property int {class_name}")
    if inst_id is not None:
        lines.append(f"property int {instance_name}")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode()
    if not binary:
        body = [" ".join(f"{c:.6f}" for c in v) for v in vertices]
        for k, poly in enumerate(polygons):
            row = [str(len(poly)), *map(str, poly)]
            if class_id is not None:
                row.append(str(int(class_id[k])))
            if inst_id is not None:
                row.append(str(int(inst_id[k])))
            body.append(" ".join(row))
        path.write_bytes(header + ("\n".join(body) + "\n").encode())
        return
    chunks = [header, np.asarray(vertices, dtype="<f4").tobytes()]
    for k, poly in enumerate(polygons):
        chunks.append(np.uint8(len(poly)).tobytes() + np.asarray(poly, dtype="<i4").tobytes())
        if class_id is not None:
            chunks.append(np.int32(class_id[k]).astype("<i4").tobytes())
        if inst_id is not None:
            chunks.append(np.int32(inst_id[k]).astype("<i4").tobytes())
    path.write_bytes(b"".join(chunks))


def brute_force_distance(mesh: trimesh.Trimesh, points: np.ndarray, chunk: int = 200) -> np.ndarray:
    """Exact distance from each point to the mesh: closest point on every triangle (no index)."""
    tri = mesh.triangles
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk]
        pi = np.repeat(np.arange(len(p)), len(tri))
        cp = trimesh.triangles.closest_point(np.tile(tri, (len(p), 1, 1)), p[pi])
        out[s:s + chunk] = np.linalg.norm(cp - p[pi], axis=1).reshape(len(p), len(tri)).min(axis=1)
    return out
