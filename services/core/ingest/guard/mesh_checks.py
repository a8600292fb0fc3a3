"""Checks of a mesh file before it is parsed: truncation, element counts past the limits, unsafe file
references.

trimesh accepts a truncated ASCII PLY or OBJ silently with a fraction of its faces, reads a PLY header's
counts before looking at the data, and follows texture paths wherever they point. `check_source` reads the
file itself (headers, and the lines of text formats, streamed) and raises SpaceError with a message for the
user when:

- the file is cut short: an ASCII PLY with fewer lines than its header declares, an OBJ whose last line is
  an incomplete vertex or face, a face that refers to a vertex the file does not have, or a GLB shorter than
  its header's length;
- a PLY header or an OBJ declares more faces than MAX_FACES (refused before any array is allocated);
- an OBJ has vertices but no faces (a triangle mesh is needed), or is big and mostly degenerate faces
  (`services.core.ingest.guard.degenerate`: sampled, before the full parse);
- a material library, texture, glTF buffer or image is named by an absolute path or one climbing out of the
  mesh's folder ('..'), or a texture an .mtl names is missing (these give the clearer messages; that no
  file outside the scan's folder is ever read is the confined resolver's guarantee,
  `services.core.ingest.guard.confine`);
- an image a GLB or glTF embeds declares more pixels than the texture limit
  (`services.core.ingest.guard.texture_limits`).

It returns warnings: an .mtl that is missing (the mesh renders untextured), an OBJ whose last line is whole
but has no newline (exporters end with one: it may have been cut at a token's end).
"""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from services.core.ingest.errors import SpaceError
from services.core.ingest.guard.confine import ReferenceRefused, read_confined
from services.core.ingest.guard.degenerate import CHECKED_FROM_FACES, FaceSample, degenerate_refusal
from services.core.ingest.guard.obj_scan import MAX_BYTES, plain_obj_mtllibs
from services.core.ingest.guard.texture_limits import embedded_refusal, glb_bin_offset

MAX_FACES = 50_000_000  # beyond every scan we render; trimesh needs ~100 bytes per face while loading
MAX_VERTICES = 3 * MAX_FACES
MAX_HEADER_BYTES = 1 << 20  # a PLY header larger than this is not a scan

_PLY_ELEMENT = re.compile(rb"^element\s+(\S+)\s+(\S+)\s*$")
_OBJ_REF = re.compile(r"^-?\d+(/-?\d*)?(/-?\d+)?$")
_MTL_MAP = re.compile(r"^\s*(map_\w+|bump|disp|decal|norm)\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", re.IGNORECASE)
_OBJ_MIN_FIELDS = {"v": 3, "vn": 3, "vt": 1, "f": 3, "l": 2}


def check_source(source: Path, *, max_faces: int = MAX_FACES) -> list[str]:
    """Refuse (SpaceError) a mesh file that is truncated, over the limits or names unsafe paths; return
    warnings."""
    suffix = source.suffix.lower()
    if suffix == ".ply":
        _check_ply(source, max_faces)
    elif suffix == ".obj":
        return _check_obj(source, max_faces)
    elif suffix == ".gltf":
        doc = _gltf_json(source)
        _check_gltf_refs(source, doc)
        _check_embedded_images(source, doc, None)
    elif suffix == ".glb":
        doc = _glb_json(source)
        _check_gltf_refs(source, doc)
        _check_embedded_images(source, doc, glb_bin_offset(source))
    return []


def check_face_count(name: str, faces: int, max_faces: int) -> None:
    """SpaceError when a mesh has more faces than `max_faces`."""
    if faces > max_faces:
        raise SpaceError(
            f"{name}: {faces:,} faces, more than the limit of {max_faces:,}; decimate the mesh first"
        )


def check_reference(owner: Path, ref: str, what: str) -> Path:
    """The file `ref` (named inside `owner`) under owner's folder; SpaceError for absolute or '..' paths."""
    clean = unquote(ref.strip().strip('"')).replace("\\", "/")
    if clean.startswith("/") or re.match(r"^[A-Za-z]:", clean) or clean.startswith("file:"):
        raise SpaceError(
            f"{owner.name}: {what} {ref!r} is an absolute path; name it relative to the mesh and include it"
        )
    if ".." in PurePosixPath(clean).parts:
        raise SpaceError(f"{owner.name}: {what} {ref!r} climbs out of the mesh's folder ('..'); refusing it")
    return owner.parent / clean


