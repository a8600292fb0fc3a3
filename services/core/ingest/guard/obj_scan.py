"""The OBJ pre-check's fast path: the whole file's lines judged at once with numpy over its bytes.

`mesh_checks._check_obj` reads an OBJ line by line in Python (~0.1 CPU-s for a 2.7 MB room scan, paid by
every `generate` and `plan` before the mesh is parsed). `plain_obj_mtllibs` reaches the same verdict for the
plain files exporters write, at a fraction of the cost, and answers only when it can prove the line-by-line
check would accept the file: it returns the material libraries that check would collect, or None, and then the
line-by-line check runs as before and gives its own answer (a refusal with its message, a warning). So every
refusal, and its wording, still comes from the one line-by-line reading.

It answers only for a file that:
- is at most MAX_BYTES and MAX_LINES, ASCII, made of printable characters, spaces, tabs and '\\n' only (no
  '\\r', no other whitespace Python's str.split would also split at), and ends with '\\n';
- has no line starting with a space or tab (statements start their line);
- has faces (fewer than `CHECKED_FROM_FACES`: bigger files are sampled for degenerate faces there, and at most
  `max_faces`) whose lines hold at most MAX_FACE_BYTES in all, of digits, '/', '-', spaces and tabs only;
- has face references that are each `[-]digits` (up to 18), optionally followed by '/' and more (no '-'
  there), and name a vertex that comes before the face (positive: at most the count so far; negative: at most
  that many back; never 0).
Under these rules a line's statement is the text before its first space or tab, as the line-by-line check
reads it, and its face references are the runs of characters between spaces and tabs.
"""

from __future__ import annotations

import numpy as np

# Past these the line-by-line check streams the file: the fast path holds it whole, with a few index arrays
# per line and per byte of its face lines (a hostile file of empty lines or one endless face stays cheap)
MAX_BYTES = 32 << 20
MAX_LINES = 2_000_000
MAX_FACE_BYTES = 8 << 20
_MAX_DIGITS = 18  # int64 holds any 18-digit number
_SPACE, _TAB, _NEWLINE, _SLASH, _MINUS = (ord(c) for c in " \t\n/-")


_PLAIN = bytes(range(0x20, 0x7F)) + b"\t\n"  # printable ASCII, tab, newline
_FACE_BODY = b"0123456789/- \t"  # what a plain face line holds past its 'f'


def plain_obj_mtllibs(data: bytes, max_faces: int, checked_from_faces: int) -> list[str] | None:
    """The `mtllib` references the line-by-line check would collect from the OBJ text `data`, when that check
    would accept the file; None when this fast path cannot tell (see the module docstring)."""
    if len(data) > MAX_BYTES or not data.endswith(b"\n") or data.count(b"\n") > MAX_LINES:
        return None
    if data.translate(None, _PLAIN):
        return None
    buf = np.frombuffer(data, dtype=np.uint8)
    ends = np.flatnonzero(buf == _NEWLINE)
    starts = np.concatenate(([0], ends[:-1] + 1))
    first = buf[starts]  # '\n' for an empty line
    if ((first == _SPACE) | (first == _TAB)).any():
        return None
    # the character after a line's first: a separator makes that first character a one-letter statement
    second = buf[np.minimum(starts + 1, len(buf) - 1)]
    one_letter = ((second == _SPACE) | (second == _TAB)) & (starts + 1 < ends)
    is_vertex = one_letter & (first == ord("v"))
    is_face = one_letter & (first == ord("f"))
    faces = int(is_face.sum())
    if faces == 0 or faces > max_faces or faces >= checked_from_faces:
        return None  # no faces, or over the limit, or sampled: the line-by-line check decides
    before = np.cumsum(is_vertex)[is_face]  # vertex lines before each face line
    if not _face_refs_exist(buf, starts[is_face], ends[is_face], before):
        return None
    return _mtllibs(data, starts[first == ord("m")], ends[first == ord("m")])


def _mtllibs(data: bytes, starts: np.ndarray, ends: np.ndarray) -> list[str]:
    """The references of the `mtllib` statements among the lines [starts, ends): the text past the first
    space or tab after the word, stripped (none when empty)."""
    refs = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        line = data[a:b]
        if line.startswith(b"mtllib") and line[6:7] in (b" ", b"\t") and line[7:].strip():
            refs.append(line[7:].strip().decode("ascii"))
    return refs


def _face_refs_exist(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, vertices: np.ndarray) -> bool:
    """Whether every reference of the face lines [starts, ends) is `[-]digits[/...]` and names one of the
    `vertices` (per line) that come before it."""
    # the face lines' bytes past their 'f' and its separator, one after another, each tagged with its line
    lengths = ends - starts - 2
    line_end = np.cumsum(lengths)
    if line_end[-1] > MAX_FACE_BYTES:
        return False
    # int32 indices: the file is at most MAX_BYTES
    pos = np.arange(int(line_end[-1]), dtype=np.int32) + np.repeat(
        (starts + 2 - (line_end - lengths)).astype(np.int32), lengths)
    line = np.repeat(np.arange(len(starts), dtype=np.int32), lengths)
    chars = buf[pos]
    if chars.tobytes().translate(None, _FACE_BODY):
        return False
    sep = (chars == _SPACE) | (chars == _TAB)
    # a reference starts where a non-separator follows a separator or its line's start
    after_sep = np.ones(len(chars), dtype=bool)
    after_sep[1:] = sep[:-1] | (line[1:] != line[:-1])
    begin = np.flatnonzero(~sep & after_sep)
    if len(begin) == 0:
        return True  # faces without references: the line-by-line check keeps them as empty faces
    first_digit = begin + (chars[begin] == _MINUS)
    # its number runs to the first '/' or separator, or to its line's end
    stops = np.append(np.flatnonzero(sep | (chars == _SLASH)), len(chars))
    number_end = np.minimum(stops[np.searchsorted(stops, first_digit)], line_end[line[begin]])
    count = number_end - first_digit
    if (count < 1).any() or (count > _MAX_DIGITS).any():
        return False
    # digits, '/', '-' and separators only: a '-' anywhere but a reference's start (inside its number, or
    # past its '/') is left to the line-by-line check
    minus = np.flatnonzero(chars == _MINUS)
    if len(minus) and not np.isin(minus, begin).all():
        return False
    value = np.zeros(len(begin), dtype=np.int64)
    for k in range(int(count.max())):
        more = k < count
        value[more] = value[more] * 10 + (chars[first_digit[more] + k] - ord("0")).astype(np.int64)
    index = np.where(first_digit > begin, -value, value)
    have = vertices[line[begin]]
    return bool(((index != 0) & (index <= have) & (-index <= have)).all())
