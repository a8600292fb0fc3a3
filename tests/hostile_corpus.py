"""A corpus of hostile scan files (issues 11 and 19): each must be refused with a clear message.

`HOSTILE_FILES[case] = (file name, builder, needles)`: the builder returns the bytes to upload (or to write
and pass to the CLI); the refusal's message must contain one of the needles (case-insensitive). The files
are built from a small valid mesh at test time, so the corpus needs no binary fixtures.

Many cases name files outside the upload: `secret_files()` are such files on the server (a red PNG and a
material library pointing at it, in a folder of the temp dir); the tests watch them with inotify and
assert no entry point ever opens them. `HOSTILE_FOLDERS[case] = (builder(folder), needles)` are scans that
need a file system (symbolic links inside a folder pointing out of it), for the CLI and the folder store.
"""

from __future__ import annotations

import io
import json
import os
import struct
import tempfile
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

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
                        ("end_header", "expands")),
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

# ------------------------------------------------------------------------------ issue 19: files outside the upload

SECRET_DIR = Path(tempfile.gettempdir()) / "omnidata-hostile-secrets"
SECRET_RGB = (255, 0, 17)  # a colour no test scene renders: its pixels in an output would show a leak
UV_FACES = b"vt 0 0\nvt 1 0\nvt 0 1\n" + TRI_OBJ.replace(b"f 1 2 3", b"f 1/1 2/2 3/3")


def secret_files() -> dict[str, Path]:
    """Files on the server no scan may read: a red PNG, a material library naming it, an OBJ (made once)."""
    from PIL import Image

    SECRET_DIR.mkdir(exist_ok=True)
    files = {"png": SECRET_DIR / "secret.png", "mtl": SECRET_DIR / "evil_abs.mtl", "obj": SECRET_DIR / "outside.obj"}
    if not files["png"].exists():
        Image.new("RGB", (16, 16), SECRET_RGB).save(files["png"])
    if not files["mtl"].exists():  # written once: a test watching them must see no open of its own making
        files["mtl"].write_text(f"newmtl m\nKd 1 1 1\nmap_Kd {files['png']}\n")
    if not files["obj"].exists():
        files["obj"].write_bytes(b"mtllib evil_abs.mtl\nusemtl m\n" + UV_FACES)
    return files


def _secret(kind: str = "png") -> str:
    return str(secret_files()[kind])


def _climbing(kind: str = "png") -> str:
    """The secret named by enough '../' to reach / from any folder, then its absolute path."""
    return "../" * 16 + _secret(kind).lstrip("/")


def _obj_with(head: str) -> bytes:
    return head.encode() + b"\nusemtl m\n" + UV_FACES


def _obj_mtl_zip(obj_head: str, mtl_body: str, extra: dict[str, bytes] | None = None) -> bytes:
    return _zip({"scan.obj": _obj_with(obj_head), "evil.mtl": f"newmtl m\nKd 1 1 1\n{mtl_body}\n".encode(),
                 **(extra or {})})


def _gltf_doc() -> dict:
    return json.loads(bytes(mesh().export(file_type="gltf", embed_buffers=True)["model.gltf"]))


def _gltf_image(uri: str) -> bytes:
    doc = _gltf_doc()
    doc["images"] = [{"uri": uri}]
    doc["textures"] = [{"source": 0}]
    doc["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]
    return _zip({"scan.gltf": json.dumps(doc).encode()})


def _ply_texture_file(name: str) -> bytes:
    head = (
        "ply\nformat ascii 1.0\n"
        f"comment TextureFile {name}\n"
        "element vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 4\nproperty list uchar int vertex_indices\nproperty list uchar float texcoord\nend_header\n"
    )
    uv = "6 0 0 1 0 0 1"
    body = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n" + "".join(f"3 {f} {uv}\n" for f in ("0 1 2", "0 1 3", "0 2 3", "1 2 3"))
    return (head + body).encode()


def png_declaring(width: int, height: int) -> bytes:
    """A tiny PNG whose header declares width x height pixels (its data is one row: never decodable)."""
    png = bytearray(_PNG)
    ihdr = struct.pack(">II", width, height) + bytes(png[24:29])
    png[16:29] = ihdr
    png[29:33] = struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return bytes(png)


def _glb_embedded_png(png: bytes) -> bytes:
    """The valid GLB with `png` embedded in its binary chunk as image 0 (a buffer view)."""
    glb = _glb()
    json_len = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20 : 20 + json_len])
    bin_len = struct.unpack_from("<I", glb, 20 + json_len)[0]
    binary = glb[28 + json_len : 28 + json_len + bin_len] + png
    binary += b"\0" * (-len(binary) % 4)
    doc.setdefault("bufferViews", []).append({"buffer": 0, "byteOffset": bin_len, "byteLength": len(png)})
    doc["images"] = [{"bufferView": len(doc["bufferViews"]) - 1, "mimeType": "image/png"}]
    doc["buffers"][0]["byteLength"] = len(binary)
    body = json.dumps(doc).encode()
    body += b" " * (-len(body) % 4)
    total = 12 + 8 + len(body) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(body), 0x4E4F534A) + body
            + struct.pack("<II", len(binary), 0x004E4942) + binary)


