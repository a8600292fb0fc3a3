"""Domain errors: a request the service refuses, with a message meant for the person who made it.

Library code raises these and never knows who asked; the edges map them: the API's one exception handler
(services.api.errors) to an HTTP status, the command line (services.cli.main) to exit status 2 and one line
`omnidata COMMAND: error: MESSAGE`.
"""

from __future__ import annotations


class DomainError(Exception):
    """A refused request, said in a message for the user (never a bug: those stay ordinary exceptions)."""


class Invalid(DomainError, ValueError):
    """The input cannot be used as given (HTTP 422)."""


class NotFound(DomainError, LookupError):
    """The thing asked for does not exist, or is not the caller's to see (HTTP 404)."""


class Conflict(DomainError):
    """The request clashes with the current state (HTTP 409): a name taken, a job in the wrong state."""


class Forbidden(DomainError):
    """The caller may not do this (HTTP 403), e.g. a signed link that expired."""


class TooLarge(DomainError):
    """The input is over a configured size limit (HTTP 413)."""


class TooManyRequests(DomainError):
    """The caller is over a per-tenant rate or concurrency limit (HTTP 429, with Retry-After)."""

    def __init__(self, message: str, *, retry_after_s: int = 1) -> None:
        super().__init__(message)
        self.retry_after_s = max(1, int(retry_after_s))
