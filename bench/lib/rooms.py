"""The real rooms the cost benchmarks load in-process.

name -> (space path, load_space frame arguments). The kitchen's fused mesh ships its gravity direction; up is
its negative, as bench/render/room_cost.py gives it to `generate`. The copy room's up is the measured one
(bench/scans/copyroom/SOURCE.md).
"""

from __future__ import annotations

from pathlib import Path

SCENES = Path(__file__).resolve().parents[3] / "shared" / "scenes"
SCANS = Path(__file__).resolve().parents[1] / "scans"  # real scans the project carries (each with SOURCE.md)
ROOMS: dict[str, tuple[Path, dict]] = {
    "icl_livingroom": (SCENES / "icl_livingroom", {}),
    "7scenes_redkitchen": (SCENES / "7scenes_redkitchen" / "mesh_tsdf_2cm_from_1000frames.ply",
                           {"up": (0.009, -0.904, -0.427)}),
    "copyroom": (SCANS / "copyroom", {"up": (-0.0023, -0.8052, -0.5930)}),
}