# ---------------------------------------------------------------------------------------------- PLY


def _check_ply(source: Path, max_faces: int) -> None:
    name = source.name
    with open(source, "rb") as f:
        header = f.read(MAX_HEADER_BYTES)
        end = header.find(b"end_header")
        if not header.startswith(b"ply"):
            return  # not a PLY at all: trimesh's own error is clear enough
        if end < 0:
            raise SpaceError(
                f"{name}: no 'end_header' in the first {MAX_HEADER_BYTES:,} bytes: not a readable PLY mesh"
            )
        lines = header[:end].splitlines()
        counts = _ply_counts(name, lines)
        check_face_count(name, counts.get("face", 0), max_faces)
        if counts.get("vertex", 0) > MAX_VERTICES:
            raise SpaceError(
                f"{name}: {counts['vertex']:,} vertices, more than the limit of {MAX_VERTICES:,}"
            )
        if not any(ln.strip() == b"format ascii 1.0" for ln in lines):
            return  # binary: trimesh checks the data length against the header
        f.seek(end + len(b"end_header"))
        f.readline()
        rows = sum(1 for ln in f if ln.strip())
    expected = sum(counts.values())
    if rows < expected:
        raise SpaceError(
            f"{name}: the file is truncated: its header declares {expected:,} element lines "
            f"({', '.join(f'{n} {c:,}' for n, c in counts.items())}) but only {rows:,} follow"
        )


def _ply_counts(name: str, lines: list[bytes]) -> dict[str, int]:
    """Each element's count as the PLY readers take it: Python's int() of the token, so '+4000000000' and
    '4_000_000_000' count in full; a negative count is refused, a token int() refuses is trimesh's to
    judge."""
    counts: dict[str, int] = {}
    for line in lines:
        m = _PLY_ELEMENT.match(line.strip())
        if m is None:
            continue
        element = m.group(1).decode("latin-1")
        try:
            count = int(m.group(2))
        except ValueError:
            continue
        if count < 0:
            raise SpaceError(f"{name}: its header declares {count:,} {element} elements: not a count")
        counts[element] = count
    return counts


# ---------------------------------------------------------------------------------------------- OBJ


def _check_obj(source: Path, max_faces: int) -> list[str]:
    # a plain file the fast path proves acceptable; anything else (every refusal and warning) is read below
    if source.stat().st_size <= MAX_BYTES:
        mtllibs = plain_obj_mtllibs(source.read_bytes(), max_faces, CHECKED_FROM_FACES)
        if mtllibs is not None:
            return _check_mtllibs(source, mtllibs)
    return _check_obj_lines(source, max_faces)


def _check_obj_lines(source: Path, max_faces: int) -> list[str]:
    """_check_obj line by line: the file streamed, every refusal and warning named."""
    name = source.name
    vertices = faces = 0
    mtllibs: list[str] = []
    sample = FaceSample()
    last = ""
    with open(source, encoding="utf-8", errors="replace", newline="") as f:
        for lineno, line in enumerate(f, 1):
            last = line
            if line.startswith("v "):  # most lines of a big scan: counted without splitting
                vertices += 1
                continue
            head, _, rest = line.lstrip().partition(" ")
            if "\t" in head:  # tab-separated statement
                head, _, rest = line.lstrip().partition("\t")
            if head == "v":
                vertices += 1
            elif head == "f":
                faces += 1
                if faces > max_faces:
                    check_face_count(name, faces, max_faces)
                sample.add(_check_face_refs(name, lineno, rest, vertices))
                if faces == CHECKED_FROM_FACES:  # enough to judge: refused here, before the rest is read
                    degenerate_refusal(source, sample)
            elif head == "mtllib" and rest.strip():
                mtllibs.append(rest.strip())
    if last and not last.endswith("\n") and not _complete_obj_line(last):
        raise SpaceError(
            f"{name}: the file is truncated: its last line {last[:80]!r} stops mid-statement; "
            "upload the whole file"
        )
    if faces == 0 and vertices > 0:
        raise SpaceError(f"{name}: {vertices:,} vertices but no faces; a triangle mesh is needed")
    warnings = _check_mtllibs(source, mtllibs)
    # whole, but exporters end with a newline: maybe cut at a token's end
    if last and not last.endswith("\n"):
        warnings.append(f"the last line {last[:80]!r} has no newline: the file may be truncated")
    return warnings


