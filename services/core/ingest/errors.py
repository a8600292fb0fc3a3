"""The ingest error: a space that cannot be used, with a message for the user who uploaded it.

Its own module so the checks that run before parsing (mesh_checks) and the loader can both raise it
without importing each other.
"""

from __future__ import annotations

from services.core.domain.errors import Invalid


class SpaceError(Invalid):
    """A space that cannot be used, with a message meant for the user who uploaded it."""
