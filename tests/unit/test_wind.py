"""Wind to the standards: mean-wind profile, Dryden realisation (RMS vs sigma, banded PSD vs the
analytic PSD), closed forms vs quadrature, gust magnitudes tied to the turbulence, and what the
Monte-Carlo sampler records."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad

from afbl_jax.scenario import (
    KNOT,
    ROUGHNESS_LENGTH,
    TURBULENCE_INTENSITIES,
    Wind,
    dryden_band_amplitudes,
    dryden_band_fraction,
    dryden_correlation,
    dryden_cumulative,
    dryden_low_altitude,
    dryden_psd,
    gust_magnitude,
    mean_wind_speed,
    mean_wind_velocity,
    turbulence_edges,
    turbulence_grid,
    w20,
)
from afbl_jax.studies import montecarlo as mc

FT = 0.3048  # m per ft
SPEC = mc.DEFAULT_DISTRIBUTION["turbulence"]
BAND = (SPEC["n_frequencies"], SPEC["omega_min"], SPEC["omega_max"])


def _psd_np(omega, sigma, scale, airspeed, j):
    """MIL-HDBK-1797 one-sided temporal Dryden PSD of axis j (independent numpy transcription)."""
    x = scale[j] * omega / airspeed
    base = sigma[j] ** 2 * 2.0 * scale[j] / (np.pi * airspeed)
    if j == 0:
        return base / (1.0 + x**2)
    return base * (1.0 + 12.0 * x**2) / (1.0 + 4.0 * x**2) ** 2


def _turbulence(amp, omega, phase):
    return Wind(jnp.zeros(0), jnp.ones((0, 3)), jnp.zeros((0, 3)), amp, omega, phase)


def test_mean_wind_log_profile():
    # MIL-F-8785C: W(h) = W20 ln(h / z0) / ln(20 ft / z0), z0 = 0.15 ft (category C)
    assert ROUGHNESS_LENGTH == pytest.approx(0.15 * FT)
    np.testing.assert_allclose(mean_wind_speed(7.0, 20.0 * FT), 7.0, rtol=1e-12)
    h_ft = 10.0 / FT
    ratio = math.log(h_ft / 0.15) / math.log(20.0 / 0.15)
    for name, knots in (("light", 15.0), ("moderate", 30.0), ("severe", 45.0)):
        assert w20(name) == pytest.approx(knots * KNOT)
        np.testing.assert_allclose(mean_wind_speed(w20(name), 10.0), knots * KNOT * ratio)
    # at 10 m it is 1.7x (light) to 5.1x (severe) the 5 m/s the field used to be carried at
    assert 1.6 < mean_wind_speed(w20("light"), 10.0) / 5.0 < 1.8
    assert 5.0 < mean_wind_speed(w20("severe"), 10.0) / 5.0 < 5.2
    v = mean_wind_velocity(4.0, np.pi / 2)
    np.testing.assert_allclose(v, [0.0, 4.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="roughness"):
        mean_wind_speed(5.0, 0.01)


def test_dryden_closed_forms_agree_with_quadrature():
    sigma, scale = dryden_low_altitude("moderate", 10.0)
    airspeed = 17.0
    grid = np.geomspace(1e-3, 1e3, 7)
    np.testing.assert_allclose(
        np.asarray(dryden_psd(grid, sigma, scale, airspeed)),
        [_psd_np(grid, sigma, scale, airspeed, j) for j in range(3)],
        rtol=1e-12,
    )
    for omega in (0.03, 0.7, 12.0, 250.0):
        cum = np.asarray(dryden_cumulative(np.array([omega]), sigma, scale, airspeed))[:, 0]
        for j in range(3):
            ref = quad(_psd_np, 0.0, omega, args=(sigma, scale, airspeed, j), limit=400)[0]
            np.testing.assert_allclose(cum[j], ref, rtol=1e-8)
    total = np.asarray(dryden_cumulative(np.array([1e12]), sigma, scale, airspeed))[:, 0]
    np.testing.assert_allclose(total, sigma**2, rtol=1e-9)
    # correlation = cosine transform of the spatial PSD (one-sided), normalised by sigma^2
    for r in (0.5, 4.0, 30.0):
        rho = np.asarray(dryden_correlation(r, scale))
        for j in range(3):
            ref = quad(_psd_np, 0.0, np.inf, args=(sigma, scale, 1.0, j), weight="cos", wvar=r)[0]
            ref /= sigma[j] ** 2
            np.testing.assert_allclose(rho[j], ref, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("intensity", ["light", "moderate", "severe"])
def test_realised_rms_within_one_percent_of_sigma(intensity):
    """Default lines (the grid up to the cutoff), carried at the mean-wind speed at 10 m:
    realised variance >= 99 % of sigma^2 on every axis at light intensity (the default
    distribution's mean winds, up to 8 m/s), >= 97.5 % at moderate and severe (17 and 25 m/s
    carry the w spectrum past the cutoff), equal to the band integral; time-domain RMS
    agrees."""
    sigma, scale = dryden_low_altitude(intensity, 10.0)
    airspeed = float(mean_wind_speed(w20(intensity), 10.0))
    omega, edges = mc.turbulence_lines(SPEC)
    assert len(omega) < SPEC["n_frequencies"] and omega[-1] <= SPEC["omega_cutoff"]
    amp = np.asarray(dryden_band_amplitudes(edges, sigma, scale, airspeed))
    realised = np.sqrt(0.5 * np.sum(amp**2, axis=1))
    fraction = np.asarray(dryden_band_fraction(edges, scale, airspeed))
    np.testing.assert_allclose(realised**2, fraction * sigma**2, rtol=1e-10)
    assert np.all(fraction >= (0.99 if intensity == "light" else 0.975)), fraction
    # sample RMS of realisations (random phases) over a long record
    rng = np.random.default_rng(1)
    t = jnp.asarray(np.arange(0.0, 600.0, 0.01))
    var = np.zeros(3)
    for _ in range(16):
        w = _turbulence(amp, omega, rng.uniform(0, 2 * np.pi, amp.shape))
        var += np.mean(np.asarray(jax.vmap(w)(t)) ** 2, axis=0) / 16
    # lines below ~0.01 rad/s barely move in 600 s: their phases add ensemble scatter
    np.testing.assert_allclose(np.sqrt(var), realised, rtol=0.1)


def test_banded_ensemble_psd_matches_analytic_psd():
    """Periodogram of random-phase realisations, integrated over bands of 8 grid cells,
    against the analytic PSD integrated over the same bands."""
    sigma, scale = dryden_low_altitude("severe", 10.0)
    airspeed = float(mean_wind_speed(w20("severe"), 10.0))
    edges = turbulence_edges(*BAND)
    omega, _ = turbulence_grid(*BAND)
    amp = np.asarray(dryden_band_amplitudes(edges, sigma, scale, airspeed))
    dt, n = 0.01, 2**18  # 2621 s record, Nyquist 314 rad/s
    t = jnp.asarray(np.arange(n) * dt)
    freqs = 2 * np.pi * np.fft.rfftfreq(n, dt)
    band_edges = edges[::8]
    keep = band_edges[:-1] >= 0.1  # bands the record resolves (>= 40 periods)
    rng = np.random.default_rng(2)
    power = np.zeros((3, len(band_edges) - 1))
    n_real = 4
    for _ in range(n_real):
        w = _turbulence(amp, omega, rng.uniform(0, 2 * np.pi, amp.shape))
        x = np.asarray(jax.jit(jax.vmap(w))(t))
        spec = 2.0 * np.abs(np.fft.rfft(x, axis=0)) ** 2 / n**2
        for b in range(len(band_edges) - 1):
            sel = (freqs >= band_edges[b]) & (freqs < band_edges[b + 1])
            power[:, b] += spec[sel].sum(axis=0) / n_real
    cum = np.asarray(dryden_cumulative(band_edges, sigma, scale, airspeed))
    expected = np.diff(cum, axis=1)
    np.testing.assert_allclose(power[:, keep], expected[:, keep], rtol=0.03)


def test_gust_magnitude_is_the_rms_velocity_change_over_the_gust_length():
    sigma, scale = dryden_low_altitude("moderate", 10.0)
    np.testing.assert_allclose(gust_magnitude(0.0, sigma, scale), 0.0, atol=1e-12)
    np.testing.assert_allclose(gust_magnitude(1e9, sigma, scale), np.sqrt(2) * sigma)
    lengths = np.array([5.0, 20.0, 60.0])
    mags = np.asarray(gust_magnitude(lengths, sigma, scale))
    assert np.all(np.diff(mags / sigma) != 0)
    # against the realised field: RMS of w(t + d / V) - w(t) over a long record
    airspeed = 17.0
    edges = np.geomspace(1e-4, 2000.0, 129)
    omega = np.sqrt(edges[:-1] * edges[1:])
    amp = np.asarray(dryden_band_amplitudes(edges, sigma, scale, airspeed))
    rng = np.random.default_rng(3)
    t = jnp.asarray(np.arange(0.0, 1200.0, 0.02))
    for d in (5.0, 30.0):
        acc = np.zeros(3)
        for _ in range(6):
            w = _turbulence(amp, omega, rng.uniform(0, 2 * np.pi, amp.shape))
            inc = np.asarray(jax.vmap(w)(t + d / airspeed)) - np.asarray(jax.vmap(w)(t))
            acc += np.mean(inc**2, axis=0) / 6
        np.testing.assert_allclose(np.sqrt(acc), gust_magnitude(d, sigma, scale), rtol=0.05)


def test_sampler_records_mean_wind_turbulence_and_gusts():
    """Default cases: a continuous mean wind in [0, cap], the turbulence intensities of that
    wind (MIL-HDBK-1797 low altitude, written out here), carried at the mean airspeed of a
    vehicle holding position (floored at min_airspeed), the gust tied to them."""
    dist = mc.default_distribution()
    batch = mc.sample_cases(dist, 32, 0)
    inp = {k: np.asarray(v) for k, v in batch.inputs.items()}
    assert batch.aerodynamics.name == "rotor_drag"
    speed = inp["mean_wind_speed"]
    assert np.all((speed >= 0) & (speed <= mc.MEAN_WIND_CAP)) and len(np.unique(speed)) == 32
    np.testing.assert_allclose(inp["turbulence_airspeed"], np.maximum(speed, 1.0), rtol=1e-6)
    z0, h = 0.15 * 0.3048, 10.0
    w20_case = speed * np.log(20 * 0.3048 / z0) / np.log(h / z0)
    sigma_w = 0.1 * w20_case
    sigma_u = sigma_w / (0.177 + 0.000823 * h / 0.3048) ** 0.4
    np.testing.assert_allclose(inp["turbulence_sigma_w"], sigma_w, rtol=1e-6)
    np.testing.assert_allclose(inp["turbulence_sigma_u"], sigma_u, rtol=1e-6)
    np.testing.assert_allclose(inp["turbulence_sigma_v"], sigma_u, rtol=1e-6)
    knots = w20_case / 0.514444
    band = np.where(knots <= 0, 0, np.where(knots <= 15, 1, np.where(knots <= 30, 2, 3)))
    np.testing.assert_array_equal(inp["turbulence_level"], band)
    assert np.all(np.abs(inp["mean_wind_direction"]) <= np.pi)
    wind = batch.scenario.wind
    expected_mean = mean_wind_velocity(inp["mean_wind_speed"], inp["mean_wind_direction"])
    np.testing.assert_allclose(np.asarray(wind.mean), expected_mean, rtol=1e-5, atol=1e-6)
    for ax in "uvw":
        sig, rms = inp[f"turbulence_sigma_{ax}"], inp[f"turbulence_rms_{ax}"]
        assert np.all((rms <= sig) & (rms >= 0.98 * sig))
    # the earth-frame realisation keeps the total turbulence power of (u, v, w)
    total = np.sum(np.asarray(wind.turbulence_rms) ** 2, axis=1)
    np.testing.assert_allclose(
        total, sum(inp[f"turbulence_rms_{ax}"] ** 2 for ax in "uvw"), rtol=1e-5
    )
    # tied gust magnitude: multiple x sigma sqrt(2 (1 - rho(V T)))
    _, scale = dryden_low_altitude("light", 10.0)
    for i in range(4):
        sigma = np.array([inp[f"turbulence_sigma_{ax}"][i] for ax in "uvw"])
        buildup = np.array([inp[f"gust_buildup_{ax}"][i] for ax in "xyz"])
        mag = inp["gust_sigma_multiple"][i] * np.asarray(
            gust_magnitude(inp["turbulence_airspeed"][i] * buildup, sigma, scale)
        )
        np.testing.assert_allclose(inp["gust_speed"][i], np.linalg.norm(mag), rtol=1e-5)
        w = jax.tree.map(lambda x, i=i: x[i], wind)
        late = np.asarray(w.mean + jnp.sum(w.gust_amplitude, axis=0))
        np.testing.assert_allclose(
            late[:2] - np.asarray(w.mean)[:2],
            [inp["gust_amplitude_x"][i], inp["gust_amplitude_y"][i]],
            rtol=1e-5,
            atol=1e-6,
        )


def test_cutoff_drops_the_lines_above_it_and_keeps_the_rest():
    """A case keeps its turbulence lines below ``omega_cutoff`` exactly (same phases, same
    amplitudes) whatever the cutoff; the lines above it are left out."""
    full_spec = {"turbulence": {"omega_cutoff": SPEC["omega_max"]}}
    full = mc.sample_cases(mc.Distribution.from_dict(full_spec), 8, 3).scenario.wind
    cut = mc.sample_cases(mc.default_distribution(), 8, 3).scenario.wind
    omega_full, _ = turbulence_grid(*BAND)
    k = int(np.sum(omega_full <= SPEC["omega_cutoff"]))
    assert 0 < k < SPEC["n_frequencies"]
    assert cut.turbulence_cos.shape[-1] == k and full.turbulence_cos.shape[-1] == len(omega_full)
    np.testing.assert_array_equal(np.asarray(cut.turbulence_frequency)[0], omega_full[:k])
    for name in ("turbulence_cos", "turbulence_sin"):
        np.testing.assert_array_equal(
            np.asarray(getattr(cut, name)), np.asarray(getattr(full, name))[..., :k]
        )
    with pytest.raises(ValueError, match="omega_cutoff .* leaves no line"):
        mc.Distribution.from_dict({"turbulence": {"omega_cutoff": 1e-5}})


def test_sampler_table_levels_and_drifting_vehicle():
    """Stress distributions: levels drawn from a table, the mean wind W20 of the level (the
    standard's discrete intensities); a vehicle drifting with the air carries the turbulence
    at min_airspeed; independent gust magnitudes without a mean wind."""
    table = mc.Distribution.from_dict(
        {"mean_wind": {"source": "w20"}, "turbulence": {"intensity": "table"}}
    )
    inp = {k: np.asarray(v) for k, v in mc.sample_cases(table, 16, 0).inputs.items()}
    names = np.array(TURBULENCE_INTENSITIES)[inp["turbulence_level"]]
    speeds = np.array([mean_wind_speed(w20(n), 10.0) for n in names])
    np.testing.assert_allclose(inp["mean_wind_speed"], speeds, rtol=1e-6)
    sigma = np.stack([dryden_low_altitude(n, 10.0)[0] for n in names])
    np.testing.assert_allclose(inp["turbulence_sigma_u"], sigma[:, 0], rtol=1e-6)
    drift = mc.Distribution.from_dict({"flight": {"position_hold": False}})
    assert drift.spec["reference"]["profile_probabilities"] == {"step": 0.5, "sine": 0.5}
    b = mc.sample_cases(drift, 8, 0)
    np.testing.assert_allclose(np.asarray(b.inputs["turbulence_airspeed"]), 1.0)
    # drifting: the trimmed start moves with the mean wind, level
    np.testing.assert_allclose(np.asarray(b.scenario.initial_state[:, 6:9]), b.scenario.wind.mean)
    assert b.position_loop is None and b.scenario.position is None
    independent = mc.Distribution.from_dict(
        {
            "gust": {"magnitude": "independent"},
            "mean_wind": {"enabled": False},
            "turbulence": {"intensity": "table"},
        }
    )
    b2 = mc.sample_cases(independent, 16, 0)
    assert np.all(np.isnan(np.asarray(b2.inputs["gust_sigma_multiple"])))
    assert np.all(np.asarray(b2.inputs["mean_wind_speed"]) == 0.0)
    assert np.all(np.asarray(b2.scenario.wind.mean) == 0.0)
    assert np.all(np.asarray(b2.inputs["gust_speed"]) <= np.sqrt(6.0**2 * 2 + 2.0**2) + 1e-6)


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"aero": {"model": "quadratic"}}, "aero.model must be one of"),
        ({"gust": {"magnitude": "standard"}}, "gust.magnitude must be one of"),
        ({"mean_wind": {"source": "w20", "speed": [-1.0, 2.0]}}, "mean_wind.speed"),
        ({"mean_wind": {"source": "w20"}}, 'needs turbulence.intensity = "table"'),
        ({"mean_wind": {"enabled": False}}, "switches off"),
        (
            {"turbulence": {"intensity_probabilities": {"none": 0.0, "light": 1.0}}},
            "draws a level per case, which needs",
        ),
        ({"turbulence": {"min_airspeed": 0.0}}, "min_airspeed must be > 0"),
        ({"turbulence": {"airspeed": -1.0}}, "turbulence.airspeed must be a finite number >= 0"),
        ({"flight": {"position_hold": False, "start": "level"}}, "flight.start must be one of"),
        ({"flight": {"tilt_max": 2.0}}, "flight.tilt_max must be a number > 0 and < 1.5708"),
        ({"envelope": {"tilt": 0.8}}, "must be below the position loop's tilt limit"),
        ({"envelope": {"rotor_reserve": 1.0}}, "envelope.rotor_reserve must be a number >= 0"),
        (
            {"reference": {"profile_probabilities": {"step": 1.0}}},
            "cannot be flown with a position loop",
        ),
        (
            {
                "flight": {"position_hold": False},
                "reference": {"profile_probabilities": {"hold": 1.0}},
            },
            "cannot be flown without a position loop",
        ),
    ],
)
def test_wind_distribution_errors(overrides, match):
    with pytest.raises(ValueError, match=match):
        mc.Distribution.from_dict(overrides)
