"""`--cpu-report N` (tests/fixtures/cpu_report.py) names the tests that used the most CPU, their children's
included, across pytest-xdist workers as `make test` runs them."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO_ROOT

TESTS = '''
import subprocess, sys, time

def test_busy_child():  # about 1 CPU-s, all of it in a child process the test waits for
    subprocess.run([sys.executable, "-c", "import time\\nt = time.process_time()\\n"
                    "while time.process_time() - t < 1.0: pass"], check=True)

def test_sleeps():  # as long, waiting
    time.sleep(1.0)

def test_busy_here():  # about 0.4 CPU-s in the test's own process
    t = time.process_time()
    while time.process_time() - t < 0.4:
        pass
'''


def test_the_report_ranks_tests_by_cpu_their_children_included(tmp_path: Path) -> None:
    (tmp_path / "test_cpu_cases.py").write_text(TESTS)
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "xdist.plugin", "-p", "tests.fixtures.cpu_report",
         "--cpu-report", "2", "-n", "2", "-p", "no:cacheprovider", "--rootdir", str(tmp_path),
         "-c", os.devnull, str(tmp_path)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        # only the plugins named here (the installed ones cost seconds a process to load)
        env={**os.environ, "PYTHONPATH": str(REPO_ROOT), "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"},
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    head = re.search(r"most CPU: 2 of 3 tests \(([\d.]+) CPU-s in all\)", run.stdout)
    rows = re.findall(r"^\s*([\d.]+) CPU-s  \S+::(\w+)$", run.stdout, re.M)
    assert head and [name for _, name in rows] == ["test_busy_child", "test_busy_here"], run.stdout[-2000:]
    child, here = (float(s) for s, _ in rows)
    assert 0.9 <= child <= 2.5 and 0.35 <= here < child
    # the sleeping test adds next to nothing (each figure is printed to 0.1: 0.05 of rounding apiece)
    assert child + here - 0.1 <= float(head.group(1)) < child + here + 0.5
