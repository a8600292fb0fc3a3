"""Benchmark: real rooms levelled as users bring them, without asking.

Corpus: bench/scans/rooms/truth.json (real reconstructions and scans from several public sources, each with
its true up, how that truth is known, its source and licence; SOURCE.md beside each file). Every room is tried
- as delivered (the file's own frame and format),
- exported levelled as a Z-up PLY and as a Y-up GLB,
- under 5 random rotations, in metres, centimetres, millimetres, inches and metres again (PLY),
- and, reported apart (`tilted_about_a_wall`), levelled with its largest wall turned onto X, Y or Z and then
  tilted about that axis (`tests.fixtures.rotation_corpus.wall_tilts`): the wall on a source axis, the
  floor not, as a camera held unrolled and pitched leaves a fused scan about X,
through `resolve_frame`, the call `load_space` makes once the file is read. A point cloud is meshed by the
service's reconstruction in each case's own frame and units, as that file uploaded would be (cached in
$OMNIDATA_DATA_DIR/meshed: a first run meshes every case, ~5 s each), and its points go with its mesh.
Outcome per case: levelled (within 3 degrees), wrong (planned more than 3 degrees off without asking) or
refused (with the true up as the first candidate, or not). Single depth frames (one sensor view, not a room)
are reported apart from the rooms, and so are the held-out rooms (`"held_out": true`, files in
shared/rooms_held_out: never tuned on), with a figure of their own and one per held-out set
(`"held_out_set"`, 1 where absent). A gravity recorded beside a room
(`services.core.ingest.frame.recorded_gravity`) and the camera poses delivered with it (`capture_up` in
truth.json: the mean camera up) count for the delivered case only, as load_space reads them beside the file.

Run: `.venv/bin/python bench/ingest/ingest_real.py [--out FILE]`; writes the "real_rooms" section of
bench/results/ingest_real.json and prints the table per source, the held-out rooms apart.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from bench.lib.results import results_dir  # noqa: E402
from services.core.ingest.errors import SpaceError, UnitsAmbiguous, UpAmbiguous  # noqa: E402
from services.core.ingest.frame.recorded_gravity import read_recorded_up  # noqa: E402
from services.core.ingest.frame.resolve import FrameRequest, resolve_frame, rotation_to_z  # noqa: E402
from services.core.ingest.loading import load_space  # noqa: E402
from services.core.ingest.pointcloud import (  # noqa: E402
    CLOUD_SUFFIXES,
    Cloud,
    CloudError,
    cloud_from_ply,
    mesh_cloud_cached,
    read_text_cloud,
)
from tests.fixtures.rotation_corpus import wall_tilts  # noqa: E402

ROOMS = REPO / "bench" / "scans" / "rooms" / "truth.json"
SCALES = (1.0, 0.01, 0.001, 0.0254, 1.0)  # metres per unit of the rotated copies, in turn
LEVEL_DEG = 3.0
FIRST_DEG = 10.0  # a refusal's first candidate this close to the truth offers the true up first
Y_UP = Rotation.from_euler("x", -90, degrees=True).as_matrix()  # +Z -> +Y


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions, degrees."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def cases(suffix: str, up: np.ndarray, seed: int) -> Iterator[tuple[str, np.ndarray, float, str]]:
    """(case, rotation of the delivered frame, metres per unit, file suffix) of one room."""
    yield "delivered", np.eye(3), 1.0, suffix
    yield "levelled_z_ply", rotation_to_z(up), 1.0, ".ply"
    yield "levelled_y_glb", Y_UP @ rotation_to_z(up), 1.0, ".glb"
    rotations = Rotation.random(len(SCALES), random_state=np.random.default_rng(seed)).as_matrix()
    for i, (R, scale) in enumerate(zip(rotations, SCALES, strict=True)):
        yield f"rotated_{i}", R, scale, ".ply"


def run_case(mesh: Any, R: np.ndarray, scale: float, suffix: str, up: np.ndarray,
             name: str, recorded_up: np.ndarray | None = None,
             capture_up: np.ndarray | None = None, cloud: Cloud | None = None) -> dict[str, Any]:
    """One case through resolve_frame: its outcome against the truth. `recorded_up`: the up a gravity file
    beside the delivered room gives (load_space reads it there); `capture_up`: the mean camera up of the
    poses delivered with it (load_space reads a capture there); `cloud`: a point cloud as delivered, meshed
    anew in the case's frame (`mesh` is then unused), its points handed over for their own planes as
    load_space does."""
    T = np.eye(4)
    T[:3, :3] = R / scale
    if cloud is None:
        copy = mesh.copy()
        copy.apply_transform(T)
        points = None
    else:  # the points turned and scaled, then meshed as load_space meshes an uploaded cloud
        try:
            copy, points = meshed(cloud, R, scale, name)
        except CloudError as e:  # the upload would be refused so, naming the problem
            return {"outcome": "error", "message": str(e)[:200]}
    truth = R @ up
    request = FrameRequest("auto", "auto", None, None, capture_up=capture_up, recorded_up=recorded_up)
    try:
        _, est, units = resolve_frame(copy, suffix, request, name, None if points is None else lambda: points)
    except UpAmbiguous as e:
        first = angle_deg(np.asarray(e.candidates[0]["up"], dtype=float), truth)
        return {"outcome": "refused", "true_first": first < FIRST_DEG, "first_error_deg": round(first, 2)}
    except UnitsAmbiguous:
        return {"outcome": "units_refused"}
    except SpaceError as e:
        return {"outcome": "error", "message": str(e)[:200]}
    error = angle_deg(est.up, truth)
    record = est.record(units.scale)
    return {"outcome": "levelled" if error <= LEVEL_DEG else "wrong", "error_deg": round(error, 2),
            "units_right": bool(abs(units.scale - scale) <= 1e-9 * scale), "method": est.method,
            "reason": record.get("reason"), "probability": record.get("probability"),
            "margin": None if est.margin is None or not np.isfinite(est.margin) else round(est.margin, 3)}


def meshed(cloud: Cloud, R: np.ndarray, scale: float, name: str) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The cloud turned by `R` and written in units of `scale` metres, meshed as an upload of it would be
    (cached): the mesh and the turned points."""
    points = cloud.points @ (R / scale).T
    turned = Cloud(points, None if cloud.normals is None else cloud.normals @ R.T, cloud.colors)
    checksum = hashlib.sha256(points.tobytes() + f"{name}".encode()).hexdigest()
    return mesh_cloud_cached(lambda: turned, checksum, name)[0], points


