"""Benchmark: does any physical cue tell a floor seen from above from a ceiling seen from below?

A scan showing one horizontal plane and no opposite one (a floor without its ceiling, a ceiling-only
capture) is a mirror image: `services.core.ingest.frame.up_evidence` caps the geometry's lead of one sign over
the other (`mirror`). A cue that breaks the mirror must separate, with a margin, every floor of the real
rooms from the ceilings, the ceiling-only captures above all. Each horizontal plane of every real room of
bench/scans/rooms/truth.json is measured on its true up (metres): each room's floor, its ceiling where it
has one, and the ceiling of the ceiling-only captures (`"floor": false`). The plane is the densest band of
area facing into the room near its end; `r` is the distance from it into the room; a 2-D grid of `CELL`
across the plane, inside the plane's convex hull less `WALL_M` along its boundary, is its interior.

- `plane_missing_under_clutter`: the share of interior cells holding clutter (anything 0.05-1.2 m from the
  plane) where the plane itself is missing. Things standing on a floor touch it and hide it from a camera
  above; a fixture hanging from a ceiling leaves a gap through which oblique views could see the ceiling.
- `plane_missing_elsewhere`: the same share over interior cells with nothing 0.05-2 m from the plane (the
  scan's own holes), and `occlusion_excess`, the difference.
- `columns_touching`: the share of interior cells with a vertical surface spanning more than 0.15 m whose
  lowest point is within 0.08 m of the plane (furniture sides reach a floor; hanging fixtures stop short).
- `tops_supported`: the share of the area of patches facing away from the plane 0.15-1.5 m from it (tops
  on a floor, fixtures' undersides below a ceiling) with a vertical surface in or around their footprint
  that reaches within 0.08 m of the plane and rises to half their height (legs and sides; wires are not
  scanned).
- `tops_elongated`: the share of that area in long thin patches (at least 1 m long and 4 times longer than
  wide): ducts and strip lights at one offset below a ceiling.
- `tops_near_walls`: how much more of the tops lie within 0.6 m of the hull's boundary than its area there
  would give (furniture stands against walls; fixtures hang over the middle).
- `clutter_touching`: the share of the interior's clutter (surface samples 0.03-1.5 m from the plane) in
  connected clusters (5 cm voxels) that come within 0.10 m of the plane: what stands is connected to it,
  what hangs floats.
- `support_over_plane`: the area facing away from the plane 0.1-1.5 m from it over the plane's area.
- `far_half_horizontal`: the horizontal area (either side) further than half the extent from the plane, over
  the plane's area (a camera above a floor still sees tops and soffits up there).

Run: `.venv/bin/python bench/ingest/mirror_sign.py [--rooms NAME ...] [--out FILE]`; writes
bench/results/mirror_sign.json (per plane, and each measure's range per class: floors, ceilings of ordinary
rooms, ceiling-only captures; `separates`: whether the captures' range lies clear of the floors'). On the
real rooms none does: each range of the captures overlaps the floors' (the table it prints).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, QhullError

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from bench.lib.results import results_dir  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402

ROOMS = REPO / "bench" / "scans" / "rooms" / "truth.json"
SAMPLES = 300_000  # surface samples per room, drawn by area (a fixed seed)
CELL = 0.10  # metres, the grid across the plane
WALL_M = 0.3  # the hull's boundary band left out of the interior (walls and what stands against them)
PLANE_TOL_M = 0.04
TOUCH_M = 0.08
VOXEL_M = 0.05
MEASURES = ("plane_missing_under_clutter", "plane_missing_elsewhere", "occlusion_excess", "columns_touching",
            "tops_supported", "tops_elongated", "clutter_touching", "support_over_plane",
            "far_half_horizontal", "tops_near_walls")


class Plane:
    """One horizontal plane of a room and the samples around it: `d` points from the plane into the room."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, areas: np.ndarray, d: np.ndarray) -> None:
        h, self.c = points @ d, normals @ d
        lo, hi = float(h.min()), float(h.max())
        near = (self.c > np.cos(np.radians(15.0))) & (h < lo + 0.4 * (hi - lo))
        hist, edges = np.histogram(h[near], bins=np.arange(lo, lo + 0.4 * (hi - lo) + 0.02, 0.01),
                                   weights=areas[near])
        self.r = h - (edges[int(np.argmax(hist))] + 0.005)
        self.areas = areas
        a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        self.uv = np.column_stack([points @ a, points @ np.cross(d, a)])
        self.on = (np.abs(self.r) < PLANE_TOL_M) & (self.c > np.cos(np.radians(30.0)))
        self.extent = float(self.r.max())

    def grid(self, cell: float) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
        """(cell index per sample, grid shape, interior mask) on a grid of `cell` metres."""
        origin = self.uv[self.on].min(axis=0) - 1.0
        ij = np.floor((self.uv - origin) / cell).astype(np.int64)
        shape = (int(ij[:, 0].max()) + 3, int(ij[:, 1].max()) + 3)
        ij = np.clip(ij, 0, np.array(shape) - 1)
        hull = Delaunay(self.uv[self.on][ConvexHull(self.uv[self.on]).vertices])
        gi, gj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
        centres = np.column_stack([gi.ravel(), gj.ravel()]) * cell + origin + cell / 2
        inside = (hull.find_simplex(centres) >= 0).reshape(shape)
        return ij, shape, ndimage.binary_erosion(inside, iterations=max(1, round(WALL_M / cell)))


