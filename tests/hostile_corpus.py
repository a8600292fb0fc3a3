"""A corpus of hostile scan files (issue 11, item 15): each must be refused with a clear message.

`HOSTILE_FILES[case] = (file name, builder, needles)`: the builder returns the bytes to upload (or to write
and pass to the CLI); the refusal's message must contain one of the needles (case-insensitive). The files
are built from a small valid mesh at test time, so the corpus needs no binary fixtures.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
from collections.abc import Callable

import numpy as np
import trimesh

Case = tuple[str, Callable[[], bytes], tuple[str, ...]]

TRI_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
_PNG = (  # a 1x1 PNG
    b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x01\x00\x00\x00\x01\x08\x02\x00\x00\x00\x90wS\xde\x00\x00"
    b"\x00\x0cIDATx\x9cc\xf8\xcf\xc0\x00\x00\x03\x01\x01\x00\xc9\xfe\x92\xef\x00\x00\x00\x00IEND\xaeB`\x82"
)


def mesh() -> trimesh.Trimesh:
    """A small closed mesh (an icosphere of 1280 faces, 1 m across)."""
    return trimesh.creation.icosphere(subdivisions=3, radius=0.5)


def _obj() -> bytes:
    return mesh().export(file_type="obj").encode()


def _ply(encoding: str) -> bytes:
    return bytes(mesh().export(file_type="ply", encoding=encoding))


def _glb() -> bytes:
    return bytes(mesh().export(file_type="glb"))


def _zip(members: dict[str, bytes], *, method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _corrupt_member(method: int) -> bytes:
    """A zip whose mesh member's data is damaged after the headers were written (bad CRC / bad deflate)."""
    data = bytearray(_zip({"scan.ply": _ply("ascii")}, method=method))
    start = 30 + len("scan.ply")  # local header + name: the member's data follows
    for i in range(start + 200, start + 260):
        data[i] ^= 0x5A
    return bytes(data)


def _textured_zip(map_line: str, *, with_texture: bool = False) -> bytes:
    obj = b"mtllib scan.mtl\nusemtl m\nvt 0 0\nvt 1 0\nvt 0 1\n" + TRI_OBJ.replace(b"f 1 2 3", b"f 1/1 2/2 3/3")
    members = {"scan.obj": obj, "scan.mtl": f"newmtl m\nKd 1 1 1\n{map_line}\n".encode()}
    if with_texture:
        members["tex.png"] = _PNG
    return _zip(members)


def _gltf_zip(uri: str) -> bytes:
    doc = json.loads(bytes(mesh().export(file_type="gltf", embed_buffers=True)["model.gltf"]))
    doc["buffers"][0]["uri"] = uri
    return _zip({"scan.gltf": json.dumps(doc).encode()})


def _glb_external_image(uri: str) -> bytes:
    glb = bytearray(_glb())
    json_len = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(bytes(glb[20 : 20 + json_len]))
    doc["images"] = [{"uri": uri}]
    body = json.dumps(doc).encode()
    body += b" " * (-len(body) % 4)
    rest = bytes(glb[20 + json_len :])
    out = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(body) + len(rest)) + struct.pack("<II", len(body), 0x4E4F534A)
    return out + body + rest


def _truncated_obj_mid_token() -> bytes:
    data = _obj()
    cut = data.rindex(b"\nf ") + 4  # "f 12" of the last face: cut mid-statement
    return data[:cut]


def _face_past_the_end() -> bytes:
    return TRI_OBJ + b"f 1 2 99\n"


def _ply_declaring(faces: int) -> bytes:
    head = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        f"property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return head.encode() + np.zeros(9, dtype="<f4").tobytes() + b"\x03" + np.arange(3, dtype="<i4").tobytes()


def _ascii_ply(vertices: str, faces: str, n_vertices: int, n_faces: int) -> bytes:
    return (
        "ply\nformat ascii 1.0\n"
        f"element vertex {n_vertices}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {n_faces}\nproperty list uchar int vertex_indices\nend_header\n{vertices}{faces}"
    ).encode()


