"""Cue registry and file encodings: every catalog cue is registered, files have the documented format."""

from __future__ import annotations

import io
import json
import tempfile
import zlib

import numpy as np
import OpenEXR
import pytest
from PIL import Image
from pydantic import ValidationError

from services.core.domain.cues import CATALOG, OUTPUT_CUES, UnknownCueError
from services.core.domain.jobspec import CueParams
from services.datasets.decode import read_png
from services.worker.context import ViewContext
from services.worker.cues import REGISTRY, encode, get_impl
from services.worker.cues.encoding import decode_exr_rgb, encode_exr_rgb, encode_png, zlib_deflater
from services.worker.cues.registry import cue_value
from services.worker.cues.semantic import pack_panoptic, unpack_panoptic
from tests.fixtures.exr import openexr_file_bytes
from tests.fixtures.png import png_chunks, png_header
from tests.fixtures.raycast import make_room, raycast_passes, room_view


def test_every_catalog_cue_is_registered() -> None:
    assert set(REGISTRY) == set(CATALOG)


def test_unknown_cue_error_lists_known_cues() -> None:
    with pytest.raises(UnknownCueError) as e:
        get_impl("depth_banana")
    msg = str(e.value)
    assert "depth_banana" in msg
    assert all(c in msg for c in OUTPUT_CUES)


def test_png_16bit_is_real_16bit_and_round_trips() -> None:
    a = (np.arange(64 * 48, dtype=np.uint32) * 21 % 65536).astype(np.uint16).reshape(48, 64)
    data = encode("depth_zbuffer", a)
    assert png_header(data) == (64, 48, 16, 0)  # 16-bit greyscale
    back = np.array(Image.open(io.BytesIO(data)))
    np.testing.assert_array_equal(back.astype(np.uint16), a)
    assert back.max() > 255


def test_png_8bit_rgb_and_grey() -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (16, 20, 3)).astype(np.uint8)
    data = encode("normal", rgb)
    assert png_header(data) == (20, 16, 8, 2)
    np.testing.assert_array_equal(np.array(Image.open(io.BytesIO(data))), rgb)
    grey = rgb[..., 0]
    assert png_header(encode("mask_valid", grey)) == (20, 16, 8, 0)