def _cells(ij: np.ndarray, shape: tuple[int, int], mask: np.ndarray) -> np.ndarray:
    g = np.zeros(shape, dtype=bool)
    g[ij[mask, 0], ij[mask, 1]] = True
    return g


def occlusion(p: Plane) -> dict[str, float]:
    """Where clutter stands over the interior, is the plane missing there, against elsewhere?"""
    ij, shape, interior = p.grid(CELL)
    plane = _cells(ij, shape, p.on)
    clutter = _cells(ij, shape, (p.r > 0.05) & (p.r < 1.2)) & interior
    empty = interior & ~_cells(ij, shape, (p.r > 0.05) & (p.r < 2.0))
    under = float((clutter & ~plane).sum() / max(int(clutter.sum()), 1))
    elsewhere = float((empty & ~plane).sum() / max(int(empty.sum()), 1))
    return {"plane_missing_under_clutter": under, "plane_missing_elsewhere": elsewhere,
            "occlusion_excess": under - elsewhere}


def columns_touching(p: Plane) -> float | None:
    """Share of interior cells with a tall vertical surface whose lowest point reaches the plane."""
    ij, shape, interior = p.grid(CELL)
    vert = (np.abs(p.c) < 0.3) & (p.r > -0.02) & (p.r < 1.2)
    low, high = np.full(shape, np.inf), np.full(shape, -np.inf)
    np.minimum.at(low, (ij[vert, 0], ij[vert, 1]), p.r[vert])
    np.maximum.at(high, (ij[vert, 0], ij[vert, 1]), p.r[vert])
    tall = interior & np.isfinite(low) & (high - low > 0.15)
    return None if not tall.any() else float((low[tall] < TOUCH_M).sum() / tall.sum())


Patches = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]


def _top_patches(p: Plane, cell: float) -> Patches:
    """Patches facing away from the plane 0.15-1.5 m from it, on a grid of `cell`: (labels, cells per patch,
    mean distance per patch, cell index per sample, grid shape)."""
    ij, shape, _ = p.grid(cell)
    top = (p.c > np.cos(np.radians(15.0))) & (p.r > 0.15) & (p.r < 1.5)
    count, height = np.zeros(shape), np.zeros(shape)
    np.add.at(count, (ij[top, 0], ij[top, 1]), 1.0)
    np.add.at(height, (ij[top, 0], ij[top, 1]), p.r[top])
    labels, n = ndimage.label(count >= 2)
    index = np.arange(1, n + 1)
    size = np.asarray(ndimage.sum(count >= 2, labels, index), dtype=np.float64)
    mean_h = np.asarray(ndimage.sum(height, labels, index)) / np.maximum(
        np.asarray(ndimage.sum(count, labels, index)), 1.0)
    return labels, size, mean_h, ij, shape


