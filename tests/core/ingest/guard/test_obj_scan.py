"""The OBJ pre-check's fast path (services.core.ingest.guard.obj_scan) gives the line-by-line check's verdict:
on plain files it answers, on anything else it leaves the file to that check; either way `_check_obj`'s
outcome (warnings, or the refusal's message) equals the line-by-line reading's."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from services.core.ingest.errors import SpaceError
from services.core.ingest.guard import mesh_checks, obj_scan
from services.core.ingest.guard.degenerate import CHECKED_FROM_FACES
from services.core.ingest.guard.obj_scan import plain_obj_mtllibs

BASE = (
    "# exported\nmtllib room.mtl\nmtllib missing.mtl\no room\n"
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n"
    "usemtl wall\ns off\nf 1/1/1 2/2/1 3/3/1\nf 2 4 3\nf -4 -3 -2\nf 4//1 3//1 2//1\n"
    "v 2 2 0\nf 5 4 -1\nl 1 2\n"
)


def outcome(check, path: Path, max_faces: int) -> tuple[str, object]:
    try:
        return "ok", check(path, max_faces)
    except SpaceError as e:
        return "refused", str(e)
    except ValueError as e:  # a malformed reference the line-by-line check does not survive
        return "error", str(e)


def same_verdict(path: Path, max_faces: int = 100) -> bool:
    """`_check_obj` (fast path first) and the line-by-line check alone say the same of the file."""
    return outcome(mesh_checks._check_obj, path, max_faces) == outcome(mesh_checks._check_obj_lines, path,
                                                                       max_faces)


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    (tmp_path / "room.mtl").write_text("newmtl wall\nKd 1 1 1\n")
    return tmp_path


def test_plain_file_is_answered_by_the_fast_path(folder: Path) -> None:
    data = BASE.encode()
    assert plain_obj_mtllibs(data, 100, CHECKED_FROM_FACES) == ["room.mtl", "missing.mtl"]
    path = folder / "room.obj"
    path.write_bytes(data)
    assert mesh_checks._check_obj(path, 100) == mesh_checks._check_obj_lines(path, 100)
    missing = "material library 'missing.mtl' is missing: the mesh renders untextured"
    assert mesh_checks._check_obj(path, 100) == [missing]


@pytest.mark.parametrize("text", [
    BASE + "f 1 2 9\n",  # a vertex that does not exist
    BASE + "f 0 1 2\n",
    BASE + "f -9 1 2\n",
    BASE.replace("v 2 2 0\n", ""),  # "f 5 ..." before its vertex
    BASE + "f 1 2 3",  # no newline at the end
    BASE + "f 1 2 3\r\n",
    BASE.replace("\n", "\r\n"),
    " " + BASE,
    BASE + "\tf 1 2 3\n",
    BASE + "f 1 2 --3\n",
    BASE + "f 1 2 3-\n",
    BASE + "f 1/-1 2 3\n",
    BASE + "f 1 2 x\n",
    BASE + "f 1 2 " + "9" * 25 + "\n",
    BASE + "f 1 2 \u00b2\n",
    BASE + "f 1 2 3\x0b\n",
    "v 0 0 0\nv 1 0 0\n",
    "",
])
def test_anything_but_plain_gives_the_line_by_line_verdict(folder: Path, text: str) -> None:
    path = folder / "room.obj"
    path.write_bytes(text.encode())
    assert same_verdict(path)


def test_the_face_limit_and_the_sampled_size_are_left_to_the_line_by_line_check() -> None:
    data = BASE.encode()
    assert plain_obj_mtllibs(data, 4, CHECKED_FROM_FACES) is None  # 5 faces, over the limit
    assert plain_obj_mtllibs(data, 100, 5) is None  # degenerate faces are sampled line by line


def test_mutated_files_give_the_same_verdict(folder: Path) -> None:
    rng = random.Random(7)
    alphabet = [" ", "\t", "\n", "\r", "-", "/", "0", "1", "4", "9", "f", "v", "m", "t", "x", "\x0b",
                "\u00e9"]
    path = folder / "room.obj"
    answered = 0
    for _ in range(600):
        text = list(BASE)
        for _ in range(rng.randint(1, 3)):
            i = rng.randrange(len(text) + 1)
            if rng.random() < 0.5 and i < len(text):
                del text[i]
            else:
                text.insert(i, rng.choice(alphabet))
        data = "".join(text).encode()
        path.write_bytes(data)
        answered += plain_obj_mtllibs(data, 100, CHECKED_FROM_FACES) is not None
        assert same_verdict(path), data
    assert answered > 50  # the comparison covers the fast path's answers, not only its refusals to answer


def test_files_past_the_fast_paths_sizes_are_left_to_the_streaming_check() -> None:
    many_lines = (BASE + "\n" * (obj_scan.MAX_LINES + 1)).encode()
    one_long_face = (BASE + "f 1 2 3" + " " * (obj_scan.MAX_FACE_BYTES + 1) + "\n").encode()
    assert plain_obj_mtllibs((BASE + "\n" * 1000).encode(), 100, CHECKED_FROM_FACES) is not None
    assert plain_obj_mtllibs(many_lines, 100, CHECKED_FROM_FACES) is None
    assert plain_obj_mtllibs(one_long_face, 100, CHECKED_FROM_FACES) is None
