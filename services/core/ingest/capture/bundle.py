"""A scan and its capture sent as two parts (multipart upload: the scan file or zip, and a .zip of the
capture) put into one folder, which is then loaded and stored like a folder upload. Both archives are
extracted with the same zip checks as every upload (services.core.ingest.guard.archive.safe_extract_zip)."""

from __future__ import annotations

import shutil
from pathlib import Path

from services.core.ingest.guard.archive import safe_extract_zip


def bundle_scan_and_capture(scan: Path, capture_zip: Path, dest: Path) -> Path:
    """The folder `dest` holding the scan (a file, or what its zip holds) and the capture under `capture/`."""
    dest.mkdir(parents=True, exist_ok=True)
    if scan.suffix.lower() == ".zip":
        safe_extract_zip(scan, dest)
    else:
        shutil.copyfile(scan, dest / scan.name)
    safe_extract_zip(capture_zip, dest / "capture")
    return dest