def _zip_with_symlink() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("scan.obj", _obj_with("mtllib evil.mtl"))
        link = zipfile.ZipInfo("evil.mtl")
        link.external_attr = (0o120777 << 16)  # a symbolic link to the secret library
        zf.writestr(link, _secret("mtl"))
    return buf.getvalue()


_MTL_FIELDS = ("map_Ka", "map_Ks", "map_Ns", "map_d", "map_bump", "bump", "disp", "decal", "norm", "map_Pr")

HOSTILE_FILES.update({
    # the three uploads of the issue: each made the renderer read a server image
    "obj_comment_mtllib_absolute_texture": (
        "cmt.zip", lambda: _obj_mtl_zip("# mtllib evil.mtl", f"map_Kd {_secret()}"), ("absolute",)),
    "obj_comment_mtllib_dotdot_texture": (
        "cmtdd.zip", lambda: _obj_mtl_zip("# mtllib evil.mtl", f"map_Kd {_climbing()}"), ("climbs out",)),
    "obj_object_name_mtllib_absolute": ("oname.obj", lambda: _obj_with(f"o xmtllib {_secret('mtl')}"), ("absolute",)),
    # their relatives: wherever trimesh finds 'mtllib', however the name is spelled
    "obj_group_name_mtllib_dotdot": ("gname.obj", lambda: _obj_with(f"g xmtllib {_climbing('mtl')}"), ("climbs out",)),
    "obj_mtllib_in_vertex_comment": ("vc.obj", lambda: _obj_with(f"v 0 0 0 # mtllib {_secret('mtl')}"), ("absolute",)),
    "obj_mtllib_tab_absolute": ("tab.obj", lambda: _obj_with(f"mtllib\t{_secret('mtl')}"), ("absolute",)),
    "obj_mtllib_file_url": ("url.obj", lambda: _obj_with(f"mtllib file://{_secret('mtl')}"), ("absolute",)),
    "mtl_map_kd_percent_dotdot": (
        "pct.zip", lambda: _obj_mtl_zip("mtllib evil.mtl", "map_Kd " + "%2e%2e/" * 16 + _secret().lstrip("/")),
        ("climbs out",)),
    "mtl_map_kd_with_options_absolute": (
        "opt.zip", lambda: _obj_mtl_zip("mtllib evil.mtl", f"map_Kd -s 1 1 1 -o 0 0 0 {_secret()}"),
        ("absolute", "missing")),
    "mtl_map_kd_windows_drive": ("drive.zip", lambda: _obj_mtl_zip("# mtllib evil.mtl", "map_Kd C:\\secret.png"),
                                 ("absolute",)),
    **{f"mtl_{field.lower()}_absolute": (f"{field}.zip", (lambda f=field: _obj_mtl_zip("mtllib evil.mtl",
                                                                                    f"{f} {_secret()}")),
                                         ("absolute",)) for field in _MTL_FIELDS},
    "gltf_image_absolute": ("gimg.zip", lambda: _gltf_image(_secret()), ("absolute",)),
    "gltf_image_percent_dotdot": ("gpct.zip", lambda: _gltf_image("%2e%2e/" * 16 + _secret().lstrip("/")),
                                  ("climbs out",)),
    "gltf_image_file_url": ("gurl.zip", lambda: _gltf_image(f"file://{_secret()}"), ("absolute",)),
    "gltf_buffer_absolute": ("gbuf.zip", lambda: _gltf_zip(_secret()), ("absolute",)),
    "ply_texture_file_absolute": ("tex_abs.ply", lambda: _ply_texture_file(_secret()), ("absolute",)),
    "ply_texture_file_dotdot": ("tex_dd.ply", lambda: _ply_texture_file(_climbing()), ("climbs out",)),
    "zip_symlink_member": ("link.zip", _zip_with_symlink, ("symbolic link",)),
    # texture sizes, by what the header declares
    "texture_13000_png": ("big.zip", lambda: _obj_mtl_zip("mtllib evil.mtl", "map_Kd big.png",
                                                          {"big.png": png_declaring(13000, 13000)}),
                          ("more than the limit",)),
    "texture_30000_png_behind_comment": (
        "huge.zip", lambda: _obj_mtl_zip("# mtllib evil.mtl", "map_Kd big.png", {"big.png": png_declaring(30000, 30000)}),
        ("more than the limit",)),
    "ply_texture_file_13000_png": ("bigply.zip", lambda: _zip({"scan.ply": _ply_texture_file("big.png"),
                                                               "big.png": png_declaring(13000, 13000)}),
                                   ("more than the limit",)),
    "glb_embedded_30000_png": ("bigtex.glb", lambda: _glb_embedded_png(png_declaring(30000, 30000)),
                               ("more than the limit",)),
    "gltf_data_uri_13000_png": (
        "datauri.zip",
        lambda: _gltf_image("data:image/png;base64," + __import__("base64").b64encode(png_declaring(13000, 13000)).decode()),
        ("more than the limit",)),
    # a mesh its own packed zip would fail planning with: refused at upload by the same rule
    "obj_one_repeated_face_line": ("rep.obj", lambda: b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 300_000,
                                   ("expands",)),
})

