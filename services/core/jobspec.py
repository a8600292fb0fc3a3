"""JobSpec: every steering knob of DESIGN.md section 4 and every cue parameter of section 5.

Defaults follow the Omnidata annotator. Units: metres and degrees in the spec (converted to radians
where used). Every refusal names the field and the reason (pydantic reports the field path).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.core.cues import validate_cue_names
from services.core.keys import check_name

MAX_RESOLUTION = 4096
MIN_RESOLUTION = 16
FOV_LIMITS_DEG = (1.0, 179.0)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ProvidedPose(_Strict):
    """One provided camera (Omnidata camera_poses.json): location in the world frame and wxyz quaternion."""

    location: tuple[float, float, float]
    quaternion: tuple[float, float, float, float] | None = Field(
        None, description="wxyz rotation of the Blender camera; ignored for fixated views"
    )
    uuid: str | None = None


class CameraSpec(_Strict):
    mode: Literal["generate", "provided", "object"] = Field(
        "generate", description="generate: Poisson-disc in free space; provided: poses; object: on a sphere"
    )
    min_spacing_m: float = Field(0.5, gt=0, le=100, description="Poisson-disc minimum spacing")
    height_min_m: float = Field(0.2, ge=0, le=100, description="camera height above the floor, lower bound")
    height_max_m: float = Field(2.0, gt=0, le=100, description="camera height above the floor, upper bound")
    clearance_m: float = Field(0.1, ge=0, le=10, description="minimum distance from a camera to the mesh")
    max_count: int = Field(1000, ge=1, le=100_000, description="at most this many generated cameras")
    poses: list[ProvidedPose] | None = Field(None, description="cameras for mode=provided")
    object_count: int = Field(32, ge=1, le=100_000, description="cameras on the sphere (mode=object)")
    object_distance_factor: float = Field(
        2.0, gt=1.0, le=100, description="sphere radius / bounding-sphere radius (mode=object)"
    )

    @model_validator(mode="after")
    def _check(self) -> CameraSpec:
        if self.height_min_m >= self.height_max_m:
            raise ValueError(
                f"height_min_m ({self.height_min_m}) must be below height_max_m ({self.height_max_m})"
            )
        if self.mode == "provided" and not self.poses:
            raise ValueError("mode 'provided' needs a non-empty 'poses' list")
        if self.mode != "provided" and self.poses:
            raise ValueError(f"'poses' is only used with mode 'provided', not {self.mode!r}")
        return self


class PointSpec(_Strict):
    count: int | None = Field(None, ge=1, le=10_000_000, description="points of interest; default per_camera")
    per_camera: float = Field(5.0, gt=0, le=1000, description="points per camera when count is not given")
    min_views: int = Field(3, ge=1, le=1000, description="a point needs this many cameras with line of sight")
    max_views: int | None = Field(None, ge=1, le=100_000, description="views kept per point (None: all)")
    los_tolerance_m: float = Field(0.001, ge=0, le=1, description="line-of-sight tolerance")
    max_tries_per_point: int = Field(
        50, ge=1, le=100_000, description="surface samples tried per requested point before giving up"
    )

    @model_validator(mode="after")
    def _check(self) -> PointSpec:
        if self.max_views is not None and self.max_views < self.min_views:
            raise ValueError(f"max_views ({self.max_views}) is below min_views ({self.min_views})")
        return self


class ViewSpec(_Strict):
    mode: Literal["wide_baseline", "trajectory"] = "wide_baseline"
    fov_mean_deg: float = Field(77.5, description="truncated-normal mean of the field of view")
    fov_std_deg: float = Field(15.0, ge=0, le=180)
    fov_min_deg: float = Field(30.0)
    fov_max_deg: float = Field(125.0)
    roll_max_deg: float = Field(10.0, ge=0, le=180, description="roll ~ uniform [-roll_max, roll_max]")
    resolution: int = Field(512, ge=MIN_RESOLUTION, le=MAX_RESOLUTION, description="square image size, px")
    nonfixated_pruning: bool = Field(False, description="keep only views that also see another point")
    trajectory_spacing_m: float = Field(0.1, gt=0, le=100, description="frame spacing along the path")
    trajectory_max_frames: int = Field(300, ge=2, le=100_000, description="frames per point at most")
    trajectory_look: Literal["point", "ahead"] = Field(
        "point", description="point: every frame fixated on the point; ahead: look along the path (walk-through)"
    )
    trajectory_max_turn_deg_per_m: float = Field(
        60.0, gt=0, le=3600, description="largest turn of the direction of motion per metre of path"
    )
    trajectory_max_view_deg_per_m: float = Field(
        30.0, gt=0, le=3600, description="largest rotation of the camera (view and roll) per metre of path"
    )
    trajectory_min_frames: int = Field(
        1, ge=1, le=100_000, description="a clip shorter than this (cut by the limits, or a short route) is dropped (reported)"
    )

    @model_validator(mode="after")
    def _check(self) -> ViewSpec:
        lo, hi = FOV_LIMITS_DEG
        for f in ("fov_min_deg", "fov_max_deg", "fov_mean_deg"):
            v = getattr(self, f)
            if not lo <= v <= hi:
                raise ValueError(f"{f} ({v}) must lie in [{lo}, {hi}] degrees")
        if not self.fov_min_deg <= self.fov_mean_deg <= self.fov_max_deg:
            raise ValueError(
                f"fov_mean_deg ({self.fov_mean_deg}) must lie in [fov_min_deg, fov_max_deg] = "
                f"[{self.fov_min_deg}, {self.fov_max_deg}]"
            )
        if self.trajectory_min_frames > self.trajectory_max_frames:
            raise ValueError(
                f"trajectory_min_frames ({self.trajectory_min_frames}) exceeds trajectory_max_frames "
                f"({self.trajectory_max_frames})"
            )
        return self


class CueParams(_Strict):
    """Parameters of the cue derivations (DESIGN.md section 5)."""

    depth_units_per_m: float = Field(512.0, gt=0, description="depth PNG units per metre")
    max_depth_m: float = Field(128.0, gt=0, le=10_000, description="deeper surfaces are 'no surface'")
    curvature_clip_m: float = Field(0.03, gt=0, description="k1,k2 clipped to +-1/curvature_clip_m")
    curvature_radius_m: float = Field(0.05, gt=0, description="neighbourhood radius of curvature fitting")
    reshading_albedo: float = Field(0.8, gt=0, le=1, description="constant grey albedo")
    edge_texture_sigma: float = Field(2.0, ge=0, le=50, description="Gaussian blur before Sobel")
    edge_occlusion_sigma: float = Field(1.0, ge=0, le=50, description="blur of sqrt(depth) before Sobel")
    keypoints2d_sigmas: tuple[float, ...] = Field((1.0, 2.0, 4.0, 8.0), min_length=1)
    keypoints3d_support_m: float = Field(0.1, gt=0, le=10, description="NARF-like support size")
    segment2d_scale: float = Field(200.0, gt=0)
    segment2d_sigma: float = Field(0.8, ge=0)
    segment2d_min_size: int = Field(50, ge=1)
    segment_ncut_thresh: float = Field(0.005, gt=0)
    segment25d_weights: tuple[float, float, float] = Field(
        (1.0, 1.0, 1.0), description="weights of log-depth, normals, occlusion edges"
    )
    edge_scale: float = Field(
        1000.0, gt=0, description="16-bit edge images (edge_texture, edge_occlusion) store round(response * edge_scale)"
    )
    keypoints2d_scale: float = Field(
        250_000.0, gt=0,
        description="keypoints2d stores round(DoH response * scale); the DoH of a [0,1] image peaks near 0.06-0.25",
    )
    segment_max_superpixels: int = Field(
        512, ge=2, le=4096, description="Felzenszwalb regions before normalized cuts, at most (bounds the cost)"
    )
    segment_ncut_sigma: float = Field(
        255.0, gt=0, description="RAG similarity exp(-|mean difference|^2 / sigma), features on a 0..255 scale"
    )
    segment_num_cuts: int = Field(10, ge=1, le=100, description="thresholds tried per normalized cut")


class JobSpec(_Strict):
    """What to generate: the steering knobs of a job."""

    name: str = Field("omnidata", description="component name in the output layout")
    cues: list[str] | None = Field(None, description="subset of the catalog; None = all the space supports")
    seed: int = Field(0, ge=0, le=2**63 - 1)
    up_axis: Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"] = Field(
        "auto", description="source axis that points up; auto detects floors"
    )
    unit_scale: float = Field(1.0, gt=0, le=1000, description="metres per source unit")
    priority: int = Field(0, ge=-100, le=100)
    max_attempts: int = Field(3, ge=1, le=20)
    cameras: CameraSpec = CameraSpec()
    points: PointSpec = PointSpec()
    views: ViewSpec = ViewSpec()
    params: CueParams = CueParams()

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        return check_name("name", v)

    @field_validator("cues")
    @classmethod
    def _cues(cls, v: list[str] | None) -> list[str] | None:
        if v is None:
            return None
        if not v:
            raise ValueError("cues must name at least one cue (or be omitted for all)")
        return validate_cue_names(v)

    @model_validator(mode="after")
    def _check(self) -> JobSpec:
        cams = self.cameras
        if cams.mode == "provided" and cams.poses is not None and len(cams.poses) < self.points.min_views:
            raise ValueError(
                f"points.min_views ({self.points.min_views}) exceeds the {len(cams.poses)} provided cameras: "
                "no point could ever be accepted"
            )
        if cams.mode == "object" and cams.object_count < self.points.min_views:
            raise ValueError(
                f"points.min_views ({self.points.min_views}) exceeds cameras.object_count "
                f"({cams.object_count}): no point could ever be accepted"
            )
        return self


Resolution = Annotated[int, Field(ge=MIN_RESOLUTION, le=MAX_RESOLUTION)]


def cues_for_space(spec: JobSpec, *, has_semantics: bool) -> list[str]:
    """The output cues a job renders for one space; raises ValueError naming unsupported cues."""
    from services.core.cues import default_cues, unsupported_cues

    if spec.cues is None:
        return default_cues(has_semantics)
    bad = unsupported_cues(spec.cues, has_semantics=has_semantics)
    if bad:
        raise ValueError("; ".join(f"cue {n!r} {why}" for n, why in bad.items()))
    return list(spec.cues)