def tops_supported(p: Plane, cell: float = 0.05) -> float | None:
    """Share of the area of tops (patches facing away, 0.15-1.5 m out) with a column reaching the plane."""
    labels, size, mean_h, ij, shape = _top_patches(p, cell)
    vert = (np.abs(p.c) < 0.3) & (p.r > -0.05) & (p.r < 1.5)
    low, high = np.full(shape, np.inf), np.full(shape, -np.inf)
    np.minimum.at(low, (ij[vert, 0], ij[vert, 1]), p.r[vert])
    np.maximum.at(high, (ij[vert, 0], ij[vert, 1]), p.r[vert])
    big = np.flatnonzero(size >= 8)
    if not len(big):
        return None
    boxes = ndimage.find_objects(labels)
    held = 0.0
    for k in big:
        box = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in boxes[k])
        ring = ndimage.binary_dilation(labels[box] == k + 1, iterations=2)
        reaches = (low[box][ring] < TOUCH_M) & (high[box][ring] > 0.5 * mean_h[k])
        held += size[k] if bool(reaches.any()) else 0.0
    return float(held / size[big].sum())


def tops_elongated(p: Plane, cell: float = 0.05) -> float | None:
    """Share of the area of tops in long thin patches (ducts, strip lights; counters and shelves too)."""
    labels, size, _, _, _ = _top_patches(p, cell)
    big = np.flatnonzero(size >= 8)
    if not len(big):
        return None
    cells = np.column_stack(np.nonzero(labels)) * cell
    of_cell = labels[labels > 0]
    long = 0.0
    for k in big:
        xy = cells[of_cell == k + 1]
        values, axes = np.linalg.eigh(np.cov(xy.T))
        spread = np.sqrt(np.maximum(values, (cell / 3.5) ** 2))  # a one-cell-wide strip: a cell's spread
        thin = spread[1] >= 4 * spread[0] and float(np.ptp(xy @ axes[:, 1])) >= 1.0
        long += size[k] if thin else 0.0
    return float(long / size[big].sum())


def tops_near_walls(p: Plane) -> float | None:
    """Tops within 0.6 m of the hull's boundary, over the share of the hull's area there."""
    ij, shape, interior = p.grid(CELL)
    hull = ndimage.binary_dilation(interior, iterations=max(1, round(WALL_M / CELL)))
    near = hull & (ndimage.distance_transform_edt(hull) * CELL <= 0.6)
    tops = _cells(ij, shape, (p.c > np.cos(np.radians(15.0))) & (p.r > 0.1) & (p.r < 1.5)) & hull
    if tops.sum() < 10:
        return None
    return float((tops & near).sum() / tops.sum() / (near.sum() / hull.sum()))


def clutter_touching(p: Plane) -> float | None:
    """Share of the interior's clutter in voxel clusters that come within 0.10 m of the plane."""
    ij, _, interior = p.grid(CELL)
    band = interior[ij[:, 0], ij[:, 1]] & (p.r > 0.03) & (p.r < 1.5)
    if band.sum() < 50:
        return None
    q = np.column_stack([p.uv[band], p.r[band]])
    vox = np.floor((q - q.min(axis=0)) / VOXEL_M).astype(np.int64)
    occupied = np.zeros(tuple(vox.max(axis=0) + 1), dtype=bool)
    occupied[tuple(vox.T)] = True
    labels, n = ndimage.label(occupied, structure=np.ones((3, 3, 3)))
    of_sample = labels[tuple(vox.T)]
    lowest = np.asarray(ndimage.minimum(p.r[band], of_sample, np.arange(1, n + 1)))
    weight = np.bincount(of_sample, minlength=n + 1)[1:]
    return float(weight[lowest < 0.10].sum() / weight.sum())


