"""The cue catalog (every cue's file encoding, dtype and inputs) as data, and the dependency DAG from it."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

Source = Literal["plan", "render", "derive", "internal"]

# Stored values with a meaning of their own (no depth, no face, flat), shared by the worker that writes them
# and the readers (services.datasets).
UINT16_NONE = 65535  # 16-bit depth: no surface
FRAGMENT_NONE = 4294967295  # fragments (uint32): no triangle seen
CURVATURE_FLAT = 127  # principal_curvature pixel of k = 0 (0..254 spans -kmax..kmax)
NORMAL_BACKGROUND = 128  # normal (8-bit RGB): every channel of a pixel where nothing is seen


@dataclass(frozen=True)
class Cue:
    """One output of the catalog: how it is stored and what it is made from."""

    name: str
    ext: str  # file extension without the dot
    encoding: str  # human-readable encoding, recorded in job.json
    dtype: str  # "uint8", "uint16", "uint32", "float32", "json"
    channels: int  # 1, 3; 0 for JSON
    source: Source  # plan: from the plan alone; render: from the view's pass set; derive: from other cues
    inputs: tuple[str, ...] = ()
    needs_semantics: bool = False
    per_point: bool = False  # one file per point instead of one per view
    default: bool = True  # part of "all the space supports" when a job names no cues

    @property
    def internal(self) -> bool:
        return self.source == "internal"


# `passes` is internal: the one Cycles render per view whose passes feed every render cue.
CATALOG: dict[str, Cue] = {
    c.name: c
    for c in [
        Cue("passes", "npz", "internal pass set of one view (float32 arrays)", "float32", 0, "internal"),
        Cue("rgb", "png", "8-bit RGB, unlit texture/vertex colour", "uint8", 3, "render", ("passes",)),
        Cue(
            "normal", "png", "8-bit RGB camera-space normal, 255*(0.5-0.5x, 0.5+0.5y, 0.5+0.5z), bg 128",
            "uint8", 3, "render", ("passes",),
        ),
        Cue(
            "depth_zbuffer", "png", "16-bit, optical-axis distance in 1/512 m, 65535 = none", "uint16", 1,
            "render", ("passes",),
        ),
        Cue(
            "depth_euclidean", "png", "16-bit, distance to camera centre in 1/512 m, 65535 = none", "uint16",
            1, "derive", ("depth_zbuffer",),
        ),
        Cue(
            "mask_valid", "png", "8-bit, 255 where depth_zbuffer is valid", "uint8", 1, "derive",
            ("depth_zbuffer",),
        ),
        Cue(
            "reshading", "png", "8-bit grey albedo lit by a point light at the camera", "uint8", 1, "derive",
            ("depth_zbuffer", "normal"),
        ),
        Cue(
            "principal_curvature", "png", "8-bit RGB, R,G = k1,k2 clipped to +-1/r mapped to 0..254", "uint8",
            3, "render", ("passes",),
        ),
        Cue(
            "edge_texture", "png", "16-bit Sobel magnitude of Gaussian-blurred grey rgb", "uint16", 1,
            "derive", ("rgb",),
        ),
        Cue(
            "edge_occlusion", "png", "16-bit Sobel magnitude of sqrt(depth), masked", "uint16", 1, "derive",
            ("depth_zbuffer",),
        ),
        Cue(
            "keypoints2d", "png", "16-bit max-over-scales determinant-of-Hessian", "uint16", 1, "derive",
            ("rgb",),
        ),
        Cue(
            "keypoints3d", "png", "16-bit NARF-like 3D interest from the range image", "uint16", 1, "derive",
            ("depth_zbuffer",),
        ),
        Cue(
            "segment_unsup2d", "png", "16-bit labels, Felzenszwalb + normalized cuts on colour", "uint16", 1,
            "derive", ("rgb",),
        ),
        Cue(
            "segment_unsup25d", "png", "16-bit labels on log-depth, normals and occlusion edges", "uint16", 1,
            "derive", ("depth_zbuffer", "normal", "edge_occlusion"),
        ),
        Cue(
            "segment_semantic", "png", "8-bit class id per pixel", "uint8", 1, "render", ("passes",),
            needs_semantics=True,
        ),
        Cue(
            "segment_instance", "png", "16-bit instance id per pixel", "uint16", 1, "render", ("passes",),
            needs_semantics=True,
        ),
        Cue(
            "segment_panoptic", "png", "8-bit RGB, R = class, G*256+B = instance", "uint8", 3, "derive",
            ("segment_semantic", "segment_instance"), needs_semantics=True,
        ),
        Cue(
            "fragments", "npy", "uint32 triangle index per pixel, 4294967295 = none", "uint32", 1, "render",
            ("passes",),
        ),
        Cue(
            "point_info", "json", "Omnidata point_info keys plus K, world_to_camera, conventions", "json", 0,
            "plan",
        ),
        Cue(
            "nonfixated", "json", "pixel positions of other points visible in each view of a point", "json",
            0, "plan", per_point=True,
        ),
        Cue(
            "vanishing_points", "json", "image-space and Gaussian-sphere vanishing points of world axes",
            "json", 0, "derive", ("point_info",),
        ),
        Cue(
            "position", "exr", "float32 RGB world XYZ in metres, NaN = none", "float32", 3, "render",
            ("passes",),
        ),
        Cue(
            "mask_photo", "png", "8-bit, 255 where the rgb came from a photo (capture views), else 0",
            "uint8", 1, "render", ("passes",), default=False,
        ),
        # 3D augmentations (ours, optional): rgb corrupted with the view's depth; parameters drawn per view
        Cue(
            "augment_params", "json", "the augmentation parameters drawn for this view", "json", 0, "derive",
            ("depth_zbuffer",), default=False,
        ),
        Cue(
            "rgb_refocus", "png", "8-bit RGB, thin-lens defocus at a drawn focus distance and f-number",
            "uint8", 3, "derive", ("rgb", "depth_zbuffer", "augment_params"), default=False,
        ),
        Cue(
            "rgb_fog", "png", "8-bit RGB, J t + A (1 - t), t = exp(-beta d)", "uint8", 3, "derive",
            ("rgb", "depth_euclidean", "augment_params"), default=False,
        ),
        Cue(
            "rgb_motion_blur", "png", "8-bit RGB, camera translation during the exposure, warped by depth",
            "uint8", 3, "derive", ("rgb", "depth_zbuffer", "augment_params"), default=False,
        ),
        Cue(
            "rgb_flash", "png", "8-bit RGB, a flash at the camera: ambient + power x shading / d^2", "uint8",
            3, "derive", ("rgb", "depth_euclidean", "reshading", "augment_params"), default=False,
        ),
    ]
}

OUTPUT_CUES: tuple[str, ...] = tuple(n for n, c in CATALOG.items() if not c.internal)


class UnknownCueError(ValueError):
    """A cue name that is not in the catalog."""

    def __init__(self, names: Iterable[str]):
        self.names = sorted(names)
        super().__init__(
            f"unknown cue(s): {', '.join(self.names)}; known cues: {', '.join(OUTPUT_CUES)}"
        )


def get_cue(name: str) -> Cue:
    """Return the catalog entry for `name`, or raise UnknownCueError listing the known cues."""
    try:
        return CATALOG[name]
    except KeyError:
        raise UnknownCueError([name]) from None


def validate_cue_names(names: Iterable[str]) -> list[str]:
    """Check that every name is an output cue; return them de-duplicated in catalog order."""
    wanted = set(names)
    unknown = wanted - set(OUTPUT_CUES)
    if unknown:
        raise UnknownCueError(unknown)
    return [n for n in OUTPUT_CUES if n in wanted]


def default_cues(has_semantics: bool) -> list[str]:
    """All output cues a space supports (semantic cues only for labelled spaces)."""
    return [
        n for n in OUTPUT_CUES if CATALOG[n].default and (has_semantics or not CATALOG[n].needs_semantics)
    ]


def unsupported_cues(names: Iterable[str], *, has_semantics: bool) -> dict[str, str]:
    """Cues a space cannot give, each with the reason."""
    out = {}
    for n in names:
        if get_cue(n).needs_semantics and not has_semantics:
            out[n] = "needs semantic labels, and the space has none (unlabelled scan)"
    return out


def require_supported(
    names: Iterable[str], *, has_semantics: bool, error: type[Exception] = ValueError
) -> None:
    """Raise `error` naming each cue the space cannot give and why (the one check of the API, CLIs and
    worker)."""
    bad = unsupported_cues(names, has_semantics=has_semantics)
    if bad:
        raise error("; ".join(f"cue {n!r} {why}" for n, why in bad.items()))


def closure(names: Iterable[str]) -> list[str]:
    """The requested cues plus every cue they depend on (internal ones included), in topological order."""
    needed: set[str] = set()
    stack = list(names)
    while stack:
        n = stack.pop()
        if n in needed:
            continue
        needed.add(n)
        stack.extend(get_cue(n).inputs)
    return topological_order(needed)


def topological_order(names: Iterable[str], catalog: dict[str, Cue] | None = None) -> list[str]:
    """Order cues so that each comes after its inputs; ties keep catalog order (deterministic).

    Raises ValueError naming the cue when an input is missing from `names` or the inputs form a cycle.
    """
    catalog = CATALOG if catalog is None else catalog
    names = set(names)
    for n in names:
        if n not in catalog:
            raise UnknownCueError([n])
        missing = [i for i in catalog[n].inputs if i not in names]
        if missing:
            raise ValueError(f"cue {n!r} needs {', '.join(missing)}, which is not in the set")
    order: list[str] = []
    done: set[str] = set()
    remaining = [n for n in catalog if n in names]
    while remaining:
        ready = [n for n in remaining if all(i in done for i in catalog[n].inputs)]
        if not ready:
            raise ValueError(f"cue dependency cycle among: {', '.join(remaining)}")
        order.extend(ready)
        done.update(ready)
        remaining = [n for n in remaining if n not in done]
    return order
