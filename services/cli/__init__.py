"""`omnidata` command line: the command table (main.py) and one module per command.

Only this package turns errors into exit codes and one-line messages; library code raises domain errors.
"""

from services.cli.errors import CliError
from services.cli.main import main

__all__ = ["CliError", "main"]
