"""Spaces: upload (size limit, hostile archives), register from the store, list/get/delete, tenant
isolation."""

from __future__ import annotations

import io
import stat
import zipfile
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from services.core.db.models import Space
from tests.fixtures.api import Api, make_api


def upload(api: Api, filename: str, data: bytes, headers: dict[str, str] | None = None, **fields: str):  # type: ignore[no-untyped-def]
    return api.client.post(
        "/spaces", files={"file": (filename, data)}, data=fields,
        headers=headers if headers is not None else api.a.headers,
    )


def _zip(members: dict[str, bytes], *, symlinks: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for n, d in members.items():
            zf.writestr(n, d)
        for n, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(n)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, target)
    return buf.getvalue()


def _spaces_of(api: Api, owner: str) -> int:
    with api.session() as s:
        return int(s.scalar(select(func.count()).select_from(Space).where(Space.owner == owner)) or 0)


def test_upload_ply_validates_and_stores(api: Api, bunny: Path) -> None:
    r = upload(api, "bun_zipper_res2.ply", bunny.read_bytes(), unit_scale="1.0")
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["name"] == "bun_zipper_res2"
    assert body["face_count"] > 1000 and body["vertex_count"] > 500
    assert body["source_format"] == "ply" and body["has_semantics"] is False
    assert "segment_semantic" not in body["supported_cues"] and "rgb" in body["supported_cues"]
    (lo, hi) = body["bounds"]
    assert all(h > lo_ for lo_, h in zip(lo, hi, strict=True))
    assert r.headers["location"] == f"/spaces/{body['id']}"
    assert api.store.exists(body["source_key"]) and body["source_key"].startswith(f"spaces/{body['id']}/")
    assert (
        api.client.get(f"/spaces/{body['id']}", headers=api.a.headers).json()["checksum"] == body["checksum"]
    )


def test_upload_textured_zip(api: Api, banana_dir: Path) -> None:
    data = _zip(
        {p.name: p.read_bytes() for p in banana_dir.iterdir() if p.suffix in (".obj", ".mtl", ".png")}
    )
    r = upload(api, "banana.zip", data, name="banana", up_axis="+z")
    assert r.status_code == 201, r.text
    assert r.json()["has_texture"] is True and r.json()["up_axis"] == "+z"


def test_name_conflict_and_bad_fields(api: Api, bunny: Path) -> None:
    assert upload(api, "b.ply", bunny.read_bytes(), name="same").status_code == 201
    r = upload(api, "b.ply", bunny.read_bytes(), name="same")
    assert r.status_code == 409 and "already exists" in r.json()["detail"]
    r = upload(api, "b.ply", bunny.read_bytes(), name="../evil")
    assert r.status_code == 422 and "name" in r.json()["detail"]
    r = upload(api, "b.ply", bunny.read_bytes(), unit_scale="nan")
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "unit_scale"]
    r = upload(api, "b.ply", bunny.read_bytes(), up_axis="sideways")
    assert r.status_code == 422 and "up_axis" in r.json()["detail"]
    # the same name is free for another tenant
    assert upload(api, "b.ply", bunny.read_bytes(), headers=api.b.headers, name="same").status_code == 201


NAN_OBJ = b"v 0 0 0\nv 1 0 0\nv nan nan nan\nf 1 2 3\n"
EMPTY_PLY = (
    b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
    b"element face 0\nproperty list uchar int vertex_indices\nend_header\n"
)
TRI_PLY = (
    b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
)

# one bad vertex among good ones: trimesh's vertex merging would silently fold it into another vertex
NAN_PLY = (
    b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    b"element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    b"0 0 0\n1 0 0\n0 1 0\nnan 0 1\n3 0 1 2\n3 0 1 3\n"
)


def _bomb() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        zf.writestr("scan.ply", TRI_PLY)
        zf.writestr("padding.bin", b"\0" * (40 * 1024 * 1024))  # 40 MiB that deflate to ~40 KiB
    return buf.getvalue()


