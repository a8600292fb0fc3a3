"""One horizontal plane and no opposite one (a floor without its ceiling, or a ceiling-only capture): the
geometry cannot tell its sign with certainty, and a levelled file's positive axis can
(services.core.ingest.frame.up_evidence: `mirror`, the sign of `levelled_axis`)."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.ingest.frame.candidates import CandidateFacts, FileFrame
from services.core.ingest.frame.reason_words import reason_words
from services.core.ingest.frame.single_view import SingleView
from services.core.ingest.frame.up_evidence import (
    CAMERA_SPLIT_MIN,
    MIRROR_CAP,
    MIRROR_CAP_CLOUD,
    REFUSE_MARGIN,
    SINGLE_VIEW_REFUSE_MARGIN,
    decide,
)

Z = np.array([0.0, 0.0, 1.0])
X = np.array([1.0, 0.0, 0.0])


def _facts(up: np.ndarray, floor: float, ceiling: float, mid_up: float, mid_down: float,
           height: float = 3.0, cross: float = 100.0, origin_split: float = 0.0,
           origin_height: float = 0.0, origin_gaze: float = 0.0) -> CandidateFacts:
    area = floor * cross
    return CandidateFacts(up, area + max(0.0, mid_up - mid_down), area, floor, height, cross, ceiling,
                          mid_up, mid_down, origin_split, origin_height, origin_gaze)


def _room(one_side: np.ndarray, pair: bool, origin_split: float = 0.0, origin_height: float = 1.5,
          height: float = 3.0, origin_gaze: float = 0.0, width: float = 1.0) -> list[CandidateFacts]:
    """A plane at the low end of `one_side` with tops over it (what stands on a floor or hangs below a
    ceiling), walls along X; `pair`: a second plane at the other end too. `origin_split`: the smaller share of
    the scan on either side of the origin's height along the plane's normal; `origin_height`: the origin's
    height over the plane along `one_side`; `height`: the scan's extent along it; `origin_gaze`: the sine of
    the elevation of the origin's mean gaze along `one_side`; `width`: its lengths across, in the units of a
    room 3 wide and 10 long."""
    other = 0.5 if pair else 0.0
    cross = 100.0 * width**2
    return [_facts(one_side, 0.5, other, 8.0, 0.2, height, cross, origin_split=origin_split,
                   origin_height=origin_height, origin_gaze=origin_gaze),
            _facts(-one_side, other, 0.5, 0.2, 8.0, height, cross, origin_split=origin_split,
                   origin_height=origin_height - height, origin_gaze=-origin_gaze),
            _facts(X, 0.02, 0.02, 0.0, 0.0, 10.0 * width, 30.0 * width**2),
            _facts(-X, 0.02, 0.02, 0.0, 0.0, 10.0 * width, 30.0 * width**2)]


def test_one_plane_caps_the_geometrys_sign_so_its_stated_probability_is_bounded() -> None:
    d = decide(_room(-Z, pair=False))
    assert float(d.best.up @ -Z) > 0.99
    flip = next(c for c in d.ranked if float(c.up @ Z) > 0.99)
    assert flip.terms["mirror"] > 0
    assert d.runner_up is flip and d.margin == pytest.approx(MIRROR_CAP)
    assert d.confidence < 0.95
    assert not d.ambiguous and MIRROR_CAP >= REFUSE_MARGIN  # a floor-only room is still levelled


def test_a_floor_with_its_ceiling_keeps_the_geometrys_sign_uncapped() -> None:
    d = decide(_room(Z, pair=True))
    assert float(d.best.up @ Z) > 0.99
    assert all("mirror" not in c.terms for c in d.ranked)
    assert d.margin > MIRROR_CAP


def test_a_levelled_file_with_one_plane_follows_its_positive_axis() -> None:
    """The plane at the top along +Z with fixtures below it (a ceiling-only capture exported Z-up): the file's
    levelling gives +Z, not the geometry's 'floor seen from above'."""
    d = decide(_room(-Z, pair=False), file=FileFrame(Z))
    assert float(d.best.up @ Z) > 0.99
    assert d.best.terms["levelled_axis"] > 0
    assert next(c for c in d.ranked if float(c.up @ -Z) > 0.99).terms["levelled_axis"] == 0.0
    assert not d.ambiguous
    assert "the file was levelled" in reason_words(d)


def test_the_sign_prior_holds_on_the_formats_up_axis() -> None:
    y = np.array([0.0, 1.0, 0.0])
    for file in (FileFrame(Z), FileFrame(y), FileFrame(y, True)):  # a Z-up PLY, a Y-up OBJ, a glTF
        d = decide(_room(-file.axis, pair=False), file=file)
        assert float(d.best.up @ file.axis) > 0.99 and not d.ambiguous, file


