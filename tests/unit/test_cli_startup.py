"""The ``afbl`` command answers ``--help`` (every subcommand's too) without importing JAX, the
studies' numerics, scipy, pyarrow or matplotlib; the package's public names are imported on
first use and stay the same."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

import afbl_jax
from afbl_jax.cli import SUBCOMMANDS

HEAVY = ("jax", "jaxlib", "equinox", "diffrax", "scipy", "pyarrow", "matplotlib")

_CHECK = """
import contextlib, io, json, sys
from afbl_jax.cli import main
codes = {}
for argv in json.loads(sys.argv[1]):
    with contextlib.redirect_stdout(io.StringIO()) as out:
        codes[" ".join(argv)] = [main(argv), len(out.getvalue())]
heavy = sorted({m.split(".")[0] for m in sys.modules} & set(json.loads(sys.argv[2])))
print(json.dumps({"codes": codes, "heavy": heavy}))
"""


def _subcommands() -> list[str]:
    parser = afbl_jax.cli.build_parser()
    (sub,) = [a for a in parser._actions if a.dest == "command"]
    return sorted(sub.choices)


def test_help_imports_no_jax():
    commands = _subcommands()
    assert len(commands) >= len(SUBCOMMANDS)
    argvs = [["--help"]] + [[c, "--help"] for c in commands]
    r = subprocess.run(
        [sys.executable, "-c", _CHECK, json.dumps(argvs), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout.strip().splitlines()[-1])
    for argv, (code, chars) in result["codes"].items():
        assert code == 0 and chars > 100, (argv, code, chars)  # help text printed, exit 0
    assert result["heavy"] == [], result["heavy"]


def test_help_command_line_time():
    """``python -m afbl_jax.cli --help`` as a user runs it (the time is printed: it depends on
    the machine's load; the import check above is what must hold)."""
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "afbl_jax.cli", "--help"], capture_output=True, text=True
    )
    seconds = time.perf_counter() - t0
    print(f"python -m afbl_jax.cli --help: {seconds:.2f} s")
    assert r.returncode == 0 and "montecarlo" in r.stdout, r.stderr
    assert seconds < 10.0


def test_lazy_public_names():
    code = (
        "import sys, afbl_jax; assert 'jax' not in sys.modules; "
        "n = len(afbl_jax.__all__); f = afbl_jax.simulate; "
        "print(n, 'jax' in sys.modules, f.__module__)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    n, jax_loaded, module = r.stdout.split()
    assert int(n) > 50 and jax_loaded == "True" and module.startswith("afbl_jax.sim")
    missing = [name for name in afbl_jax.__all__ if getattr(afbl_jax, name, None) is None]
    assert missing == []
    assert set(afbl_jax.__all__) <= set(dir(afbl_jax))
    assert afbl_jax.sim.simulate is afbl_jax.simulate
    try:
        afbl_jax.no_such_name  # noqa: B018
    except AttributeError as err:
        assert "no_such_name" in str(err)
    else:
        raise AssertionError("an unknown name must raise AttributeError")


def test_bench_row_names_match_the_benchmark():
    from afbl_jax.studies import bench, bench_rows

    assert tuple(bench.BATCH_STRATEGIES) == bench_rows.BATCH_ROWS
    assert bench.ALL_STRATEGIES == bench_rows.ALL_STRATEGIES


@pytest.mark.slow
def test_montecarlo_phases_add_up_to_the_command_wall_time(tmp_path):
    """``afbl montecarlo`` records its start-up phase (from the process's start) and phases
    that add up to the command's wall time as a user sees it."""
    dist = tmp_path / "short.toml"
    dist.write_text("[time]\nt1 = 2.0\n[pulses]\nstart = [0.5, 1.0]\n[gust]\nstart = [0.5, 1.0]\n")
    out = tmp_path / "mc"
    argv = ["montecarlo", "--cases", "8", "--chunk-size", "8", "--controllers", "afbl"]
    argv += ["--distribution", str(dist), "--no-progress", "--out", str(out)]
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "afbl_jax.cli", *argv], capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    phases = json.loads((out / "meta.json").read_text())["phases_seconds"]
    print(phases, f"wall {wall:.2f} s")
    assert all(phases[k] > 0 for k in ("startup", "compilation", "report"))
    assert phases["runs"] >= 0
    assert phases["total"] == pytest.approx(wall, rel=0.1, abs=1.5)
    assert "time: start-up and imports" in r.stdout