def test_encode_refuses_wrong_dtype_and_shape() -> None:
    with pytest.raises(TypeError, match="uint16"):
        encode("depth_zbuffer", np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        encode("rgb", np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(TypeError):
        encode_png(np.zeros((4, 4), dtype=np.int32))


def test_npy_and_exr_round_trip() -> None:
    f = np.array([[0, 7], [4294967295, 123456789]], dtype=np.uint32)
    back = np.load(io.BytesIO(encode("fragments", f)))
    assert back.dtype == np.uint32
    np.testing.assert_array_equal(back, f)
    pos = np.random.default_rng(1).normal(size=(8, 6, 3)).astype(np.float32)
    pos[0, 0] = np.nan
    data = encode("position", pos)
    assert data[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
    back = decode_exr_rgb(data)
    # NaN bits too
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), pos.view(np.uint32))


def test_position_exr_is_uncompressed_float32_rgb_any_reader_opens() -> None:
    pos = np.random.default_rng(2).normal(size=(32, 20, 3)).astype(np.float32)
    data = encode("position", pos)
    with tempfile.NamedTemporaryFile(suffix=".exr") as f:
        f.write(data)
        f.flush()
        with OpenEXR.File(f.name) as exr:  # (the header and channels are the open file's: checked inside)
            assert exr.header()["compression"] == OpenEXR.NO_COMPRESSION
            rgb = exr.channels()["RGB"].pixels
            assert rgb.dtype == np.float32 and np.array_equal(rgb, pos)
    assert len(data) >= pos.nbytes  # stored, not compressed


def test_position_compression_zip_is_smaller_and_decodes_to_the_same_floats() -> None:
    # smooth world coordinates (as a wall's), which ZIP does compress; NaN where nothing was hit
    yy, xx = np.mgrid[0:64, 0:48].astype(np.float32)
    pos = np.stack([xx * 0.01, yy * 0.01, np.full_like(xx, 2.5)], axis=-1)
    pos[:4] = np.nan
    plain = encode("position", pos)
    zipped = encode("position", pos, exr_compression="zip")
    assert len(zipped) < len(plain)
    with tempfile.NamedTemporaryFile(suffix=".exr") as f:
        f.write(zipped)
        f.flush()
        with OpenEXR.File(f.name) as exr:
            assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    assert np.array_equal(decode_exr_rgb(zipped).view(np.uint32), pos.view(np.uint32))


def test_position_compression_is_a_job_spec_field_that_refuses_unknown_codecs() -> None:
    assert CueParams().position_compression == "none"
    assert CueParams(position_compression="zip").position_compression == "zip"
    with pytest.raises(ValidationError, match="position_compression"):
        CueParams(position_compression="zstd")


def test_json_is_deterministic_and_plain() -> None:
    a = {"b": np.float64(1.5), "a": np.arange(3), "c": {"z": np.int64(2), "y": (1, 2)}}
    b = {"c": {"y": (1, 2), "z": 2}, "a": [0, 1, 2], "b": 1.5}
    assert encode("point_info", a) == encode("point_info", b)
    assert json.loads(encode("point_info", a)) == {"a": [0, 1, 2], "b": 1.5, "c": {"y": [1, 2], "z": 2}}


def test_panoptic_packing_round_trips() -> None:
    rng = np.random.default_rng(2)
    cls = rng.integers(0, 256, (32, 32)).astype(np.uint8)
    inst = rng.integers(0, 65536, (32, 32)).astype(np.uint16)
    packed = pack_panoptic(cls, inst)
    assert packed.dtype == np.uint8 and packed.shape == (32, 32, 3)
    np.testing.assert_array_equal(packed[..., 1].astype(int) * 256 + packed[..., 2], inst)
    c2, i2 = unpack_panoptic(np.array(Image.open(io.BytesIO(encode("segment_panoptic", packed)))))
    np.testing.assert_array_equal(c2, cls)
    np.testing.assert_array_equal(i2, inst)


def pillow_png(arr: np.ndarray) -> bytes:
    """The encoder before issue 20 (Pillow, level 3, Z_RLE): the reference the hand-written PNGs must decode
    like."""
    if arr.dtype == np.uint16:
        img = Image.frombuffer(
            "I;16", (arr.shape[1], arr.shape[0]), arr.astype("<u2").tobytes(), "raw", "I;16", 0, 1
        )
    else:
        img = Image.fromarray(arr)
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=3, compress_type=3)
    return buf.getvalue()


@pytest.mark.parametrize(
    "shape,dtype",
    [
        ((1, 1), np.uint16), ((7, 5), np.uint16), ((33, 64), np.uint8), ((9, 1, 3), np.uint8),
        ((40, 31, 3), np.uint8), ((512, 512), np.uint16),
    ],
)
def test_png_files_decode_to_the_same_arrays_as_the_previous_pillow_encoder(shape, dtype) -> None:
    rng = np.random.default_rng(sum(shape))
    top = np.iinfo(dtype).max
    # Smooth ramps (long runs after filtering), noise and the extreme values, so every filter byte wraps.
    a = (np.add.outer(np.arange(shape[0]) * 97, np.arange(shape[1]) * 13) % (top + 1))
    a = (a[..., None] if len(shape) == 3 else a) + rng.integers(0, 3, shape)
    a = np.clip(a, 0, top).astype(dtype)
    a.flat[:: max(1, a.size // 7)] = top
    new, old = encode_png(a), pillow_png(a)
    assert png_header(new) == png_header(old)
    decoded_new = np.array(Image.open(io.BytesIO(new)))
    decoded_old = np.array(Image.open(io.BytesIO(old)))
    assert decoded_new.dtype == decoded_old.dtype
    np.testing.assert_array_equal(decoded_new, decoded_old)
    np.testing.assert_array_equal(decoded_new.astype(dtype), a)


def test_png_refuses_unsupported_layouts() -> None:
    with pytest.raises(ValueError, match="single-channel"):
        encode_png(np.zeros((4, 4, 3), dtype=np.uint16))
    with pytest.raises(ValueError, match="H x W x 3"):
        encode_png(np.zeros((4, 4, 4), dtype=np.uint8))


def awkward_floats(shape: tuple[int, int, int]) -> np.ndarray:
    """Random floats with the bit patterns a copy could alter: NaNs (quiet, signalling, with payloads,
    negative), infinities, -0.0, subnormals and the extremes."""
    rng = np.random.default_rng(sum(shape))
    a = rng.normal(size=shape).astype(np.float32)
    specials = np.array([0x7FC00000, 0x7F800001, 0xFFC12345, 0x7FA00000, 0x7F800000, 0xFF800000, 0x80000000,
                         0x00000001, 0x807FFFFF, 0x7F7FFFFF, 0xFF7FFFFF], dtype=np.uint32).view(np.float32)
    flat = a.reshape(-1)
    flat[: min(flat.size, specials.size)] = specials[: flat.size]
    return a


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 3, 3), (7, 5, 3), (64, 33, 3), (3, 200, 3)])
def test_uncompressed_exr_is_the_file_openexr_writes_byte_for_byte(shape) -> None:
    pos = awkward_floats(shape)
    data = encode_exr_rgb(pos)
    assert data == openexr_file_bytes(pos)  # so every reader of OpenEXR's files opens these
    back = decode_exr_rgb(data)
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), pos.view(np.uint32))


