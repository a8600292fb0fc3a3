"""The ingest error: a space that cannot be used, with a message for the user who uploaded it.

Its own module so the checks that run before parsing (mesh_checks) and the loader can both raise it
without importing each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from services.core.domain.errors import Invalid

if TYPE_CHECKING:
    from services.core.domain.frame_records import UnitCandidateRecord, UpCandidateRecord


class SpaceError(Invalid):
    """A space that cannot be used, with a message meant for the user who uploaded it."""


class FrameAmbiguous(SpaceError):
    """Detection could not decide the frame (up or units); the message names the candidates and the flag that
    picks one."""

    def __init__(self, message: str, candidates: list[UpCandidateRecord] | list[UnitCandidateRecord]):
        super().__init__(message)
        self.candidates = candidates


class UpAmbiguous(FrameAmbiguous):
    """Up detection could not tell two candidates apart; the message names both and the flag that picks
    one."""


class UnitsAmbiguous(FrameAmbiguous):
    """More than one unit makes the scan plausible; the message names each (storey and extent) and
    --unit-scale."""