def test_a_ply_in_a_level_cameras_frame_keeps_the_geometrys_sign() -> None:
    """A floor without its ceiling in a level first camera's frame (y down, a PLY): -Y is as much a levelled
    up as +Y, so the furniture decides, and the stated probability stays bounded (`mirror`)."""
    y = np.array([0.0, 1.0, 0.0])
    d = decide(_room(-y, pair=False), file=FileFrame(Z))
    assert float(d.best.up @ -y) > 0.99
    assert d.best.terms["levelled_axis"] > 0


def test_a_levelled_floor_and_ceiling_on_a_negative_axis_keep_the_geometrys_sign() -> None:
    """A room in a camera's frame (y down) held level: with its ceiling scanned, the furniture between the two
    planes decides the sign, the file's positive axis does not."""
    y = np.array([0.0, 1.0, 0.0])
    d = decide(_room(-y, pair=True), file=FileFrame(Z))
    assert float(d.best.up @ -y) > 0.99
    assert not d.ambiguous


def test_a_point_clouds_geometry_orders_its_two_signs_but_never_decides() -> None:
    """A cloud's sides come from estimated normals: the same one-plane room as a cloud is refused, its
    geometry's sign first, where as a mesh it is levelled."""
    d = decide(_room(-Z, pair=False), file=FileFrame(X, cloud=True))
    assert d.ambiguous
    assert float(d.best.up @ -Z) > 0.99 and d.margin == pytest.approx(MIRROR_CAP_CLOUD)
    assert not decide(_room(-Z, pair=False), file=FileFrame(X)).ambiguous


def test_a_clouds_sides_seen_from_its_camera_within_the_scan_decide_like_a_meshs() -> None:
    """A cloud whose origin is its camera's place (its normals turned towards it) and which lies on both
    sides of that camera's height (the camera looked across the room) has its sides as a mesh has them: its
    one plane's sign is decided by its geometry. A camera that saw the scan on one side of its height only
    (looking up at a ceiling, or down at a floor) leaves it refused."""
    across = FileFrame(X, cloud=True, origin_camera=True)
    d = decide(_room(-Z, pair=False, origin_split=CAMERA_SPLIT_MIN + 0.1), file=across)
    assert float(d.best.up @ -Z) > 0.99 and not d.ambiguous and d.margin == pytest.approx(MIRROR_CAP)
    assert decide(_room(-Z, pair=False, origin_split=CAMERA_SPLIT_MIN / 2), file=across).ambiguous
    # the same split with an origin that is no camera: the sides are a guess
    no_camera = FileFrame(X, cloud=True)
    assert decide(_room(-Z, pair=False, origin_split=CAMERA_SPLIT_MIN + 0.1), file=no_camera).ambiguous


def test_a_plane_further_below_the_camera_than_a_storey_is_ordered_as_a_ceiling_never_decided() -> None:
    """A ceiling-only capture whose camera, at the origin, stood 4.5 m under the ceiling: read as a floor, the
    camera would have been held 4.5 m above it, higher than a storey; read as a ceiling, it stood under a tall
    one. The camera's height orders the two signs of a cloud's one plane (the ceiling first), and decides
    nothing alone, nor against one habit of the file (`camera_height`)."""
    camera = FileFrame(X, cloud=True, origin_camera=True)
    d = decide(_room(-Z, pair=False, origin_height=4.5), file=camera)
    assert float(d.best.up @ Z) > 0.99 and d.ambiguous  # asked, the ceiling reading first
    assert next(c for c in d.ranked if float(c.up @ -Z) > 0.99).terms["camera_height"] < 0
    assert d.best.terms["camera_height"] == 0.0
    # a camera held 1.5 m over the plane: the geometry's order stands
    assert float(decide(_room(-Z, pair=False), file=camera).best.up @ -Z) > 0.99
    # no camera at the origin: its height says nothing
    no_camera = decide(_room(-Z, pair=False, origin_height=4.5), file=FileFrame(X, cloud=True))
    assert float(no_camera.best.up @ -Z) > 0.99
    # 110 units tall, the camera 180 units up: 1.1 m and 1.8 m in centimetres, a floor seen from a camera
    # held by hand; only in inches (2.8 m, 4.6 m) too high. One unit where it fits is enough
    short = decide(_room(-Z, pair=False, origin_height=180.0, height=110.0, width=110.0 / 3.0), file=camera)
    assert float(short.best.up @ -Z) > 0.99
    # a floor seen from 4.5 m above whose file looks like an upside-down camera's frame (a habit for the
    # ceiling reading): an origin above a room without its ceiling may be no camera, so the two together
    # still ask (the geometry's capped lead, the camera's height and one habit)
    y = np.array([0.0, 1.0, 0.0])
    framed = decide(_room(y, pair=False, origin_height=4.5),
                    file=FileFrame(Z, cloud=True, camera=True, origin_camera=True))
    assert float(framed.best.up @ -y) > 0.99 and framed.best.terms["camera_frame"] > 0
    assert framed.ambiguous