HOSTILE: dict[str, tuple[str, Any, str | tuple[str, ...]]] = {
    "traversal": ("t.zip", lambda: _zip({"../../evil.ply": TRI_PLY}), "climbs out"),
    "absolute": ("a.zip", lambda: _zip({"/etc/evil.ply": TRI_PLY}), "absolute"),
    "symlink": (
        "s.zip", lambda: _zip({"scan.ply": TRI_PLY}, symlinks={"link.ply": "/etc/passwd"}), "symbolic link",
    ),
    "zip_bomb": ("bomb.zip", _bomb, "zip bomb"),
    "not_a_zip": ("fake.zip", lambda: b"this is not a zip archive at all" * 10, "not a readable zip"),
    "empty_mesh": ("empty.ply", lambda: EMPTY_PLY, "empty"),
    "nan_vertices": ("nan.obj", lambda: NAN_OBJ, ("nan", "degenerate")),
    "some_nan_vertices": ("nan.ply", lambda: NAN_PLY, ("nan",)),
    "no_mesh_in_zip": ("docs.zip", lambda: _zip({"README.txt": b"hello"}), "no mesh"),
    "two_meshes": ("two.zip", lambda: _zip({"a.ply": TRI_PLY, "b.ply": TRI_PLY}), "exactly one"),
    "unsupported_type": ("notes.txt", lambda: b"just text", "unsupported"),
    "garbage_ply": (
        "junk.ply", lambda: b"ply\nformat binary_little_endian 1.0\nelement vertex 99999\n", "mesh",
    ),
    "dot_dot_name": ("...", lambda: TRI_PLY, "extension"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_uploads_are_refused_and_nothing_is_stored(api: Api, case: str) -> None:
    filename, make, needles = HOSTILE[case]
    r = upload(api, filename, make())
    assert 400 <= r.status_code < 500, (case, r.status_code, r.text)
    needles = (needles,) if isinstance(needles, str) else needles
    assert any(n.lower() in r.json()["detail"].lower() for n in needles), (case, r.json()["detail"])
    assert _spaces_of(api, api.a.name) == 0
    assert list(api.store.list("spaces/")) == []
    assert api.client.get("/health").status_code == 200  # still serving


def test_upload_errors_without_a_usable_form(api: Api) -> None:
    r = api.client.post("/spaces", json={"file": "x"}, headers=api.a.headers)
    assert r.status_code == 415 and "multipart" in r.json()["detail"]
    r = api.client.post(
        "/spaces", data={"name": "x"}, files={"other": ("x.ply", b"1")}, headers=api.a.headers
    )
    assert r.status_code == 422 and "'other'" in r.json()["detail"]
    r = upload(api, "empty.ply", b"")
    assert r.status_code == 422 and "empty" in r.json()["detail"]
    r = upload(api, "noext", b"abc")
    assert r.status_code == 422 and "extension" in r.json()["detail"]
    body = b"--XX\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.ply\"\r\n\r\nply\nfor"
    r = api.client.post(
        "/spaces", content=body, headers={**api.a.headers, "Content-Type": "multipart/form-data; boundary=XX"}
    )
    assert r.status_code == 400 and "incomplete" in r.json()["detail"]


def test_upload_over_the_limit_is_413(pg_url: str, local_store, bunny: Path) -> None:  # type: ignore[no-untyped-def]
    with make_api(pg_url, local_store, upload_max_bytes=10_000) as api:
        data = bunny.read_bytes()
        assert len(data) > 10_000
        r = upload(api, "bunny.ply", data)
        assert r.status_code == 413 and "10000 bytes" in r.json()["detail"]

        # chunked body without Content-Length: refused while streaming
        def chunks():  # type: ignore[no-untyped-def]
            yield b'--BB\r\nContent-Disposition: form-data; name="file"; filename="big.ply"\r\n\r\n'
            for _ in range(40):
                yield b"x" * 1000
            yield b"\r\n--BB--\r\n"

        r = api.client.post(
            "/spaces",
            content=chunks(),
            headers={**api.a.headers, "Content-Type": "multipart/form-data; boundary=BB"},
        )
        assert r.status_code == 413, r.text
        assert list(api.store.list("spaces/")) == [] and _spaces_of(api, api.a.name) == 0


def test_register_staged_object(api: Api, bunny: Path) -> None:
    key = f"uploads/{api.a.name}/scans/bunny.ply"
    api.store.put_file(key, bunny)
    r = api.client.post("/spaces/register", json={"key": key, "name": "staged"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    assert r.json()["name"] == "staged" and r.json()["source_key"].startswith("spaces/")
    assert api.store.exists(key)  # the staged object is kept
    # another tenant cannot register it: outside its staging area
    r = api.client.post("/spaces/register", json={"key": key}, headers=api.b.headers)
    assert r.status_code == 422 and "staging area" in r.json()["detail"]
    r = api.client.post(
        "/spaces/register", json={"key": f"uploads/{api.a.name}/nope.ply"}, headers=api.a.headers
    )
    assert r.status_code == 404
    r = api.client.post("/spaces/register", json={"key": "../x"}, headers=api.a.headers)
    assert r.status_code == 422
    r = api.client.post("/spaces/register", json={"key": key, "unit_scale": "3"}, headers=api.a.headers)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "unit_scale"]  # JSON: a number
    r = api.client.post("/spaces/register", json={}, headers=api.a.headers)
    assert r.status_code == 422 and "exactly one" in r.json()["detail"]
    r = api.client.post("/spaces/register", json={"uri": "s3://elsewhere/x.ply"}, headers=api.a.headers)
    assert r.status_code == 422 and "not in this service's object store" in r.json()["detail"]


def test_list_get_delete_and_isolation(api: Api, bunny: Path) -> None:
    data = bunny.read_bytes()
    ids = [upload(api, "b.ply", data, name=f"s{i}").json()["id"] for i in range(3)]
    r = api.client.get("/spaces?limit=2&offset=0", headers=api.a.headers)
    assert r.status_code == 200
    page = r.json()
    assert page["total"] == 3 and page["limit"] == 2 and [s["id"] for s in page["items"]] == ids[::-1][:2]
    page2 = api.client.get("/spaces?limit=2&offset=2", headers=api.a.headers).json()
    assert [s["id"] for s in page2["items"]] == [ids[0]]
    # tenant b sees none of them: 404, not 403
    assert api.client.get("/spaces", headers=api.b.headers).json()["total"] == 0
    assert api.client.get(f"/spaces/{ids[0]}", headers=api.b.headers).status_code == 404
    assert api.client.delete(f"/spaces/{ids[0]}", headers=api.b.headers).status_code == 404
    # delete
    key = api.client.get(f"/spaces/{ids[0]}", headers=api.a.headers).json()["source_key"]
    assert api.client.delete(f"/spaces/{ids[0]}", headers=api.a.headers).status_code == 204
    assert not api.store.exists(key)
    assert api.client.get(f"/spaces/{ids[0]}", headers=api.a.headers).status_code == 404
    # a space used by a job cannot be deleted
    r = api.client.post(
        "/jobs", json={"space_ids": [ids[1]], "spec": {"cues": ["rgb"]}}, headers=api.a.headers
    )
    assert r.status_code == 201, r.text
    r = api.client.delete(f"/spaces/{ids[1]}", headers=api.a.headers)
    assert r.status_code == 409 and str(r.json()["detail"]).startswith(f"space {ids[1]} is used by job")
    assert api.client.get("/spaces?limit=0", headers=api.a.headers).status_code == 422


def test_upload_reports_the_detected_frame_and_refuses_bad_units(api: Api, tmp_path: Path) -> None:
    """A room in centimetres stored -Y up: the read model says up, method, confidence and the units chosen."""
    import numpy as np
    import trimesh

    from tests.fixtures import scenes

    room = scenes.furnished_room().apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    )
    room.apply_scale(100.0)
    data = room.export(file_type="ply")
    r = upload(api, "room.ply", data)
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["unit_scale"] == 0.01
    frame = body["frame"]
    assert frame["up"]["method"] == "floor" and frame["up"]["source_direction"] == [0.0, -1.0, 0.0]
    assert frame["up"]["confidence"] in ("high", "low") and frame["up"]["floor_area_m2"] > 20
    assert frame["units"]["unit"] == "centimetres"
    assert api.client.get(f"/spaces/{body['id']}", headers=api.a.headers).json()["frame"] == frame
    r = upload(api, "room.ply", data, name="r2", unit_scale="feet")
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "unit_scale"]
    ball = trimesh.creation.icosphere(subdivisions=1).apply_scale(300.0).export(file_type="ply")  # 600 units
    r = upload(api, "ball.ply", ball)
    assert r.status_code == 422 and "unit_scale" in r.json()["detail"]
    assert _spaces_of(api, api.a.name) == 1


def _racing_deletes(client: Any, path: str, headers: dict[str, str], n: int) -> list[int]:
    """The status codes of `n` DELETEs of `path` released together from `n` threads."""
    import threading

    start = threading.Barrier(n)
    codes: list[int] = []

    def delete() -> None:
        start.wait()
        codes.append(client.delete(path, headers=headers).status_code)

    threads = [threading.Thread(target=delete) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return codes


def test_concurrent_deletes_of_one_space_answer_204_exactly_once(api: Api, bunny: Path) -> None:
    import httpx

    from tests.fixtures.api import live_server

    data = bunny.read_bytes()
    ids = [upload(api, "b.ply", data, name=f"race{i}").json()["id"] for i in range(4)]
    with live_server(api.app) as base, httpx.Client(base_url=base, timeout=60) as client:
        for space_id in ids:
            codes = _racing_deletes(client, f"/spaces/{space_id}", api.a.headers, 6)
            assert sorted(codes) == [204] + [404] * 5, (space_id, codes)
    with api.session() as s:
        assert s.scalar(select(func.count()).select_from(Space).where(Space.id.in_(ids))) == 0