def measure(p: Plane) -> dict[str, Any]:
    """Every measure of one plane (module docstring); None where the plane has nothing to measure."""
    plane_area = float(p.areas[p.on].sum())
    away = (p.c > np.cos(np.radians(15.0))) & (p.r > 0.1) & (p.r < 1.5)
    out: dict[str, Any] = {"plane_m2": round(plane_area, 2), "extent_m": round(p.extent, 2)}
    try:
        out.update(occlusion(p))
        out.update(columns_touching=columns_touching(p), tops_supported=tops_supported(p),
                   tops_elongated=tops_elongated(p), clutter_touching=clutter_touching(p))
    except (QhullError, ValueError):
        return out
    far = (np.abs(p.c) > np.cos(np.radians(15.0))) & (p.r > 0.5 * p.extent)
    out["tops_near_walls"] = tops_near_walls(p)
    if plane_area > 0:
        out.update(support_over_plane=float(p.areas[away].sum()) / plane_area,
                   far_half_horizontal=float(p.areas[far].sum()) / plane_area)
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


def planes_of(room: dict[str, Any]) -> list[tuple[str, float]]:
    """(which, sign along the true up) of a room's horizontal planes: its floor, its ceiling if it has one."""
    out = [] if room.get("floor") is False else [("floor", 1.0)]
    return out + ([("ceiling", -1.0)] if room.get("ceiling") else [])


def class_of(room: dict[str, Any], which: str) -> str:
    """floor | ceiling | ceiling_capture, single depth frames apart (`frame_` before it)."""
    name = "ceiling_capture" if room.get("floor") is False else which
    return ("frame_" if room.get("single_frame") else "") + name


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Each measure's range per class, and whether the ceiling captures lie clear of every floor."""
    out: dict[str, Any] = {}
    for m in MEASURES:
        ranges = {}
        for cls in sorted({r["class"] for r in rows}):
            values = [r[m] for r in rows if r["class"] == cls and r.get(m) is not None]
            if values:
                ranges[cls] = [min(values), max(values)]
        floors = [v for c, v in ranges.items() if c.endswith("floor")]
        caps = ranges.get("ceiling_capture")
        gap = None if not floors or caps is None else max(
            caps[0] - max(f[1] for f in floors), min(f[0] for f in floors) - caps[1])
        out[m] = {"ranges": ranges, "gap_captures_to_floors": None if gap is None else round(gap, 3),
                  "separates": gap is not None and gap > 0}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", nargs="*", help="only these rooms (names in truth.json)")
    ap.add_argument("--out", type=Path, default=results_dir() / "mirror_sign.json")
    args = ap.parse_args()
    truth = json.loads(ROOMS.read_text())
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for name, room in truth.items():
        if args.rooms and name not in args.rooms:
            continue
        mesh = load_space(REPO / room["file"], source_to_world=np.eye(4).tolist()).mesh
        points, faces = trimesh.sample.sample_surface(mesh, SAMPLES, seed=0)
        normals, areas = mesh.face_normals[faces], np.full(len(faces), mesh.area / SAMPLES)
        up = np.asarray(room["up"], dtype=np.float64) / np.linalg.norm(room["up"])
        for which, sign in planes_of(room):
            row = {"room": name, "plane": which, "class": class_of(room, which),
                   "held_out": bool(room.get("held_out")),
                   **measure(Plane(points, normals, areas, sign * up))}
            rows.append(row)
            print(json.dumps(row), flush=True)
    result: dict[str, Any] = {
        "protocol": __doc__.split("\n\n")[1].replace("\n", " "), "summary": summary(rows),
        "seconds": round(time.perf_counter() - t_start, 1), "planes": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print("\n| measure | floors (rooms) | floors (frames) | ceilings | ceiling-only captures | separates |")
    print("|---|---|---|---|---|---|")
    for m, s in result["summary"].items():
        def cell(cls: str, ranges: dict[str, list[float]] = s["ranges"]) -> str:
            return "-" if cls not in ranges else f"{ranges[cls][0]:.2f}-{ranges[cls][1]:.2f}"
        print(f"| {m} | {cell('floor')} | {cell('frame_floor')} | {cell('ceiling')} | "
              f"{cell('ceiling_capture')} | {s['separates']} (gap {s['gap_captures_to_floors']}) |")


if __name__ == "__main__":
    main()
