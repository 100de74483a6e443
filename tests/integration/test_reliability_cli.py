"""The real ``afbl`` command in subprocesses, as a new user runs it: solver failures, gains at
full precision, two runs into one folder, user errors (one line, exit 2, nothing written),
results that cannot fit, and generated bad input files.

In-process counterparts (cheaper, more cases): tests/unit/test_reliability.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import afbl_jax as A

from ..fuzz_inputs import bad_files

ROOT = Path(__file__).resolve().parents[2]


def _command() -> list[str]:
    """The installed ``afbl`` console script beside this Python (what a user runs); where it
    is missing, the same entry point through this Python."""
    script = Path(sys.executable).with_name("afbl")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from afbl_jax.cli import main; sys.exit(main())"]


def afbl(*args: str, cwd: Path | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*_command(), *args], capture_output=True, text=True, timeout=timeout, cwd=cwd
    )


def start(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [*_command(), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def assert_user_error(r, command: str, match: str) -> None:
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"afbl {command}: error: "), r.stderr
    assert match in lines[0], lines[0]


def _strict_json(text: str):
    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


def test_solver_failure_stops_where_it_failed(tmp_path):
    """The reported case: with inertia x 1e-9 and a start off the trim, every run stops after
    microseconds. The results say where (not t1) and why; the summary says "no successful
    runs" in words and holds null."""
    dist = tmp_path / "it.toml"
    dist.write_text(
        "[model_error]\ninertia_scale = [1e-9, 1e-9]\n[initial]\nattitude = [0.05, 0.1]\n"
    )
    out = tmp_path / "X"
    r = afbl(
        "montecarlo",
        "--cases",
        "4",
        "--chunk-size",
        "4",
        "--controllers",
        "fbl",
        "--distribution",
        str(dist),
        "--out",
        str(out),
        "--no-report",
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    cols = pq.read_table(out / "results.parquet").to_pydict()
    assert cols["status"] == ["solver_failed"] * 4
    assert all(0 < t < 1e-4 for t in cols["t_final"]), cols["t_final"]
    assert all(p > 0 for p in cols["peak_attitude_error"])  # the initial error, not 0.0
    summary = _strict_json((out / "summary.json").read_text())
    assert summary["controllers"]["fbl"]["ise_attitude"]["p50"] is None
    assert "no successful runs" in r.stdout and "nan" not in r.stdout


def test_gains_file_runs_at_full_precision(tmp_path):
    """The file's gains, exactly: docs/tuned_gains_afbl.json with k_z = 80.123456789012345 is
    recorded unrounded in ise.json and flown (its ISE is a float64 simulation's with them)."""
    data = json.loads((ROOT / "docs" / "tuned_gains_afbl.json").read_text())
    data["k"][3] = 80.123456789012345
    gains = tmp_path / "gains.json"
    gains.write_text(json.dumps(data))
    out = tmp_path / "paper"
    r = afbl(
        "reproduce",
        "--out",
        str(out),
        "--controllers",
        "afbl",
        "--gains",
        str(gains),
        "--no-figures",
        "--n-save",
        "11",
        "--rtol",
        "1e-6",
        "--atol",
        "1e-8",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((out / "ise.json").read_text())
    recorded = doc["meta"]["config"]["controllers"]["afbl"]
    assert recorded == {**data, "controller": "afbl"}
    assert recorded["k"][3] == 80.123456789012345
    ctrl = A.AFBL(gamma=data["gamma"], k=data["k"], lam=data["lambda"])
    # the reproduction flies the paper's vehicle with eq. 14's gyroscopic sign (its default)
    vehicle = A.QuadrotorParams(gyro_sign=A.EQ14_GYRO_SIGN)
    direct = A.simulate(ctrl, A.paper_scenario("uncertain", "step"), vehicle, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(
        doc["uncertain_step"]["afbl"]["ise_attitude"], float(direct.ise_attitude), rtol=1e-9
    )


def test_two_runs_into_one_folder_share_the_chunks(tmp_path):
    """Two processes on one --out and a third alone: both finish, together they compute every
    chunk once, and the shared folder's table is the lone run's, bit for bit. Gains with full
    float64 precision are recorded unrounded in run.json."""
    data = json.loads((ROOT / "docs" / "tuned_gains_afbl.json").read_text())
    data["k"][3] = 80.123456789012345
    gains = tmp_path / "gains.json"
    gains.write_text(json.dumps(data))
    shared, alone = tmp_path / "shared", tmp_path / "alone"
    common = ["montecarlo", "--cases", "48", "--chunk-size", "8", "--controllers", "afbl"]
    common += ["--gains", str(gains), "--no-report", "--no-progress", "--out"]
    procs = [start(*common, str(shared)), start(*common, str(shared)), start(*common, str(alone))]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0 and "Traceback" not in err, err[-2000:]
    assert pq.read_table(shared / "results.parquet").equals(
        pq.read_table(alone / "results.parquet")
    )
    runs = json.loads((shared / "meta.json").read_text())["invocations"]
    assert len(runs) == 2 and sum(e["chunks_computed"] for e in runs) == 6
    assert not list(shared.rglob("*.tmp")) and not list((shared / "chunks").glob(".*.lock"))
    config = json.loads((shared / "run.json").read_text())
    assert config["controllers"]["afbl"]["k"][3] == 80.123456789012345


def _unwritable(tmp_path: Path) -> Path | None:
    """A folder path that cannot be created: below a read-only folder, or (for root, whom
    permissions do not stop) below /sys; None if neither works here."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    for target in (ro / "out", Path("/sys/afbl-test-out")):
        try:
            target.mkdir()
        except OSError:
            return target
        target.rmdir()
    return None


@pytest.mark.parametrize(
    "case", ["out_is_file", "out_unwritable", "distribution_is_dir", "seed_2_64", "cases_1e12"]
)
def test_user_errors_are_one_line_and_write_nothing(tmp_path, case):
    before = set(tmp_path.rglob("*"))
    out = tmp_path / "out"
    args = ["montecarlo", "--out", str(out), "--no-progress"]
    match = {
        "out_is_file": "is an existing file; give a folder",
        "out_unwritable": "",
        "distribution_is_dir": "is a directory; give a .toml or .json file",
        "seed_2_64": "argument --seed: expected an integer in [0, 2^63 - 1]",
        "cases_1e12": "of memory for the results table",
    }[case]
    if case == "out_is_file":
        out.write_text("not a folder")
        before = set(tmp_path.rglob("*"))
    elif case == "out_unwritable":
        target = _unwritable(tmp_path)
        if target is None:
            pytest.skip("no unwritable place on this machine")
        before = set(tmp_path.rglob("*"))
        args[2] = str(target)
    elif case == "distribution_is_dir":
        args += ["--distribution", str(tmp_path)]
    elif case == "seed_2_64":
        args += ["--seed", "18446744073709551616"]
    else:
        args += ["--cases", "1000000000000"]
    r = afbl(*args)
    assert_user_error(r, "montecarlo", match)
    assert set(tmp_path.rglob("*")) == before  # nothing written
    if case == "out_unwritable":
        assert not Path(args[2]).exists()


def test_generated_bad_files_through_the_real_command(tmp_path):
    """A few generated bad files (the in-process fuzz test runs many more): exit 2, one line
    naming the file, no traceback, nothing written."""
    cases = bad_files(tmp_path / "bad", seed=7, n_distribution=2, n_gains=1)
    out = tmp_path / "never"
    for kind, path, what in cases:
        flag = "--distribution" if kind == "distribution" else "--gains"
        r = afbl("montecarlo", "--out", str(out), "--controllers", "fbl,afbl,afbl_paper", flag,
                 str(path))  # fmt: skip
        assert_user_error(r, "montecarlo", str(path))
        assert not out.exists(), what
