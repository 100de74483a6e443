"""The tests marked ``default_codegen`` with XLA's default CPU code generator.

The suite compiles with XLA's classic CPU code generator (tests/conftest.py), which does not
keep the rounding of an operation the same between programs of different shapes. The tests
that assert two different programs agree bit for bit (the work queue against chunks, dense
output against SaveAt samples, the sampler against its variates) are left out of the run and
run here, in one pytest subprocess that compiles as the library does (``AFBL_TEST_CODEGEN=
default``), with the session's compilation cache.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from ..conftest import CODEGEN_ENV

ROOT = Path(__file__).resolve().parents[2]


def test_bitwise_checks_with_xlas_default_code_generator():
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("PYTEST_", "AFBL_TEST_COMPILE_LOG"))
    }
    env[CODEGEN_ENV] = "default"  # its conftest drops the classic code generator's flag
    command = [
        sys.executable,
        "-m",
        "pytest",
        "-n",
        "0",
        "-q",
        "-p",
        "no:cacheprovider",
        "-m",
        "default_codegen and not slow",
        "tests",
    ]
    proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    report = proc.stdout[-6000:] + proc.stderr[-2000:]
    assert proc.returncode == 0, report
    summary = proc.stdout.strip().splitlines()[-1]
    assert " passed" in summary and "failed" not in summary, report