def read_cloud(path: Path) -> Cloud | None:
    """A cloud file (a PLY without faces, .xyz, .pts) as load_space reads it; None for a mesh."""
    if path.suffix.lower() in CLOUD_SUFFIXES:
        return read_text_cloud(path)
    if path.suffix.lower() == ".ply":
        raw = trimesh.load(path)  # as load_space reads a PLY of points
        if len(getattr(raw, "faces", ())) == 0:
            return cloud_from_ply(raw)
    return None


def shares(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Levelled / wrong / refused (true up first or not) / other, as counts and shares of the cases."""
    n = len(rows)
    refused = [r for r in rows if r["outcome"] == "refused"]
    counts = {"cases": n, "levelled": sum(r["outcome"] == "levelled" for r in rows),
              "wrong": sum(r["outcome"] == "wrong" for r in rows), "refused": len(refused),
              "refused_true_first": sum(r["true_first"] for r in refused),
              "other": sum(r["outcome"] in ("units_refused", "error") for r in rows)}
    counts["share_levelled"] = round(counts["levelled"] / max(n, 1), 4)
    counts["share_true_first_of_refused"] = (round(counts["refused_true_first"] / len(refused), 4)
                                             if refused else None)
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rooms", nargs="*", help="only these rooms (names in truth.json)")
    ap.add_argument("--cases", nargs="*", help="only these cases (delivered, levelled_z_ply, levelled_y_glb, "
                    "rotated_0 ... rotated_4, tilted_x, tilted_y, tilted_z)")
    ap.add_argument("--extra", type=Path, action="append", default=[],
                    help="another truth.json of the same form (rooms that may not be redistributed), "
                    "measured alike")
    ap.add_argument("--out", type=Path, default=results_dir() / "ingest_real.json")
    args = ap.parse_args()

    truth = json.loads(ROOMS.read_text())
    for extra in args.extra:
        truth.update({name: {**room, "extra": True} for name, room in json.loads(extra.read_text()).items()})
    rows: list[dict[str, Any]] = []
    tilted: list[dict[str, Any]] = []  # reported apart: not the protocol
    t_start = time.perf_counter()
    # held-out rooms last and each held-out set after the earlier ones, so adding rooms leaves the other
    # rooms' random rotations (seed + index) as they were
    order = sorted(truth.items(), key=lambda item: (bool(item[1].get("held_out")),
                                                     int(item[1].get("held_out_set", 1)), item[0]))
    for i, (name, room) in enumerate(order):
        if args.rooms and name not in args.rooms:
            continue
        path = REPO / room["file"]  # an absolute path stays as it is
        # the file read and meshed as on ingest, kept in its own frame (identity source_to_world)
        cloud = read_cloud(path)  # meshed per case in run_case
        mesh = None if cloud is not None else load_space(path, source_to_world=np.eye(4).tolist()).mesh
        up = np.asarray(room["up"], dtype=float)
        # converted copies: the format as delivered
        delivered = room.get("delivered_as") or path.suffix.lower()
        # what the capture delivered beside the room (a recorded gravity, the camera poses): only the
        # delivered file has it (the exported and rotated copies are new files, judged on their own)
        recorded = read_recorded_up(path.parent)
        poses = room.get("capture_up")
        for case, R, scale, suffix in cases(delivered, up / np.linalg.norm(up), args.seed + i):
            if args.cases and case not in args.cases:
                continue
            given = recorded.up if recorded is not None and case == "delivered" else None
            cameras = np.asarray(poses, dtype=float) if poses is not None and case == "delivered" else None
            row = {"room": name, "place": room.get("place", name), "source": room["source"],
                   "held_out_set": int(room.get("held_out_set", 1)) if room.get("held_out") else None,
                   "kind": room["kind"], "single_frame": bool(room.get("single_frame")),
                   "held_out": bool(room.get("held_out")), "extra": bool(room.get("extra")), "case": case,
                   "recorded_gravity": given is not None, "capture_poses": cameras is not None,
                   **run_case(mesh, R, scale, suffix, up, name, given, cameras, cloud)}
            rows.append(row)
            print(json.dumps(row), flush=True)
        tilts: list[tuple[str, np.ndarray]] = []
        if not args.cases or any(c.startswith("tilted_") for c in args.cases):
            try:
                tilts = wall_tilts(mesh if cloud is None else meshed(cloud, np.eye(3), 1.0, name)[0], up)
            except CloudError:  # refused as delivered (above): no wall to find
                pass
        for case, R in tilts:
            if args.cases and case not in args.cases:
                continue
            row = {"room": name, "held_out": bool(room.get("held_out")), "single_frame":
                   bool(room.get("single_frame")), "case": case,
                   **run_case(mesh, R, 1.0, ".ply", up, name, cloud=cloud)}
            tilted.append(row)
            print(json.dumps(row), flush=True)

    def pick(single: bool, held_out: bool = False, **kw: object) -> list[dict[str, Any]]:
        return [r for r in rows if r["single_frame"] == single and r["held_out"] == held_out
                and all(r[k] == v for k, v in kw.items())]

    held = [r for r in rows if r["held_out"]]

    places = sorted({r["place"] for r in rows})
    sources = sorted({r["source"] for r in rows})
    result = {
        "protocol": "each room as delivered, levelled Z-up PLY, levelled Y-up GLB, 5 random rotations in "
                    "m/cm/mm/in/m; levelled = within 3 degrees without asking",
        "corpus": {"places": len(places), "sources": len(sources), "files": len({r["room"] for r in rows}),
                   "extra_files": sorted({r["room"] for r in rows if r["extra"]})},
        "rooms": shares(pick(False)),
        "rooms_by_case": {c: shares(pick(False, case=c)) for c in dict.fromkeys(r["case"] for r in rows)},
        "by_source": {s: shares([r for r in rows if r["source"] == s]) for s in sources},
        "by_room": {n: [r["outcome"] + ("" if r["outcome"] != "refused" else "+" if r["true_first"] else "-")
                        for r in rows if r["room"] == n] for n in sorted({r["room"] for r in rows})},
        "single_depth_frames": shares(pick(True)),
        "held_out": {"files": sorted({r["room"] for r in held}), "rooms": shares(pick(False, True)),
                     "single_depth_frames": shares(pick(True, True)),
                     "by_kind": {k: shares([r for r in held if r["kind"] == k])
                                 for k in sorted({r["kind"] for r in held})},
                     "by_set": {str(k): shares([r for r in held if r["held_out_set"] == k])
                                for k in sorted({r["held_out_set"] for r in held})}},
        "wrong_cases": [r for r in rows if r["outcome"] == "wrong"],
        "tilted_about_a_wall": {"rooms": shares([r for r in tilted if not r["single_frame"]]),
                                "single_depth_frames": shares([r for r in tilted if r["single_frame"]]),
                                "wrong_cases": [r for r in tilted if r["outcome"] == "wrong"],
                                "rows": tilted},
        "seconds": round(time.perf_counter() - t_start, 1),
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
        "rows": rows,
    }
    document = json.loads(args.out.read_text()) if args.out.exists() else {}
    document["real_rooms"] = result
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    print("\n| source | cases | levelled | wrong | refused (true up first) |\n|---|---|---|---|---|")
    for label, s in [*result["by_source"].items(), ("all rooms (multi-view)", result["rooms"]),
                     ("single depth frames", result["single_depth_frames"]),
                     ("held-out rooms (multi-view)", result["held_out"]["rooms"]),
                     ("held-out single depth frames", result["held_out"]["single_depth_frames"]),
                     ("tilted about a wall's axis, rooms", result["tilted_about_a_wall"]["rooms"]),
                     ("tilted about a wall's axis, single frames",
                      result["tilted_about_a_wall"]["single_depth_frames"])]:
        print(f"| {label} | {s['cases']} | {s['levelled']} ({s['share_levelled']:.0%}) | {s['wrong']} | "
              f"{s['refused']} ({s['refused_true_first']}) |")
    print(f"{len(places)} places from {len(sources)} sources; wrote {args.out}")


if __name__ == "__main__":
    main()
