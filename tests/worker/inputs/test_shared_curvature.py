"""Curvature shared between a machine's worker processes (services.worker.inputs.shared_curvature): computed
once, read back bit for bit, and the principal_curvature cue's bytes the same with or without the shared
file."""

from __future__ import annotations

import io
import logging
import multiprocessing as mp
from pathlib import Path

import numpy as np
import pytest
import trimesh

import services.worker.inputs.curvature as estimator
from services.worker.inputs.shared_curvature import _read, shared_curvature

RADIUS = 0.2


def room_like() -> trimesh.Trimesh:
    """A curved, irregular mesh (a noisy sphere) with every curvature sign."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rng = np.random.default_rng(1)
    return trimesh.Trimesh(
        mesh.vertices * (1 + 0.05 * rng.standard_normal((len(mesh.vertices), 1))), mesh.faces
    )


def test_the_shared_array_is_the_computed_one_and_is_computed_once(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    direct = estimator.principal_curvatures(room_like(), RADIUS)
    first = shared_curvature(room_like(), RADIUS, tmp_path)
    assert first.dtype == direct.dtype and first.tobytes() == direct.tobytes()

    def no_compute(*_a: object) -> np.ndarray:
        raise AssertionError("computed again")

    monkeypatch.setattr(estimator, "principal_curvatures", no_compute)
    again = shared_curvature(room_like(), RADIUS, tmp_path)  # another process's mesh: same inputs, read back
    assert again.dtype == direct.dtype and again.tobytes() == direct.tobytes()
    with pytest.raises(AssertionError, match="computed again"):  # another radius is another file
        shared_curvature(room_like(), RADIUS * 2, tmp_path)
    moved = room_like()
    moved.vertices[0] += 0.01
    with pytest.raises(AssertionError, match="computed again"):  # so is another mesh (or frame)
        shared_curvature(moved, RADIUS, tmp_path)


def test_a_damaged_file_is_computed_again(tmp_path: Path) -> None:
    direct = estimator.principal_curvatures(room_like(), RADIUS)
    shared_curvature(room_like(), RADIUS, tmp_path)
    (npy,) = tmp_path.glob("*.npy")
    npy.write_bytes(npy.read_bytes()[:100])  # truncated
    assert shared_curvature(room_like(), RADIUS, tmp_path).tobytes() == direct.tobytes()
    kept = _read(npy, len(direct))
    assert kept is not None and kept.tobytes() == direct.tobytes()  # rewritten whole
    np.save(npy, direct + 1)  # a plain .npy of the right shape (the layout without a checksum): not read
    assert shared_curvature(room_like(), RADIUS, tmp_path).tobytes() == direct.tobytes()


def test_a_flipped_byte_in_the_array_is_refused_and_the_file_replaced(
    tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    """A file of the right size and shape whose values changed (a bad disk, a stray write) is never used."""
    direct = estimator.principal_curvatures(room_like(), RADIUS)
    shared_curvature(room_like(), RADIUS, tmp_path)
    (npy,) = tmp_path.glob("*.npy")
    good = npy.read_bytes()
    data = bytearray(good)
    at = len(data) - 4 * len(direct)  # a float inside the array's data (the last vertex's): its low byte
    data[at] ^= 0x01
    npy.write_bytes(bytes(data))
    arr = np.load(io.BytesIO(bytes(data[data.index(b"\x93NUMPY"):])))
    assert arr.shape == direct.shape and arr.dtype == direct.dtype and arr.tobytes() != direct.tobytes()

    with caplog.at_level(logging.WARNING, logger="services.worker.inputs.shared_curvature"):
        again = shared_curvature(room_like(), RADIUS, tmp_path)
    assert again.tobytes() == direct.tobytes()
    assert "damaged" in caplog.text
    assert npy.read_bytes() == good  # replaced by a whole file


def _worker(folder: str, log: str) -> None:
    real = estimator.principal_curvatures

    def counted(mesh: trimesh.Trimesh, radius: float) -> np.ndarray:
        with open(log, "a") as fh:
            fh.write("computed\n")
        return real(mesh, radius)

    estimator.principal_curvatures = counted  # type: ignore[assignment]
    out = shared_curvature(room_like(), RADIUS, Path(folder))
    np.save(Path(log).with_suffix(f".{mp.current_process().pid}.npy"), out)


def test_processes_started_together_compute_it_once(tmp_path: Path) -> None:
    ctx = mp.get_context("spawn")  # as the embedded pool starts its workers
    log = tmp_path / "log.txt"
    procs = [ctx.Process(target=_worker, args=(str(tmp_path / "cache"), str(log))) for _ in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    assert log.read_text().splitlines() == ["computed"]
    direct = estimator.principal_curvatures(room_like(), RADIUS)
    outs = sorted(tmp_path.glob("log.*.npy"))
    assert len(outs) == 3 and all(np.load(o).tobytes() == direct.tobytes() for o in outs)


@pytest.mark.bpy
def test_the_curvature_cue_has_the_same_bytes_with_the_shared_file(tmp_path: Path) -> None:
    from services.worker.executor import make_context, produce
    from services.worker.inputs.space_cache import SpaceContext
    from tests.fixtures.raycast import object_view

    g = object_view(room_like(), np.array([2.5, 1.5, 1.0]), 48)
    files = []
    for folder in (None, tmp_path, tmp_path):  # computed alone; computed and shared; read back
        space = SpaceContext(key="sphere", mesh=room_like(), curvature_dir=folder)
        try:
            files.append(produce("principal_curvature", make_context(space, g, ["principal_curvature"])))
        finally:
            space.close()
    assert len(list(tmp_path.glob("*.npy"))) == 1
    assert files[0] == files[1] == files[2]
