"""A stand-in for the designer's warm process: answers each request after `payload["sleep"]` seconds."""

from __future__ import annotations

import os
import time
from multiprocessing.connection import Connection


def serve(conn: Connection) -> None:
    """Answer ("ok", {"pid": ...}) to each request until the pool closes the socket."""
    while True:
        try:
            _kind, payload = conn.recv()
        except (EOFError, OSError):
            return
        time.sleep(float(payload.get("sleep", 0)))
        conn.send(("ok", {"pid": os.getpid()}))
