"""What a worker process loads: the OpenEXR module only when a task needs it (a ZIP-compressed position file),
as its load costs a worker ~0.09 CPU-s at every start and the default cues never need it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_worker_loads_openexr_only_for_a_zip_compressed_position():
    probe = (
        "import sys\n"
        "import services.embedded.pool, services.worker.run.runner, services.worker.cues.registry\n"
        "import numpy as np\nfrom services.worker.cues.encoding import encode_exr_rgb\n"
        "from services.core.domain.exr import decode_exr_rgb\n"
        "a = np.arange(48, dtype=np.float32).reshape(4, 4, 3)\nplain = encode_exr_rgb(a)\n"
        "print('OpenEXR' in sys.modules)\nzipped = encode_exr_rgb(a, 'zip')\n"
        "print('OpenEXR' in sys.modules, len(zipped) != len(plain), (decode_exr_rgb(zipped) == a).all())\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.stdout.split() == ["False", "True", "True", "True"]
