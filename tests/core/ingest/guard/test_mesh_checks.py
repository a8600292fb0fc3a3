"""Pre-parse checks of mesh files: valid OBJ variants pass, damage is named (the hostile corpus covers the
rest)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from services.core.ingest.errors import SpaceError
from services.core.ingest.guard import mesh_checks
from services.core.ingest.guard.mesh_checks import check_source

QUAD = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"


@pytest.mark.parametrize(
    "text",
    [
        QUAD + "f 1 2 3\nf 2 4 3\n",
        QUAD.replace("v ", "v\t") + "f\t1 2 3\r\nf 2/1 4/2/3 3//1\r\n",  # tabs, CRLF, uv/normal refs
        QUAD + "f -4 -3 -2\n  f 2 4 3\n",  # relative indices, indented statements
        "# comment\n" + QUAD + "g group\nusemtl none\nf 1 2 3\n",
    ],
)
def test_valid_obj_variants_pass(tmp_path: Path, text: str) -> None:
    path = tmp_path / "ok.obj"
    path.write_bytes(text.encode())
    assert check_source(path) == []


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (QUAD + "f 1 2 3\nf 2 4", "stops mid-statement"),
        (QUAD + "f 1 2 3\nv 0.5 0.", "stops mid-statement"),
        (QUAD + "f 1 2 5\n", "refers to vertex 5 but only 4"),
        (QUAD + "f -5 1 2\n", "refers to vertex -5"),
        (QUAD + "f 1 2 3\nf 0 1 2\n", "refers to vertex 0"),
        (QUAD, "4 vertices but no faces"),
    ],
)
def test_damaged_obj_is_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_bytes(text.encode())
    with pytest.raises(SpaceError, match=message):
        check_source(path)


def test_a_whole_last_line_without_newline_is_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "cut.obj"
    path.write_bytes((QUAD + "f 1 2 3\nf 2 4 3").encode())
    assert any("may be truncated" in w for w in check_source(path))


def test_face_limit_counts_obj_faces(tmp_path: Path) -> None:
    obj = tmp_path / "many.obj"
    obj.write_bytes((QUAD + "f 1 2 3\n" * 5).encode())
    with pytest.raises(SpaceError, match="more than the limit of 4"):
        check_source(obj, max_faces=4)
    assert check_source(obj, max_faces=5) == []


def _glb(doc: dict[str, object]) -> bytes:
    chunk = json.dumps(doc).encode()
    chunk += b" " * (-len(chunk) % 4)
    return struct.pack("<4sIIII", b"glTF", 2, 20 + len(chunk), len(chunk), 0x4E4F534A) + chunk


@pytest.mark.parametrize("suffix", [".gltf", ".glb"])
def test_references_of_big_gltf_files_are_checked_too(
    tmp_path: Path, suffix: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A glTF's size does not exempt it: padding one past the header limit must not let '../' through."""
    monkeypatch.setattr(mesh_checks, "MAX_HEADER_BYTES", 1024)  # a small limit keeps the file small
    (tmp_path / "outside.bin").write_bytes(b"\0" * 36)
    doc: dict[str, object] = {
        "asset": {"version": "2.0"}, "buffers": [{"uri": "../outside.bin", "byteLength": 36}],
        "extras": "x" * (70 * mesh_checks.MAX_HEADER_BYTES),
    }
    (tmp_path / "sub").mkdir()
    path = tmp_path / "sub" / f"big{suffix}"
    path.write_bytes(json.dumps(doc).encode() if suffix == ".gltf" else _glb(doc))
    with pytest.raises(SpaceError, match="climbs out of the mesh's folder"):
        check_source(path)


def test_a_glb_whose_json_chunk_runs_past_the_end_is_refused(tmp_path: Path) -> None:
    data = bytearray(_glb({"asset": {"version": "2.0"}}))
    data[12:16] = struct.pack("<I", 10_000)  # the JSON chunk's length
    path = tmp_path / "cut.glb"
    path.write_bytes(bytes(data))
    with pytest.raises(SpaceError, match="truncated or corrupt"):
        check_source(path)


def test_a_big_obj_of_degenerate_faces_is_refused_before_the_rest_is_read(tmp_path: Path) -> None:
    from tests.fixtures.hostile_corpus import varied_degenerate_obj

    path = tmp_path / "line.obj"
    # after the first 100k faces, a face naming a vertex that does not exist: never reached
    path.write_bytes(varied_degenerate_obj(150_000, collinear=True) + b"f 1 2 999999999\n")
    with pytest.raises(SpaceError, match="sampled faces .* are degenerate"):
        check_source(path)


def test_a_big_obj_of_good_faces_is_not_taken_for_degenerate(tmp_path: Path) -> None:
    side = 300  # a 300 x 300 grid: 178,802 triangles, none degenerate
    verts = "".join(f"v {x} {y} {(x * y) % 7 * 0.01}\n" for y in range(side) for x in range(side))
    faces = "".join(f"f {y * side + x + 1} {y * side + x + 2} {(y + 1) * side + x + 1}\n"
                    f"f {y * side + x + 2} {(y + 1) * side + x + 2} {(y + 1) * side + x + 1}\n"
                    for y in range(side - 1) for x in range(side - 1))
    path = tmp_path / "grid.obj"
    path.write_text(verts + faces)
    assert check_source(path) == []
