"""`afbl reproduce` end to end, and gains-file validation."""

import json

import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.cli import main
from afbl_jax.io import controller_from_dict, gains_to_dict, load_gains, save_gains
from afbl_jax.plotting.paper import PAPER_FIGURES
from afbl_jax.studies.reproduce import SCENARIO_KEYS


def test_reproduce_cli_end_to_end(tmp_path, capsys):
    gains = tmp_path / "gains.json"
    gains.write_text(
        json.dumps(
            {
                "controller": "afbl",
                "gamma": [8, 15, 8, 20],
                "k": [8, 15, 8, 80],
                "lambda": [4, 4, 4, 4],
            }
        )
    )
    out = tmp_path / "paper"
    rc = main(
        [
            "reproduce",
            "--out",
            str(out),
            "--n-save",
            "201",
            "--rtol",
            "1e-7",
            "--atol",
            "1e-9",
            "--gains",
            str(gains),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "ISE reduction of afbl vs fbl" in text and "uncertain_step" in text
    doc = json.loads((out / "ise.json").read_text())
    assert set(doc) == {*SCENARIO_KEYS, "meta"}
    for key in SCENARIO_KEYS:
        assert set(doc[key]) == {"fbl", "afbl", "afbl_paper"}
        for vals in doc[key].values():
            assert set(vals) == {"ise_attitude", "ise_altitude"}
            assert all(isinstance(v, float) for v in vals.values())
    meta = doc["meta"]
    assert meta["config"]["rtol"] == 1e-7 and meta["versions"]["jax"]
    assert "git_revision" in meta and meta["x64"] is True
    # the JSON holds the numbers a direct simulation gives
    direct = A.simulate(
        A.FBLPID(),
        A.paper_scenario("uncertain", "step"),
        A.QuadrotorParams(gyro_sign=A.EQ14_GYRO_SIGN),  # reproduce's default sign
        rtol=1e-7,
        atol=1e-9,
        n_save=0,
    )
    np.testing.assert_allclose(
        doc["uncertain_step"]["fbl"]["ise_attitude"], float(direct.ise_attitude), rtol=1e-6
    )
    for name in PAPER_FIGURES:
        assert (out / name).stat().st_size > 10_000


def test_reproduce_cli_rejects_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps(
            {"controller": "afbl", "gamma": [1, 2, 3], "k": [1, 1, 1, 1], "lambda": [1, 1, 1, 1]}
        )
    )
    out = tmp_path / "out"
    assert main(["reproduce", "--out", str(out), "--gains", str(bad)]) == 2
    assert "list of 4 numbers" in capsys.readouterr().err
    assert main(["reproduce", "--out", str(out), "--controllers", "fbl,lqr"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("afbl reproduce: error: unknown controller") and err.count("\n") == 1
    assert main(["reproduce"]) == 2  # --out is required (argparse): one line as well
    err = capsys.readouterr().err
    assert (
        err == "afbl reproduce: error: the following arguments are required: --out (see "
        "afbl reproduce --help)\n"
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "data, match",
    [
        ({"controller": "mpc", "P": [1, 1, 1, 1]}, "unknown controller"),
        ({"controller": "fbl", "P": [1, 1, 1, 1], "I": [1, 1, 1, 1]}, "missing D"),
        (
            {"controller": "fbl", "P": [1, 1, 1, 1], "I": [1, 1, 1, 1], "D": [1, 1, 1, -1]},
            "must be positive",
        ),
        (
            {"controller": "fbl", "P": [1, 1, 1], "I": [1, 1, 1, 1], "D": [1, 1, 1, 1]},
            "list of 4 numbers",
        ),
        (
            {"controller": "fbl", "P": [1, 1, 1, "a"], "I": [1, 1, 1, 1], "D": [1, 1, 1, 1]},
            "non-numeric",
        ),
        (
            {"controller": "afbl", "gamma": [1] * 4, "k": [1] * 4, "lambda": [1] * 4, "x": 1},
            "unknown x",
        ),
        ([1, 2], "expected a JSON object"),
    ],
)
def test_bad_gains_are_rejected(data, match):
    with pytest.raises(ValueError, match=match):
        controller_from_dict(data)


def test_gains_roundtrip(tmp_path):
    ctrl = A.AFBL(k=[1.0, 2.0, 3.0, 4.0], lam=[2.0, 3.0, 4.0, 5.0])
    path = tmp_path / "g.json"
    save_gains(ctrl, path)
    assert json.loads(path.read_text()) == gains_to_dict(ctrl)
    assert set(gains_to_dict(ctrl)) == {"controller", "gamma", "k", "lambda"}
    back = load_gains(path)
    assert isinstance(back, A.AFBL)
    np.testing.assert_array_equal(back.lam, ctrl.lam)
    with pytest.raises(ValueError, match="does not exist"):
        load_gains(tmp_path / "missing.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_gains(tmp_path / "broken.json")


def test_bench_cli_smoke(tmp_path, capsys):
    out = tmp_path / "bench"
    rc = main(
        [
            "bench",
            "--out",
            str(out),
            "--sizes",
            "4",
            "--strategies",
            "scipy_rk45_loop,ensemble",
            "--scipy-cases",
            "1",
            "--loop-cases",
            "1",
            "--ref-cases",
            "4",
        ]
    )
    assert rc == 0
    rows = json.loads((out / "bench.json").read_text())
    assert isinstance(rows, list) and [r["strategy"] for r in rows] == [
        "scipy_rk45_loop",
        "ensemble",
    ]
    keys = {
        "strategy",
        "N",
        "dtype",
        "sims_per_s",
        "ratio_to_scipy",
        "compile_s",
        "peak_rss_delta_mb",
        "max_rel_ise_error",
        "meta",
    }
    for r in rows:
        assert keys <= set(r) and r["sims_per_s"] > 0
        assert r["meta"]["config"]["seed"] == 0 and r["meta"]["versions"]["diffrax"]
    scipy_row, ens = rows
    assert scipy_row["ratio_to_scipy"] == 1.0
    # both solve the same problem: the scipy loop agrees with the reference too
    assert scipy_row["max_rel_ise_error"] < 1e-3 and ens["max_rel_ise_error"] < 1e-4
    assert ens["N"] == 4 and ens["dtype"] == "float64"
    assert rows[0]["meta"]["config"]["reference_check_max_rel_error"] < 1e-7
    assert (out / "bench.png").stat().st_size > 5_000
    assert "ensemble" in capsys.readouterr().out
    assert main(["bench", "--out", str(out), "--strategies", "magic"]) == 2
    assert "unknown strategies" in capsys.readouterr().err


def _fake_gradient_cost(seen):
    """`gradient_cost`'s output with given seconds (its measurement is tested on its own)."""

    def cost(base, repeats=3, log=print):
        seen.update(n_cases=base.n_cases, repeats=repeats, controller=base.controller)
        log("float32: forward 0.500 s, value-and-gradient 2.000 s")
        return {
            "float32": {
                "forward_s": 0.5,
                "gradient_s": 2.0,
                "rtol": 3e-6,
                "atol": 3e-7,
                "gradient_compile_s": 20.0,
            },
            "float64": {
                "forward_s": 0.8,
                "gradient_s": 4.0,
                "rtol": 1e-6,
                "atol": 1e-8,
                "gradient_compile_s": 22.0,
            },
            "n_cases": base.n_cases,
            "float32_gradient_rel_error": 3e-5,
        }

    return cost


def test_bench_tuning_gradient_rows(tmp_path, capsys, monkeypatch):
    """The tuning_gradient rows: one per precision, the ratios to each forward pass computed
    from the measured seconds, no ISE error or scipy ratio invented for them, and no reference
    of the canonical cases computed when no canonical row is asked for."""
    from afbl_jax.studies import bench, tuning

    seen = {}
    monkeypatch.setattr(tuning, "gradient_cost", _fake_gradient_cost(seen))
    monkeypatch.setattr(bench, "reference_ise", lambda *a, **k: pytest.fail("reference"))
    out = tmp_path / "bench"
    argv = ["bench", "--out", str(out), "--strategies", "tuning_gradient", "--sizes", "4"]
    assert main([*argv, "--gradient-cases", "3"]) == 0
    assert seen == {"n_cases": 3, "repeats": 3, "controller": "afbl"}
    rows = json.loads((out / "bench.json").read_text())
    assert [(r["strategy"], r["dtype"], r["N"]) for r in rows] == [
        ("tuning_gradient", "float32", 3),
        ("tuning_gradient", "float64", 3),
    ]
    f32, f64 = rows
    assert f32["gradient_to_forward"] == pytest.approx(4.0)
    assert f64["gradient_to_forward"] == pytest.approx(5.0)
    assert f64["gradient_to_forward_float32"] == pytest.approx(8.0)
    assert f32["sims_per_s"] == pytest.approx(1.5) and f64["compile_s"] == 22.0
    assert f32["gradient_rel_error"] == 3e-5 and f64["gradient_rel_error"] == 0.0
    for r in rows:
        assert r["max_rel_ise_error"] is None and r["ratio_to_scipy"] is None
        assert r["meta"]["config"]["gradient_cases"] == 3
    printed = capsys.readouterr().out
    assert "value-and-gradient 4.00 s = 5.0x its forward pass" in printed
    assert "8.0x the float32 forward pass" in printed
    assert main([*argv, "--gradient-cases", "0"]) == 2
    assert "--gradient-cases must be > 0" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["montecarlo", "--estimator", "mlmc"], "unknown --estimator 'mlmc'; allowed: crude"),
        (["montecarlo", "--attitude-limit", "0.3"], "--attitude-limit/--altitude-limit apply"),
        (["montecarlo", "--estimator", "ce", "--attitude-limit", "-1"], "--attitude-limit must"),
        (["montecarlo", "--estimator", "ce", "--stage-cases", "1"], "--stage-cases must be"),
        (
            ["montecarlo", "--estimator", "ce-mixture", "--strategy", "vmap"],
            "--strategy must be auto or ensemble",
        ),
        (["montecarlo", "--estimator", "subset", "--p0", "0.7"], "--p0 must lie in (0, 0.5]"),
        (["montecarlo", "--estimator", "subset", "--p0", "0"], "--p0 must lie in (0, 0.5]"),
        (["montecarlo", "--estimator", "subset", "--p0", "nan"], "--p0 must lie in (0, 0.5]"),
        (
            ["montecarlo", "--estimator", "subset", "--stage-cases", "10", "--p0", "0.1"],
            "--estimator subset needs --stage-cases x --p0 >= 2 chains",
        ),
        (["falsify", "--budget", "4", "--starts", "8"], "--budget (4) must be >= --starts (8)"),
        (["falsify", "--sensitivity-samples", "48"], "must be 0 or a power of 2, got 48"),
        (["falsify", "--design-budget", "-1"], "--design-budget must be >= 0, got -1"),
    ],
)
def test_rare_failure_cli_rejects_bad_input(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"afbl {argv[0]}: error: ") and err.count("\n") == 1
    assert message in err
    assert not out.exists()


def test_rare_failure_cli_refuses_unmodeled(tmp_path, capsys):
    dist = tmp_path / "d.toml"
    dist.write_text("[unmodeled]\nenabled = true\nmotor_tau = [0.01, 0.02]\n")
    assert main(["falsify", "--distribution", str(dist), "--out", str(tmp_path / "o")]) == 2
    assert "[unmodeled] enabled = true is not supported" in capsys.readouterr().err