HOSTILE_FILES: dict[str, Case] = {
    # archives
    "zip_bad_crc": ("crc.zip", lambda: _corrupt_member(zipfile.ZIP_STORED), ("corrupt",)),
    "zip_corrupt_deflate": ("deflate.zip", lambda: _corrupt_member(zipfile.ZIP_DEFLATED), ("corrupt",)),
    "zip_cut_in_half": ("half.zip", lambda: _zip({"scan.ply": _ply("binary")})[:2000], ("not a readable zip",)),
    # OBJ
    "obj_truncated_mid_token": ("cut.obj", _truncated_obj_mid_token, ("truncated",)),
    "obj_face_past_the_end": ("past.obj", _face_past_the_end, ("truncated or corrupt",)),
    "obj_vertices_no_faces": ("cloud.obj", lambda: b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", ("no faces",)),
    "obj_nan_vertex": ("nan.obj", lambda: TRI_OBJ.replace(b"v 0 0 1", b"v 0 nan 1"), ("nan",)),
    "obj_inf_vertex": ("inf.obj", lambda: TRI_OBJ.replace(b"v 0 0 1", b"v 0 inf 1"), ("infinite", "nan")),
    "obj_degenerate_faces_only": ("flat.obj", lambda: b"v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\nf 1 1 2\n",
                                  ("degenerate", "no faces")),
    "obj_garbage": ("junk.obj", lambda: bytes(range(256)) * 40, ("no vertices", "mesh")),
    # PLY
    "ply_ascii_truncated": ("cut.ply", lambda: _ply("ascii")[: len(_ply("ascii")) * 2 // 3], ("truncated",)),
    "ply_binary_truncated": ("cutb.ply", lambda: _ply("binary")[: len(_ply("binary")) // 2], ("could not read",)),
    "ply_over_limit_faces": ("huge.ply", lambda: _ply_declaring(10**12), ("more than the limit",)),
    "ply_inf_vertex": ("inf.ply", lambda: _ascii_ply("0 0 0\n1 0 0\n0 1 0\n0 0 inf\n", "3 0 1 2\n3 0 1 3\n", 4, 2),
                       ("nan or infinite",)),
    "ply_zero_faces_declared": ("none.ply", lambda: _ascii_ply("", "", 0, 0), ("empty", "no vertices")),
    "ply_only_degenerate_faces": ("deg.ply", lambda: _ascii_ply("0 0 0\n1 1 1\n2 2 2\n", "3 0 1 2\n", 3, 1),
                                  ("degenerate", "no faces")),
    "ply_huge_header": ("hdr.ply", lambda: b"ply\nformat ascii 1.0\n" + b"comment " + b"x" * 3_000_000 + b"\n",
                        ("end_header",)),
    # GLB / glTF
    "glb_truncated": ("cut.glb", lambda: _glb()[: len(_glb()) // 2], ("truncated",)),
    "glb_not_gltf": ("fake.glb", lambda: b"\x89PNG\r\n\x1a\n" + bytes(2000), ("not a glb",)),
    "glb_external_image_absolute": ("abs.glb", lambda: _glb_external_image("/etc/passwd"), ("absolute",)),
    "gltf_buffer_dotdot": ("dd.zip", lambda: _gltf_zip("../../secret.bin"), ("climbs out",)),
    "gltf_buffer_missing": ("nobuf.zip", lambda: _gltf_zip("missing.bin"), ("missing",)),
    # textures
    "texture_absolute_path": ("abs.zip", lambda: _textured_zip("map_Kd /etc/passwd"), ("absolute",)),
    "texture_dotdot_path": ("dd.zip", lambda: _textured_zip("map_Kd ../../../etc/shadow.png"), ("climbs out",)),
    "texture_missing": ("miss.zip", lambda: _textured_zip("map_Kd nowhere.png"), ("missing",)),
    "mtllib_absolute_path": ("mtl.obj", lambda: b"mtllib /etc/passwd\n" + TRI_OBJ, ("absolute",)),
    # wrong extensions
    "ply_named_obj": ("scan.obj", lambda: _ply("binary"), ("no vertices", "mesh", "truncated")),
    "obj_named_glb": ("scan.glb", lambda: TRI_OBJ, ("not a glb",)),
    "text_file": ("notes.txt", lambda: b"hello", ("unsupported file type",)),
    "no_extension": ("scan", lambda: TRI_OBJ, ("extension", "unsupported file type")),
}

# the same mesh files, valid: the corpus's controls (a refusal must come from the damage, not the format)
VALID_FILES: dict[str, tuple[str, Callable[[], bytes]]] = {
    "obj": ("ok_obj.obj", _obj),
    "ply_ascii": ("ok_ascii.ply", lambda: _ply("ascii")),
    "ply_binary": ("ok_binary.ply", lambda: _ply("binary")),
    "glb": ("ok_glb.glb", _glb),
    "textured_zip": ("tex.zip", lambda: _textured_zip("map_Kd tex.png", with_texture=True)),
}
