"""The command line's own error: a user mistake in the arguments of an `omnidata` command."""

from __future__ import annotations


class CliError(Exception):
    """A user mistake on the command line; printed as `omnidata COMMAND: error: ...`, exit status 2."""
