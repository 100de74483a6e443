"""Run the default test suite (`python -m pytest`, as CI does) and write the time of each test
file.

    python studies/test_times.py --out test_times.json

Runs pytest in the repository root with ``--durations=0`` and sums, per test file, the setup,
call and teardown seconds of its tests (worker time: with the default two worker processes,
each file on one of them, the files' times add up to about twice the wall time), and, from the
test processes' JAX events (``AFBL_TEST_COMPILE_LOG``, tests/conftest.py), the seconds spent
tracing and lowering, the XLA programs compiled (persistent-cache loads not counted), those of
them that took 1 s or more, and the XLA seconds; a test's subprocesses (`afbl` commands,
notebook kernels) are not in these counts. Writes OUT (JSON: ``wall_s``, ``cpu_s`` (user and
system seconds of pytest and the processes it waited for), ``exit_code``, ``passed``, ``failed``,
``skipped``, ``files``: one row per file with ``file``, ``tests``, ``seconds``,
``trace_lower_s``, ``compiled``, ``compiled_1s`` and ``xla_s``, slowest first) and prints the
table.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DURATION = re.compile(r"^\s*(?P<s>[0-9.]+)s (?P<when>setup|call|teardown)\s+(?P<id>\S+)")
COMPILE_KEYS = ("trace_lower_s", "compiled", "compiled_1s", "xla_s")
COUNTS = re.compile(r"(?P<n>\d+) (?P<what>passed|failed|skipped|deselected|errors?)\b")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="JSON file to write")
    parser.add_argument("pytest_args", nargs="*", help="extra arguments for pytest")
    args = parser.parse_args(argv)
    out = Path(args.out)
    command = [
        sys.executable,
        "-m",
        "pytest",
        "--durations=0",
        "--durations-min=0",
        "-q",
        *args.pytest_args,
    ]
    print(f"running {' '.join(command[1:])} in {ROOT} ...", flush=True)
    log = Path(tempfile.mkdtemp(prefix="afbl-test-compiles-"))
    env = {**os.environ, "AFBL_TEST_COMPILE_LOG": str(log)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    jax_work: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    for worker in log.glob("*.jsonl"):
        for line in worker.read_text().splitlines():
            row = json.loads(line)
            for key in COMPILE_KEYS:
                jax_work[row["id"].split("::", 1)[0]][key] += row.get(key, 0)
    shutil.rmtree(log, ignore_errors=True)
    seconds: dict[str, float] = defaultdict(float)
    tests: dict[str, set] = defaultdict(set)
    for line in proc.stdout.splitlines():
        m = DURATION.match(line)
        if m:
            path = m["id"].split("::", 1)[0]
            seconds[path] += float(m["s"])
            tests[path].add(m["id"])
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    counts = {
        m["what"].rstrip("s") if m["what"].startswith("error") else m["what"]: int(m["n"])
        for m in COUNTS.finditer(tail)
    }
    rows = sorted(
        (
            {
                "file": f,
                "tests": len(tests[f]),
                "seconds": round(s, 1),
                **{k: round(jax_work[f][k], 1) for k in COMPILE_KEYS},
            }
            for f, s in seconds.items()
        ),
        key=lambda r: -r["seconds"],
    )
    doc = {
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "exit_code": proc.returncode,
        "passed": counts.get("passed", 0),
        "failed": counts.get("failed", 0),
        "skipped": counts.get("skipped", 0),
        "files": rows,
    }
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(tail)
    for r in rows:
        print(
            f"{r['seconds']:8.1f} s  {r['tests']:4d} tests  trace+lower {r['trace_lower_s']:6.1f} s"
            f"  compiled {r['compiled']:5.0f} ({r['compiled_1s']:3.0f} >= 1 s)"
            f"  XLA {r['xla_s']:6.1f} s  {r['file']}"
        )
    print(
        f"wall {wall:.1f} s; worker time {sum(seconds.values()):.1f} s; "
        f"CPU time {cpu:.1f} s ({cpu / wall:.2f} cores busy on average)"
    )
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-5000:] + proc.stderr[-2000:])
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