def test_a_camera_that_looked_down_from_a_hands_height_decides_a_clouds_one_plane() -> None:
    """A floor-only cloud whose camera, at the origin 1.5 m over the floor, saw everything below itself
    looking 30 degrees down: read upside down, the same camera looked up at a ceiling from just below it.
    Hand-held captures look level or down, so the floor reading is levelled (`camera_looked_down`). Looking
    straight down (a wall the camera faced), held higher than a storey, or an origin that is no camera leave
    the cloud's sign capped, and asked."""
    camera = FileFrame(X, cloud=True, origin_camera=True)
    down = -float(np.sin(np.radians(30.0)))
    d = decide(_room(Z, pair=False, origin_gaze=down), file=camera)
    assert float(d.best.up @ Z) > 0.99 and not d.ambiguous
    assert d.best.terms["camera_looked_down"] > 0 and d.runner_up.terms["camera_looked_down"] == 0.0
    # a camera that looked up at the scan looked down at nothing: asked
    up = decide(_room(Z, pair=False, origin_gaze=-down), file=camera)
    assert up.ambiguous and all(c.terms["camera_looked_down"] == 0.0 for c in up.ranked)
    straight_down = -float(np.sin(np.radians(70.0)))
    assert decide(_room(Z, pair=False, origin_gaze=straight_down), file=camera).ambiguous
    assert decide(_room(Z, pair=False, origin_gaze=down, origin_height=4.0), file=camera).ambiguous
    assert decide(_room(Z, pair=False, origin_gaze=down), file=FileFrame(X, cloud=True)).ambiguous
    # saw a share of the scan above its height: the cloud's sides decide (`_mirror_cap`), not this
    across = decide(_room(Z, pair=False, origin_gaze=down, origin_split=CAMERA_SPLIT_MIN), file=camera)
    assert across.best.terms["camera_looked_down"] == 0.0
    # looked down so at a wall too (a fragment cut to a cube): neither is told from a floor
    cube = [*_room(Z, pair=False, origin_gaze=down),
            _facts(X, 0.5, 0.0, 8.0, 0.2, origin_height=1.5, origin_gaze=-0.7)]
    assert all(c.terms["camera_looked_down"] == 0.0 for c in decide(cube, file=camera).ranked)
    # ... unless that wall stood further from the camera than anyone holds one over a floor
    far = [*cube[:-1], _facts(X, 0.5, 0.0, 8.0, 0.2, origin_height=4.5, origin_gaze=-0.7)]
    assert decide(far, file=camera).best.terms["camera_looked_down"] > 0
    # 140 units tall, the camera 130 up: in centimetres 1.3 m, in inches 3.3 m, both under a storey; 150
    # units tall, the camera 140 up: 3.6 m in inches, higher than a storey in one unit, so it says nothing
    def looked_down(origin_height: float, height: float) -> float:
        ranked = decide(_room(Z, pair=False, origin_gaze=down, origin_height=origin_height, height=height),
                        file=camera).ranked
        return next(c for c in ranked if float(c.up @ Z) > 0.99).terms["camera_looked_down"]
    assert looked_down(130.0, 140.0) > 0 and looked_down(140.0, 150.0) == 0.0


def test_an_upright_cameras_frame_with_the_geometry_decides_a_clouds_sign() -> None:
    """The same cloud stored in a camera's frame (y down): where its geometry and the upright camera's -Y
    agree, it is levelled; where they disagree (an underside read as a top, or an upside-down camera's frame),
    it is refused with the camera's sign first."""
    y = np.array([0.0, 1.0, 0.0])
    d = decide(_room(-y, pair=False), file=FileFrame(Z, cloud=True, camera=True))
    assert float(d.best.up @ -y) > 0.99 and not d.ambiguous
    assert d.best.terms["camera_frame"] > 0
    d = decide(_room(y, pair=False), file=FileFrame(Z, cloud=True, camera=True))
    assert d.ambiguous and float(d.best.up @ -y) > 0.99


def test_a_single_frames_wall_the_camera_faced_is_never_planned_on_however_far_it_leads() -> None:
    """A depth frame of a wall: its only family is the wall and its mirror image, both across the view's
    direction, so the one seen from the camera leads by the whole wall's area; that lead says which side the
    camera stood on, not where up is."""
    ahead = np.array([0.0, 1.0, 0.0])
    view = SingleView(direction=ahead, short_axis=Z)
    wall = [_facts(-ahead, 0.6, 0.0, 8.0, 0.0), _facts(ahead, 0.0, 0.6, 0.0, 8.0)]
    d = decide(wall, view=view)
    assert float(d.best.up @ -ahead) > 0.99 and d.best.terms["view_direction"] < 0
    assert d.margin > SINGLE_VIEW_REFUSE_MARGIN
    assert d.ambiguous
    # the same lead across the view's direction (a floor seen from a level camera) is planned on
    floor = [_facts(Z, 0.6, 0.0, 8.0, 0.0), _facts(-Z, 0.0, 0.6, 0.0, 8.0)]
    level = decide(floor, view=view)
    assert float(level.best.up @ Z) > 0.99 and not level.ambiguous
