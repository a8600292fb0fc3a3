"""The one-line refusals that name a frame's candidates (up, units) from their records, and the flag that
picks one: the same words when a scan is loaded and when a job over a space with an ambiguous frame is
refused."""

from __future__ import annotations

from services.core.domain.frame_records import UnitCandidateRecord, UpCandidateRecord


def _candidate_words(rec: UpCandidateRecord) -> str:
    up = ",".join(f"{x:.3g}" for x in rec["up"])
    if "floor_area_m2" in rec:
        return f"up {up} (floor {rec['floor_area_m2']:.3g} m2, storey {rec['storey_height_m']:.3g} m)"
    return (f"up {up} (floor {rec['floor_area_units2']:.4g} units2, "
            f"storey {rec['storey_height_units']:.4g} units)")


def ambiguity_line(name: str, candidates: list[UpCandidateRecord], margin: float | None) -> str:
    """One line naming both candidates (and a third, when recorded; source coordinates) and the flag that
    picks one."""
    first, second = candidates[0], candidates[1]
    by = "" if margin is None else f" by only {margin:.2f}"
    third = f" (next: {_candidate_words(candidates[2])})" if len(candidates) > 2 else ""
    return (f"{name}: up is ambiguous: {_candidate_words(first)} beats "
            f"{_candidate_words(second)}{by}{third}; "
            f"pick one with --up=X,Y,Z (e.g. --up={','.join(f'{x:.3g}' for x in first['up'])}; API: spec "
            "field up or the space's chosen up), or accept the guess with --accept-up-guess "
            "(accept_up_guess)")


def units_ambiguity_line(name: str, candidates: list[UnitCandidateRecord]) -> str:
    """One line naming each candidate unit, what it makes the scan, and the flag that picks one."""
    words = [f"{c['unit']} (--unit-scale={c['unit_scale']:g}: storey {c['storey_height_m']:.3g} m, "
             f"{' x '.join(f'{x:.3g}' for x in c['extent_m'])} m)" for c in candidates]
    return (f"{name}: units are ambiguous: {' or '.join(words)}; pick one with --unit-scale=M "
            "(metres per unit; API: spec field unit_scale), or accept the guess with --accept-up-guess "
            "(accept_up_guess)")