def _check_face_refs(name: str, lineno: int, rest: str, vertices: int) -> tuple[int, ...]:
    """The face's vertex indices (1-based, negative ones resolved); SpaceError for one that does not exist."""
    resolved = []
    for tok in rest.split():
        head = tok.split("/", 1)[0]
        if not head.lstrip("-").isdigit():
            continue  # malformed tokens are trimesh's to judge
        i = int(head)
        if i > vertices or i == 0 or -i > vertices:
            raise SpaceError(
                f"{name}: face on line {lineno} refers to vertex {i} but only {vertices:,} "
                "vertices come before it: the file is truncated or corrupt"
            )
        resolved.append(i if i > 0 else vertices + 1 + i)
    return tuple(resolved)


def _complete_obj_line(line: str) -> bool:
    """Whether a last line without a newline is a whole statement (not cut mid-token)."""
    fields = line.split()
    if not fields or fields[0] not in _OBJ_MIN_FIELDS:
        return True
    args = fields[1:]
    if len(args) < _OBJ_MIN_FIELDS[fields[0]]:
        return False
    if fields[0] == "f":
        return all(_OBJ_REF.match(a) for a in args)
    try:
        [float(a) for a in args]
    except ValueError:
        return False
    return True


def _check_mtllibs(obj: Path, mtllibs: list[str]) -> list[str]:
    warnings = []
    for ref in mtllibs:
        mtl = check_reference(obj, ref, "material library")
        if not mtl.is_file():
            warnings.append(f"material library {ref!r} is missing: the mesh renders untextured")
            continue
        try:
            text = read_confined(mtl, obj).decode("utf-8", errors="replace")
        except ReferenceRefused as e:
            raise SpaceError(f"{obj.name}: material library {e}") from None
        for line in text.splitlines():
            if m := _MTL_MAP.match(line):
                tex = check_reference(mtl, m.group(2), "texture")
                if not tex.is_file():
                    raise SpaceError(
                        f"{mtl.name}: texture {m.group(2)!r} is missing: include it beside the "
                        f"mesh (in the .zip), or remove the {m.group(1)} line to render untextured"
                    )
    return warnings


# ---------------------------------------------------------------------------------------------- glTF


def _gltf_json(source: Path) -> dict[str, object]:
    # read whatever its size (embedded data: buffers make big ones): skipping a big file would skip its
    # references
    try:
        doc = json.loads(source.read_bytes())
    except (ValueError, UnicodeDecodeError) as e:
        raise SpaceError(f"{source.name}: not valid glTF JSON ({e})") from None
    except RecursionError:  # json's decoder recurses once per nesting level
        raise SpaceError(f"{source.name}: not valid glTF JSON (nested too deep)") from None
    return doc if isinstance(doc, dict) else {}


def _glb_json(source: Path) -> dict[str, object]:
    name = source.name
    size = source.stat().st_size
    with open(source, "rb") as f:
        head = f.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            raise SpaceError(f"{name}: not a GLB file (no glTF header)")
        _magic, _version, length, chunk_len, chunk_type = struct.unpack("<4sIIII", head)
        if length > size:
            raise SpaceError(
                f"{name}: the file is truncated or corrupt: its header declares {length:,} bytes, "
                f"it has {size:,}"
            )
        if chunk_type != 0x4E4F534A:
            return {}  # no JSON chunk first: not a valid GLB, trimesh names it
        if chunk_len > size - 20:
            raise SpaceError(
                f"{name}: the file is truncated or corrupt: its JSON chunk runs past the end of the file"
            )
        raw = f.read(chunk_len)
    try:
        doc = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        raise SpaceError(f"{name}: the GLB's JSON chunk is corrupt ({e})") from None
    except RecursionError:
        raise SpaceError(f"{name}: the GLB's JSON chunk is corrupt (nested too deep)") from None
    return doc if isinstance(doc, dict) else {}


def _check_embedded_images(source: Path, doc: dict[str, object], bin_offset: int | None) -> None:
    problem = embedded_refusal(source, doc, bin_offset)
    if problem is not None:
        raise SpaceError(f"{source.name}: {problem}")


def _check_gltf_refs(source: Path, doc: dict[str, object]) -> None:
    for kind in ("buffers", "images"):
        items = doc.get(kind)
        for item in items if isinstance(items, list) else []:
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and uri and not uri.startswith("data:"):
                ref = check_reference(source, uri, kind[:-1])
                if not ref.is_file():
                    raise SpaceError(
                        f"{source.name}: {kind[:-1]} {uri!r} is missing: include it beside the mesh"
                    )
