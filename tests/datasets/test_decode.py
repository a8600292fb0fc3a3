"""Cue decoding to physical units, against values computed here from DESIGN.md section 5's encodings."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from services.core.domain.jobspec import CueParams
from services.datasets import decode as dec

# 0 m, 2.5 m, the int16 edge on both sides, 78.125 m (wraps negative as int16), and "no surface"
DEPTH_UNITS = np.array([[0, 1280, 32767, 32768, 40000, 65535]], dtype=np.uint16)


def png16(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.frombuffer("I;16", (a.shape[1], a.shape[0]), a.astype("<u2").tobytes(), "raw", "I;16", 0, 1).save(
        buf, format="PNG")
    return buf.getvalue()


def png8(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _check_depth(depth: np.ndarray) -> None:
    assert depth.dtype == np.float32 and depth.shape == (1, 1, 6)
    want = np.array([0.0, 2.5, 32767 / 512, 64.0, 78.125])
    np.testing.assert_allclose(depth[0, 0, :5], want, rtol=1e-7)
    assert np.isnan(depth[0, 0, 5]) and not (depth[0, 0, :5] < 0).any()


def test_16bit_png_is_exact_and_depth_is_metres() -> None:
    data = png16(DEPTH_UNITS)
    assert dec.png_bit_depth(data) == 16
    raw = dec.read_png(data)
    assert raw.dtype == np.uint16 and np.array_equal(raw, DEPTH_UNITS)
    _check_depth(dec.decode_cue("depth_zbuffer", data))


def test_decoding_does_not_depend_on_how_pillow_widens_16_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Pillow versions open 16-bit grey as I;16, I;16B or int32 'I'; all decode to the same values."""
    real_open = Image.open

    def big_endian(f: io.BytesIO) -> Image.Image:
        img = real_open(f)
        return Image.frombuffer(
            "I;16B", img.size, np.asarray(img).astype(">u2").tobytes(), "raw", "I;16B", 0, 1
        )

    for opener in (lambda f: real_open(f).convert("I"), big_endian):
        monkeypatch.setattr(dec.Image, "open", opener)
        raw = dec.read_png(png16(DEPTH_UNITS))
        assert raw.dtype == np.uint16 and np.array_equal(raw, DEPTH_UNITS)
    monkeypatch.setattr(dec.Image, "open", real_open)
    # a decoder that hands back int16 (wrapped) samples is undone exactly
    wrapped = DEPTH_UNITS.view(np.int16)
    assert wrapped.min() < 0 and np.array_equal(dec.as_uint16(wrapped), DEPTH_UNITS)


def test_normals_curvature_labels_fragments() -> None:
    n = np.array([0.6, 0.0, 0.8])
    px = np.rint(255 * np.array([0.5 - 0.5 * n[0], 0.5 + 0.5 * n[1], 0.5 + 0.5 * n[2]])).astype(np.uint8)
    img = np.full((1, 2, 3), 128, np.uint8)
    img[0, 0] = px
    normal = dec.decode_cue("normal", png8(img))
    assert normal.shape == (3, 1, 2) and normal.dtype == np.float32
    np.testing.assert_allclose(normal[:, 0, 0], n, atol=2 / 255)
    assert abs(np.linalg.norm(normal[:, 0, 0]) - 1) < 1e-6 and np.isnan(normal[:, 0, 1]).all()

    params = CueParams(curvature_clip_m=0.05)  # kmax = 20 / m
    curv = np.array([[[127, 254, 0], [0, 127, 0], [0, 0, 0]]], np.uint8)
    k = dec.decode_cue("principal_curvature", png8(curv), params)
    assert k.shape == (2, 1, 3)
    np.testing.assert_allclose(k[:, 0, 0], [0.0, 20.0], atol=1e-5)
    np.testing.assert_allclose(k[:, 0, 1], [-20.0, 0.0], atol=1e-5)
    assert np.isnan(k[:, 0, 2]).all()  # R = G = B = 0: nothing seen

    pan = dec.decode_cue("segment_panoptic", png8(np.array([[[3, 1, 2]]], np.uint8)))
    assert pan.dtype == np.int64 and pan[:, 0, 0].tolist() == [3, 258]
    labels = dec.decode_cue("segment_unsup2d", png16(np.array([[0, 40000]], np.uint16)))
    assert labels.dtype == np.int64 and labels[0, 0].tolist() == [0, 40000]

    buf = io.BytesIO()
    np.save(buf, np.array([[7, 4294967295]], np.uint32))
    frags = dec.decode_cue("fragments", buf.getvalue())
    assert frags.dtype == np.int64 and frags[0, 0].tolist() == [7, -1]


def test_scaled_16_bit_cues_use_the_jobs_scales() -> None:
    params = CueParams(edge_scale=100.0, keypoints2d_scale=1000.0)
    data = png16(np.array([[0, 50, 65535]], np.uint16))
    np.testing.assert_allclose(
        dec.decode_cue("edge_texture", data, params)[0, 0], [0, 0.5, 655.35], rtol=1e-6
    )
    np.testing.assert_allclose(
        dec.decode_cue("keypoints2d", data, params)[0, 0], [0, 0.05, 65.535], rtol=1e-6
    )
    np.testing.assert_allclose(
        dec.decode_cue("keypoints3d", data, params)[0, 0], [0, 50 / 65535, 1.0], rtol=1e-6
    )
    assert dec.decode_cue("point_info", b'{"a": 1}') == '{"a": 1}'
    assert dec.cue_params({"spec": {"params": {"edge_scale": 5.0}}}).edge_scale == 5.0
    assert dec.cue_params(None) == CueParams()
