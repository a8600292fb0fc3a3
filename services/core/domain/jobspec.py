"""JobSpec: every steering knob of a job (cameras, points, views, frame) and every cue parameter.

Defaults follow the Omnidata annotator. Units: metres and degrees in the spec (converted to radians
where used). Every refusal names the field and the reason (pydantic reports the field path).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Literal, TypedDict

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

from services.core.domain.augment_spec import AugmentParams
from services.core.domain.cues import validate_cue_names
from services.core.domain.frame_values import MAX_UNIT_SCALE, parse_unit_scale, similarity_scale
from services.core.domain.keys import check_name
from services.core.domain.steering_spec import FOV_LIMITS_DEG, CameraSteering, ViewSteering

MAX_RESOLUTION = 4096
MIN_RESOLUTION = 16
MAX_SIGMA_PX = 64.0  # Gaussian blurs: the kernel grows with sigma (a sigma of 1e9 asks for a 60 GiB kernel)
MAX_KEYPOINT_SCALES = 16  # every scale is one more blur of the whole image
MAX_PROVIDED_POSES = 50_000
MAX_PLANNED_VIEWS = 20_000_000  # upper estimate of the views a spec can plan (points x views per point)
MAX_SAMPLE_BUDGET = 200_000_000  # surface samples the point sampler may draw (points x max_tries_per_point)


def _list_as_tuple(v: object) -> object:
    # JSON (and a spec stored as JSON) has no tuples: take a list as one, with its items still checked
    # strictly.
    return tuple(v) if isinstance(v, list) else v


def _rows_as_tuples(v: object) -> object:
    return tuple(_list_as_tuple(r) for r in v) if isinstance(v, (list, tuple)) else v


Row4 = tuple[float, float, float, float]


class SpaceFrame(TypedDict, total=False):
    """The keyword arguments of `services.core.ingest.loading.load_space` that set a space's frame (a planned
    frame may give source_to_world alone)."""

    up_axis: str
    unit_scale: float | str
    up: Sequence[float] | None
    source_to_world: Sequence[Sequence[float]] | None
    accept_up_guess: bool


class _Strict(BaseModel):
    # strict: "3" or true is not an int, "0.5" is not a float (an int is accepted where a float is expected)
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


Vector3 = Annotated[tuple[float, float, float], BeforeValidator(_list_as_tuple)]
Matrix4 = Annotated[tuple[Row4, Row4, Row4, Row4], BeforeValidator(_rows_as_tuples)]


class ProvidedPose(_Strict):
    """One provided camera (Omnidata camera_poses.json): location in the world frame and wxyz quaternion."""

    location: Vector3
    quaternion: Annotated[tuple[float, float, float, float] | None, BeforeValidator(_list_as_tuple)] = Field(
        None, description="wxyz rotation of the Blender camera; ignored for fixated views"
    )
    uuid: str | None = None


class CameraSpec(CameraSteering, _Strict):
    mode: Literal["generate", "provided", "object", "capture"] = Field(
        "generate", description="generate: Poisson-disc in free space; provided: poses; object: on a sphere; "
        "capture: the cameras of the posed capture next to the scan (services.core.ingest.capture)"
    )
    min_spacing_m: float = Field(0.5, gt=0, le=100, description="Poisson-disc minimum spacing")
    height_min_m: float = Field(0.2, ge=0, le=100, description="camera height above the floor, lower bound")
    height_max_m: float = Field(2.0, gt=0, le=100, description="camera height above the floor, upper bound")
    clearance_m: float = Field(0.1, ge=0, le=10, description="minimum distance from a camera to the mesh")
    max_count: int = Field(1000, ge=1, le=100_000, description="at most this many generated cameras")
    poses: list[ProvidedPose] | None = Field(
        None, max_length=MAX_PROVIDED_POSES, description="cameras for mode=provided"
    )
    object_count: int = Field(32, ge=1, le=100_000, description="cameras on the sphere (mode=object)")
    object_distance_factor: float = Field(
        2.0, gt=1.0, le=100, description="sphere radius / bounding-sphere radius (mode=object)"
    )
    # posed captures (issue 18): mode=capture
    capture_views: Literal["exact", "fixated"] = Field(
        "exact",
        description="exact: one view at each capture camera (its photo as RGB); fixated: the usual points "
        "and views from the capture positions (the photo turned by a rotation homography)",
    )
    capture_fov_deg: float | None = Field(
        None, ge=FOV_LIMITS_DEG[0], le=FOV_LIMITS_DEG[1],
        description="field of view of exact capture views; None: the widest square the photo fills",
    )
    capture_refine: bool = Field(
        False, description="refine the capture's colour camera (focal length, principal point, offset) by "
        "maximising the photo/geometry alignment score before planning; recorded in job.json"
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


class ViewSpec(ViewSteering, _Strict):
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
        "point",
        description="point: every frame fixated on the point; ahead: look along the path (walk-through)",
    )
    trajectory_max_turn_deg_per_m: float = Field(
        60.0, gt=0, le=3600, description="largest turn of the direction of motion per metre of path"
    )
    trajectory_max_view_deg_per_m: float = Field(
        30.0, gt=0, le=3600, description="largest rotation of the camera (view and roll) per metre of path"
    )
    trajectory_min_frames: int = Field(
        1, ge=1, le=100_000,
        description="a clip shorter than this (cut by the limits, or a short route) is dropped (reported)",
    )
    # holes in scans (issue 9): views predicted to see too little surface are dropped at planning time
    min_valid_fraction: float = Field(
        0.0, ge=0, le=1,
        description="drop views whose share of pixels with a surface (a low-resolution ray cast "
        "at planning time) is below this; 0 keeps all, as Omnidata",
    )

    # posed captures (issue 18)
    rgb_source: Literal["auto", "mesh", "photos"] = Field(
        "auto",
        description="rgb from the mesh texture or the capture's photos; auto: photos for cameras.mode "
        "capture, else the mesh",
    )
    min_alignment: float = Field(
        0.0, ge=0, le=100,
        description="drop capture views whose photo/geometry alignment score is below this "
        "(~1 is chance; 0 keeps all)",
    )
    min_photo_coverage: float = Field(
        0.5, ge=0, le=1, description="drop views whose share of pixels the photos cover is below this "
        "(capture views and rgb_source photos)"
    )
    photo_count: int = Field(3, ge=1, le=16, description="photos blended per pixel for rgb_source photos")

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
    """Parameters of the cue derivations (clip ranges, scales, thresholds)."""

    depth_units_per_m: float = Field(512.0, gt=0, le=1e6, description="depth PNG units per metre")
    max_depth_m: float = Field(128.0, gt=0, le=10_000, description="deeper surfaces are 'no surface'")
    curvature_clip_m: float = Field(0.03, gt=0, le=100, description="k1,k2 clipped to +-1/curvature_clip_m")
    curvature_radius_m: float = Field(
        0.05, gt=0, le=5, description="neighbourhood radius of curvature fitting (its cost grows with it)"
    )
    reshading_albedo: float = Field(0.8, gt=0, le=1, description="constant grey albedo")
    position_compression: Literal["none", "zip"] = Field(
        "none", description="position EXR codec: none (every EXR reader opens it; 3.2 MB at 512 px) or zip "
        "(lossless, ~1.9 MB, ~21 CPU-ms more per view); both decode to the same floats",
    )
    edge_texture_sigma: float = Field(2.0, ge=0, le=50, description="Gaussian blur before Sobel")
    edge_occlusion_sigma: float = Field(1.0, ge=0, le=50, description="blur of sqrt(depth) before Sobel")
    keypoints2d_sigmas: Annotated[
        tuple[Annotated[float, Field(gt=0, le=MAX_SIGMA_PX)], ...], BeforeValidator(_list_as_tuple)
    ] = Field(
        (1.0, 2.0, 4.0, 8.0), min_length=1, max_length=MAX_KEYPOINT_SCALES, description="blob scales, px"
    )
    keypoints3d_support_m: float = Field(0.1, gt=0, le=10, description="NARF-like support size")
    segment2d_scale: float = Field(200.0, gt=0, le=1e6)
    segment2d_sigma: float = Field(
        0.8, ge=0, le=MAX_SIGMA_PX, description="Gaussian blur before Felzenszwalb, px"
    )
    segment2d_min_size: int = Field(50, ge=1, le=MAX_RESOLUTION**2)
    segment_ncut_thresh: float = Field(0.005, gt=0, le=10)
    segment25d_weights: Annotated[
        tuple[Annotated[float, Field(ge=0, le=1000)], Annotated[float, Field(ge=0, le=1000)],
              Annotated[float, Field(ge=0, le=1000)]],
        BeforeValidator(_list_as_tuple),
    ] = Field(
        (1.0, 1.0, 1.0), description="weights of log-depth, normals, occlusion edges"
    )
    edge_scale: float = Field(
        1000.0, gt=0, le=1e9,
        description="16-bit edge images (edge_texture, edge_occlusion) store round(response * edge_scale)",
    )
    keypoints2d_scale: float = Field(
        250_000.0, gt=0, le=1e12,
        description="keypoints2d stores round(DoH response * scale); the DoH of a [0,1] image peaks near "
        "0.06-0.25",
    )
    segment_max_superpixels: int = Field(
        512, ge=2, le=4096,
        description="Felzenszwalb regions before normalized cuts, at most (bounds the cost)",
    )
    segment_ncut_sigma: float = Field(
        255.0, gt=0, le=1e9,
        description="RAG similarity exp(-|mean difference|^2 / sigma), features on a 0..255 scale",
    )
    segment_num_cuts: int = Field(10, ge=1, le=100, description="thresholds tried per normalized cut")
    augment: AugmentParams = Field(
        AugmentParams(), description="distributions of the 3D augmentation cues' parameters"
    )


class JobSpec(_Strict):
    """What to generate: the steering knobs of a job."""

    name: str = Field("omnidata", description="component name in the output layout")
    cues: list[str] | None = Field(
        None, max_length=256, description="subset of the catalog; None = all the space supports"
    )
    seed: int = Field(0, ge=0, le=2**63 - 1)
    # --- space frame: how source coordinates become world metres, +Z up
    up_axis: Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"] = Field(  # UP_AXES
        "auto", description="source axis that points up; auto detects floors in any orientation"
    )
    unit_scale: float | Literal["auto"] = Field(
        "auto",
        description="metres per source unit; auto: from the storey height of rooms (m, cm, mm or inches)",
        json_schema_extra={
            "anyOf": [{"type": "number", "exclusiveMinimum": 0, "maximum": MAX_UNIT_SCALE}, {"const": "auto"}]
        },
    )
    up: Vector3 | None = Field(
        None, description="up direction in source coordinates, instead of up_axis"
    )
    source_to_world: Matrix4 | None = Field(
        None, description="4x4 source -> world metres (+Z up): rotation, uniform scale, translation; "
        "overrides detection, up and unit_scale"
    )
    accept_up_guess: bool = Field(
        False,
        description="when detection cannot tell two up candidates apart, plan on the better one anyway "
        "(default: refuse the space, naming both candidates); likewise when more than one unit "
        "(cm or inches) makes the scan plausible: plan in the better one",
    )
    # ---
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

    @field_validator("unit_scale", mode="plain")
    @classmethod
    def _unit_scale(cls, v: object) -> float | str:
        return parse_unit_scale(v)

    @field_validator("up")
    @classmethod
    def _up(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None and (not all(math.isfinite(x) for x in v) or math.hypot(*v) < 1e-9):
            raise ValueError(f"up {list(v)} must be a finite, non-zero direction [x, y, z]")
        return v

    @field_validator("source_to_world")
    @classmethod
    def _source_to_world(cls, v: tuple[Row4, ...] | None) -> tuple[Row4, ...] | None:
        if v is not None:
            similarity_scale(v)
        return v

    def uses_photos(self) -> bool:
        """True when rgb comes from the capture's photos (rgb_source photos, or auto with capture cameras)."""
        return self.views.rgb_source == "photos" or (
            self.views.rgb_source == "auto" and self.cameras.mode == "capture"
        )

    def space_frame(self) -> SpaceFrame:
        """The keyword arguments of `services.core.ingest.loading.load_space` that set the space frame."""
        return {"up_axis": self.up_axis, "unit_scale": self.unit_scale, "up": self.up,
                "source_to_world": self.source_to_world, "accept_up_guess": self.accept_up_guess}

    @model_validator(mode="after")
    def _check(self) -> JobSpec:
        if self.source_to_world is not None:
            given = [f for f, default in (("up_axis", "auto"), ("unit_scale", "auto"), ("up", None))
                     if getattr(self, f) != default]
            if given:
                raise ValueError(f"source_to_world sets the whole frame: leave {', '.join(given)} unset")
        if self.up is not None and self.up_axis != "auto":
            raise ValueError("give either up (a vector) or up_axis (an axis name), not both")
        if self.cues is not None and "mask_photo" in self.cues and not self.uses_photos():
            raise ValueError(
                "cue 'mask_photo' needs rgb from photos: cameras.mode capture or views.rgb_source photos"
            )
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
        self._check_plan_size()
        return self

    def views_upper_bound(self) -> int:
        """Most views one space of this spec can plan (points x views per point)."""
        return self.plan_size()[0]

    def camera_count_bound(self) -> int:
        """Most cameras one space of this spec can have (capture: its poses, counted when planned: 0 here)."""
        cams = self.cameras
        return {"generate": cams.max_count, "object": cams.object_count}.get(cams.mode, len(cams.poses or ()))

    def plan_size(self) -> tuple[int, int, int, str]:
        """(views upper bound, points, views per point, the knob that bounds views per point)."""
        pts = self.points
        n_cameras = self.camera_count_bound()
        n_points = pts.count if pts.count is not None else math.ceil(pts.per_camera * n_cameras)
        if self.views.mode == "trajectory":
            per_point, what = self.views.trajectory_max_frames, "views.trajectory_max_frames"
        else:
            per_point = min(pts.max_views or n_cameras, n_cameras)
            what = "points.max_views" if pts.max_views is not None else "the camera count"
        return n_points * per_point, n_points, per_point, what

    def _check_plan_size(self) -> None:
        """Refuse a spec whose plan could exceed MAX_PLANNED_VIEWS (its rows and tasks would exhaust memory)
        or whose point sampling could draw more than MAX_SAMPLE_BUDGET samples (hours of ray casts)."""
        pts = self.points
        _views, n_points, per_point, what = self.plan_size()
        if n_points * pts.max_tries_per_point > MAX_SAMPLE_BUDGET:
            raise ValueError(
                f"{n_points} points x points.max_tries_per_point ({pts.max_tries_per_point}) could draw "
                f"{n_points * pts.max_tries_per_point:,} surface samples, above the limit of "
                f"{MAX_SAMPLE_BUDGET:,}: lower one of them"
            )
        if n_points * per_point > MAX_PLANNED_VIEWS:
            source = "points.count" if pts.count is not None else "points.per_camera x cameras"
            raise ValueError(
                f"{source} ({n_points} points) x {what} ({per_point} views per point) could plan "
                f"{n_points * per_point:,} views, above the limit of {MAX_PLANNED_VIEWS:,}: "
                "lower the point count or set points.max_views"
            )


Resolution = Annotated[int, Field(ge=MIN_RESOLUTION, le=MAX_RESOLUTION)]


def cues_for_space(spec: JobSpec, *, has_semantics: bool) -> list[str]:
    """The output cues a job renders for one space; raises ValueError naming unsupported cues."""
    from services.core.domain.cues import default_cues, require_supported

    if spec.cues is None:
        return default_cues(has_semantics) + (["mask_photo"] if spec.uses_photos() else [])
    require_supported(spec.cues, has_semantics=has_semantics)
    return list(spec.cues)
