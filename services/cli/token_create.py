"""`omnidata token create --tenant NAME | --operator`: a new random API token and the settings entry to add.

Only the token's sha256 is kept in settings (OMNIDATA_API_TOKENS maps sha256 -> tenant;
OMNIDATA_OPERATOR_TOKENS lists operators' sha256, who see service-wide /metrics). The token itself is printed
once, here: store it.
"""

from __future__ import annotations

import argparse
import json
import re
import secrets
import shlex
import sys

from services.cli import CliError

TOKEN_BYTES = 32  # 256 bits of randomness, 43 URL-safe characters
TENANT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,127}$")


def new_token() -> str:
    """A random URL-safe token that does not start with '-': `--token -x...` would read as an option on a
    command line (argparse: "expected one argument"), and one token in 64 began so."""
    while (token := secrets.token_urlsafe(TOKEN_BYTES)).startswith("-"):
        pass
    return token


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `omnidata token`."""
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    create = sub.add_parser("create", help="print a new token and the settings entry that enables it")
    who = create.add_mutually_exclusive_group(required=True)
    who.add_argument(
        "--tenant", metavar="NAME", help="the tenant the token acts for (owner of its spaces and jobs)"
    )
    who.add_argument("--operator", action="store_true", help="an operator token: service-wide /metrics")


def run(args: argparse.Namespace) -> int:
    """Create a token: the token on stdout's first line, then the settings line to add (merged with the
    current)."""
    from services.core.settings import hash_token, load_settings

    if args.tenant is not None and not TENANT_NAME.match(args.tenant):
        raise CliError(f"--tenant {args.tenant!r}: use 1-128 letters, digits, '.', '_', '@' or '-', "
                       "starting with a letter or digit")
    settings = load_settings()  # the current entries, so the printed line keeps them
    token = new_token()
    digest = hash_token(token)
    if args.operator:
        variable, value = "OMNIDATA_OPERATOR_TOKENS", json.dumps([*settings.operator_tokens, digest])
        who = "an operator"
    else:
        variable, value = "OMNIDATA_API_TOKENS", json.dumps({**settings.api_tokens, digest: args.tenant})
        who = f"tenant {args.tenant!r}"
    print(token)
    print(f"{variable}={shlex.quote(value)}")
    print(
        f"omnidata token: the first line is a new token for {who}; it is shown only this once. Set "
        "the second line in the services' environment (it keeps the current entries) and restart them.",
        file=sys.stderr,
    )
    return 0
