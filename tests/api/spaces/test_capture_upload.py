"""Uploading a scan with its capture as two multipart parts ('file' and a 'capture' .zip): validated together,
stored as one object with the scan, and refused with a clear 422 when the capture part is not a zip."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

from services.core.db.models import Space
from tests.fixtures.api import Api
from tests.fixtures.captures import toy_frames, write_transforms


def _capture_zip(tmp_path: Path) -> bytes:
    folder = tmp_path / "cap"
    folder.mkdir()
    write_transforms(folder, toy_frames(3))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(folder).as_posix())
    return buf.getvalue()


def test_upload_scan_and_capture_parts(api: Api, bunny: Path, tmp_path: Path) -> None:
    r = api.client.post("/spaces", files=[("file", ("bunny.ply", bunny.read_bytes())),
                                          ("capture", ("capture.zip", _capture_zip(tmp_path)))],
                        data={"name": "bunny_cap", "up_axis": "+y"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["frame"]["capture"]["format"] == "transforms" and body["frame"]["capture"]["frames"] == 3
    with api.session() as s:
        key = s.get(Space, body["id"]).source_key
    stored = api.store.get_bytes(key)
    with zipfile.ZipFile(io.BytesIO(stored)) as zf:  # one object: the scan and its photos
        names = set(zf.namelist())
    assert (
        "bunny.ply" in names
        and "capture/transforms.json" in names
        and "capture/images/frame_00001.png" in names
    )


def test_capture_part_must_be_a_zip(api: Api, bunny: Path) -> None:
    r = api.client.post("/spaces", files=[("file", ("bunny.ply", bunny.read_bytes())),
                                          ("capture", ("poses.json", b"[]"))], headers=api.a.headers)
    assert r.status_code == 422 and "capture" in r.text
    r = api.client.post("/spaces", files=[("file", ("bunny.ply", bunny.read_bytes())),
                                          ("capture", ("a.zip", b"not a zip"))], headers=api.a.headers)
    assert r.status_code == 422 and "zip" in r.text


def test_upload_names_each_photo_over_the_budget_and_keeps_the_others(api: Api, bunny: Path,
                                                                     tmp_path: Path) -> None:
    from services.core.ingest.capture.photos import MAX_PHOTO_PIXELS
    from tests.fixtures.captures import write_colmap
    from tests.fixtures.hostile_corpus import png_declaring

    folder = tmp_path / "cap"
    folder.mkdir()
    frames = toy_frames(3)
    write_colmap(folder, frames)
    images = folder / "images"
    (images / f"{frames[0].name}.jpg").write_bytes(png_declaring(20000, 20000))  # past Pillow's limit
    (images / f"{frames[2].name}.jpg").write_bytes(png_declaring(9000, 9000))  # past ours
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(folder).as_posix())
    r = api.client.post("/spaces", files=[("file", ("bunny.ply", bunny.read_bytes())),
                                          ("capture", ("capture.zip", buf.getvalue()))],
                        data={"name": "bunny_big_photos", "up_axis": "+y"}, headers=api.a.headers)
    assert r.status_code == 201, r.text
    capture = r.json()["frame"]["capture"]
    assert capture["frames"] == 1 and capture["problems"] == 2
    limit = f"more than the limit of {MAX_PHOTO_PIXELS:,}"
    for f in (frames[0], frames[2]):
        messages = capture["problem_messages"]
        assert any(f"photo {f.name}.jpg declares" in m and limit in m for m in messages), capture