# accepted: trimesh reads only map_Kd, so these names are never opened (the tests prove it with inotify)
ACCEPTED_UNREAD: dict[str, tuple[str, Callable[[], bytes]]] = {
    f"comment_mtllib_{field.lower()}": (f"{field}.zip", (lambda f=field: _obj_mtl_zip(
        "# mtllib evil.mtl", f"{f} {_secret()}"))) for field in _MTL_FIELDS
}


def _link(path: Path, target: Path) -> None:
    os.symlink(target, path)


def _folder_mtl_link(folder: Path) -> None:
    (folder / "scan.obj").write_bytes(_obj_with("mtllib evil.mtl"))
    _link(folder / "evil.mtl", secret_files()["mtl"])


def _folder_comment_mtl_link(folder: Path) -> None:
    (folder / "scan.obj").write_bytes(_obj_with("# mtllib evil.mtl"))
    _link(folder / "evil.mtl", secret_files()["mtl"])


def _folder_texture_link(folder: Path) -> None:
    (folder / "scan.obj").write_bytes(_obj_with("mtllib scan.mtl"))
    (folder / "scan.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    _link(folder / "tex.png", secret_files()["png"])


def _folder_texture_dir_link(folder: Path) -> None:
    (folder / "scan.obj").write_bytes(_obj_with("# mtllib scan.mtl"))
    (folder / "scan.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd textures/secret.png\n")
    _link(folder / "textures", SECRET_DIR)


def _folder_mesh_link(folder: Path) -> None:
    _link(folder / "scan.obj", secret_files()["obj"])


def _folder_ply_texture_link(folder: Path) -> None:
    (folder / "scan.ply").write_bytes(_ply_texture_file("tex.png"))
    _link(folder / "tex.png", secret_files()["png"])


def _folder_gltf_buffer_link(folder: Path) -> None:
    doc = _gltf_doc()
    doc["images"] = [{"uri": "img.png"}]
    (folder / "scan.gltf").write_text(json.dumps(doc))
    _link(folder / "img.png", secret_files()["png"])


HOSTILE_FOLDERS: dict[str, tuple[Callable[[Path], None], tuple[str, ...]]] = {
    "folder_mtl_symlink_out": (_folder_mtl_link, ("symbolic link",)),
    "folder_comment_mtllib_symlink_out": (_folder_comment_mtl_link, ("symbolic link",)),
    "folder_texture_symlink_out": (_folder_texture_link, ("symbolic link",)),
    "folder_textures_dir_symlink_out": (_folder_texture_dir_link, ("symbolic link",)),
    "folder_mesh_symlink_out": (_folder_mesh_link, ("symbolic link",)),
    "folder_ply_texture_symlink_out": (_folder_ply_texture_link, ("symbolic link",)),
    "folder_gltf_image_symlink_out": (_folder_gltf_buffer_link, ("symbolic link",)),
}

# the same mesh files, valid: the corpus's controls (a refusal must come from the damage, not the format)
VALID_FILES: dict[str, tuple[str, Callable[[], bytes]]] = {
    "obj": ("ok_obj.obj", _obj),
    "ply_ascii": ("ok_ascii.ply", lambda: _ply("ascii")),
    "ply_binary": ("ok_binary.ply", lambda: _ply("binary")),
    "glb": ("ok_glb.glb", _glb),
    "textured_zip": ("tex.zip", lambda: _textured_zip("map_Kd tex.png", with_texture=True)),
}