def test_exr_refuses_what_is_not_float32_rgb() -> None:
    with pytest.raises(ValueError, match="H x W x 3 float32"):
        encode_exr_rgb(np.zeros((4, 4, 3), dtype=np.float64))
    with pytest.raises(ValueError, match="H x W x 3 float32"):
        encode_exr_rgb(np.zeros((4, 4, 4), dtype=np.float32))


def test_zip_exr_is_still_openexrs_file() -> None:
    pos = awkward_floats((16, 9, 3))
    assert encode_exr_rgb(pos, "zip") == openexr_file_bytes(pos, OpenEXR.ZIP_COMPRESSION)


@pytest.fixture(scope="module")
def room_values() -> dict[str, np.ndarray]:
    """Every PNG cue's array and the position of a ray-cast view of the synthetic room (128 px)."""
    mesh, cls, inst = make_room()
    g = room_view(128)
    ctx = ViewContext(g, CueParams(), passes=raycast_passes(mesh, g, face_class=cls, face_instance=inst))
    cues = [c for c in REGISTRY if (CATALOG[c].ext == "png" or c == "position")
            and c not in ("principal_curvature", "mask_photo")]  # (no mesh curvature, no photos here)
    return {c: cue_value(ctx, c) for c in cues}


def test_png_cues_decode_to_the_same_arrays_as_the_zlib_encoder_before(room_values) -> None:
    """ISA-L's deflate against zlib level 1 + Z_RLE (the encoder before): other bytes, the same arrays, read
    by Pillow and by the dataset's explicit 16-bit decoder; every chunk's CRC right."""
    before = zlib_deflater(1, zlib.Z_RLE)
    pngs = {c: a for c, a in room_values.items() if CATALOG[c].ext == "png"}
    assert {"depth_zbuffer", "rgb", "segment_panoptic", "mask_valid"} <= set(pngs)
    for cue, a in pngs.items():
        new, old = encode(cue, a), encode_png(a, before)
        assert [k for k, _ in png_chunks(new)] == [b"IHDR", b"IDAT", b"IEND"]
        assert png_header(new) == png_header(old)
        assert zlib.decompress(png_chunks(new)[1][1]) == zlib.decompress(png_chunks(old)[1][1]), cue
        with Image.open(io.BytesIO(new)) as img:
            img.verify()
        np.testing.assert_array_equal(read_png(new), a, err_msg=cue)
        np.testing.assert_array_equal(
            np.array(Image.open(io.BytesIO(new))), np.array(Image.open(io.BytesIO(old)))
        )


def test_position_of_a_room_view_is_openexrs_file(room_values) -> None:
    pos = room_values["position"]  # (every pixel sees the room here; NaNs: the byte-for-byte test above)
    data = encode("position", pos)
    assert data == openexr_file_bytes(pos)
    with tempfile.NamedTemporaryFile(suffix=".exr") as f:
        f.write(data)
        f.flush()
        with OpenEXR.File(f.name, separate_channels=True) as exr:
            ch = exr.channels()
            assert sorted(ch) == ["B", "G", "R"]
            for i, name in enumerate("RGB"):
                assert np.array_equal(ch[name].pixels.view(np.uint32), pos[..., i].view(np.uint32))
