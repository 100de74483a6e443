"""Sampling Monte-Carlo cases from a `Distribution`.

Case i is drawn from its own key (`case_keys`: ``fold_in(PRNGKey(seed), i)`` for i < 2^32, and
``fold_in(fold_in(PRNGKey(seed), i mod 2^32), i // 2^32)`` above, so every index up to
`MAX_CASE_INDEX` has its own key), so a case never depends on how many cases are drawn with it
or on how they are chunked. One exception, so that the cases of an
ensemble group can share their control sample instants: with ``[unmodeled]`` digital control,
the control rate of case i is the one drawn for case ``GROUP_SIZE * (i // GROUP_SIZE)`` (the
first case of its group of `GROUP_SIZE` consecutive indices). Every case still gets a rate from
the configured range (uniform marginal); cases of one group are just not independent in it.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._typing import Array
from ..._validation import check_seed
from ...model import (
    AERO_COEFFICIENTS,
    AbstractAerodynamics,
    EnvelopeLimits,
    LinearDrag,
    PositionHold,
    QuadrotorParams,
    UnmodeledDynamics,
    combine_margins,
    envelope_margin,
    make_aerodynamics,
    solve_trim,
)
from ...scenario import (
    TURBULENCE_INTENSITIES,
    PulseDisturbance,
    Reference,
    Scenario,
    Wind,
    dryden_band_amplitudes,
    dryden_low_altitude,
    gust_magnitude,
    mean_wind_speed,
    mean_wind_velocity,
    mission_reference,
    paper_reference,
    start_at_trim,
    trim_conditions,
    w20,
)
from ...sim import CachedJit
from ._distribution import (
    ATTITUDE_PROFILES,
    POSITION_PROFILES,
    Distribution,
    turbulence_lines,
)

GROUP_SIZE = 4
"""Cases per drawn control rate (digital control: the cases of a block of `GROUP_SIZE`
consecutive indices share one rate) and per ensemble group with a digital controller (a group
shares one sample clock; `afbl_jax.studies.montecarlo.ensemble_group_size`)."""

INPUT_COLUMNS: tuple[str, ...] = (
    "payload_fraction",
    "payload_time",
    "inertia_scale",
    "thrust_coefficient_scale",
    "drag_coefficient_scale",
    "thrust_to_weight",
    "drag_coefficient",
    "cp_offset",
    *AERO_COEFFICIENTS,
    "hub_height",
    "pulse_torque_phi",
    "pulse_torque_theta",
    "pulse_torque_psi",
    "pulse_torque_start",
    "pulse_torque_duration",
    "pulse_force_z",
    "pulse_force_start",
    "pulse_force_duration",
    "gust_amplitude_x",
    "gust_amplitude_y",
    "gust_amplitude_z",
    "gust_speed",
    "gust_buildup_x",
    "gust_buildup_y",
    "gust_buildup_z",
    "gust_start",
    "gust_sigma_multiple",
    "mean_wind_speed",
    "mean_wind_direction",
    "turbulence_level",
    "turbulence_airspeed",
    "turbulence_sigma_u",
    "turbulence_sigma_v",
    "turbulence_sigma_w",
    "turbulence_rms_u",
    "turbulence_rms_v",
    "turbulence_rms_w",
    "initial_phi",
    "initial_theta",
    "initial_psi",
    "initial_phid",
    "initial_thetad",
    "initial_psid",
    "profile",
    "envelope_margin",
    "envelope_cause",
    "trim_tilt",
)
"""Sampled inputs recorded per case (SI units, rad). ``turbulence_level`` indexes
`afbl_jax.scenario.TURBULENCE_INTENSITIES` (0 none .. 3 severe; with intensities from the mean
wind, the band its W20 falls in: up to 15, 30, 45 knots); ``profile`` indexes the flight
mode's profiles (with a position loop 0 hold, 1 waypoints; without, 0 step, 1 sine).
``envelope_margin`` [-] and ``envelope_cause`` (`afbl_jax.ENVELOPE_CAUSES`) say whether the case
lies inside the vehicle's flight envelope (margin >= 0, cause 0), decided before simulating
(`afbl_jax.envelope_margin` at the mean wind and after the gust, with the largest mass);
``trim_tilt`` [rad] is the tilt of the trim at the mean wind. Wind: ``mean_wind_speed`` [m/s]
at the altitude and ``mean_wind_direction`` [rad] (azimuth the air moves towards, from earth
x towards y; 0 speed when ``[mean_wind]`` is off); ``turbulence_airspeed`` [m/s] carries the
frozen Dryden field (the case's mean airspeed: the mean-wind speed holding position, 0
drifting with the air; at least ``turbulence.min_airspeed``); ``turbulence_sigma_u/v/w`` are
the standard's intensities sigma [m/s] and ``turbulence_rms_u/v/w`` the RMS the sum of sinusoids
realises (the lines of `turbulence_lines`, from omega_min up to omega_cutoff, leave out
the rest of sigma^2); u, v, w are along the
mean wind, across it and vertical. ``gust_amplitude_x/y/z`` [m/s] are the gust's earth-frame
components after build-up (``gust_buildup_x/y/z`` [s] are the build-up times of its u, v, w
components), ``gust_speed`` = |gust amplitude vector| [m/s], ``gust_sigma_multiple`` the
standard deviations of the tied magnitude (NaN with independent magnitudes). The aerodynamic
coefficients are those of `afbl_jax.QuadrotorParams` (the ones the case's model does not use
are drawn and recorded all the same)."""
PROFILE_NAMES = ATTITUDE_PROFILES
"""Reference profiles without a position loop (``profile`` column: 0 step, 1 sine); with one,
`POSITION_PROFILES` (0 hold, 1 waypoints)."""


def _profile_names(spec: dict) -> tuple[str, ...]:
    """The reference profiles of a distribution's flight mode (the ``profile`` codes)."""
    return POSITION_PROFILES if spec["flight"]["position_hold"] else ATTITUDE_PROFILES


def position_loop_of(distribution: Distribution) -> PositionHold | None:
    """The position loop a distribution's cases fly with (its ``[flight]`` gains), or None
    (``flight.position_hold = false``)."""
    flight = distribution.spec["flight"]
    if not flight["position_hold"]:
        return None
    return PositionHold(
        kp=flight["kp"],
        kd=flight["kd"],
        ki=flight["ki"],
        tilt_max=flight["tilt_max"],
        filter_frequency=flight["filter_frequency"],
        windup_time=flight["windup_time"],
    )


UNMODELED_COLUMNS: tuple[str, ...] = (
    "motor_tau",
    "control_rate",
    "delay_samples",
    "noise_angle",
    "noise_rate",
    "noise_altitude",
    "noise_vertical_speed",
)
"""Extra inputs recorded per case when the distribution's ``unmodeled`` section is enabled:
the case's `afbl_jax.UnmodeledDynamics` numbers (``motor_tau`` [s], ``control_rate`` [Hz],
0 = continuous controller, ``delay_samples`` [samples], noise standard deviations [rad],
[rad/s], [m], [m/s])."""
MAX_CASE_INDEX = 2**63 - 1
"""Largest case index (int64 case column); `case_keys` gives every index its own key."""
_UNMODELED_STREAM = 0x554E4D44  # fold_in constant of the per-case unmodeled key ("UNMD")
_WIND_STREAM = 0x57494E44  # fold_in constant of the per-case mean-wind/aero key ("WIND")


class CaseBatch(eqx.Module):
    """A batch of Monte-Carlo cases (leading axis = case).

    Attributes:
        scenario: batched `Scenario` (reference, pulses, payload, wind, initial state).
        vehicle: batched true vehicle `QuadrotorParams`.
        model: the controllers' nominal model (unbatched here; batched also accepted).
        inputs: every sampled number per case, each of shape (n,) (`INPUT_COLUMNS`, plus
            `UNMODELED_COLUMNS` when ``unmodeled`` is set).
        index: global case index of each row, shape (n,).
        unmodeled: batched `afbl_jax.UnmodeledDynamics` (leading axis = case; static fields
            shared), or None for the paper's closed loop.
        aerodynamics: the aerodynamic model of every case (static; its coefficients are in
            ``vehicle``), from the distribution's ``aero.model``.
        position_loop: the position loop every case flies with (`position_loop_of`), or None.
    """

    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    inputs: dict[str, Array]
    index: Array
    unmodeled: UnmodeledDynamics | None = None
    aerodynamics: AbstractAerodynamics = eqx.field(default_factory=LinearDrag)
    position_loop: PositionHold | None = None

    @property
    def input_columns(self) -> tuple[str, ...]:
        """Names of the recorded inputs, in column order."""
        return INPUT_COLUMNS + (UNMODELED_COLUMNS if self.unmodeled is not None else ())

    @property
    def n_cases(self) -> int:
        return int(np.shape(self.index)[0])

    @property
    def model_batched(self) -> bool:
        return np.ndim(self.model.m) == 1

    def take(self, indices) -> CaseBatch:
        """The cases at positions ``indices`` (an int array or a slice) of this batch."""
        if isinstance(indices, slice):
            indices = np.arange(self.n_cases)[indices]
        idx = np.asarray(indices)
        return self._map_cases(lambda x: x[idx], self.index[idx])

    def _map_cases(self, pick, index) -> CaseBatch:
        """This batch with ``pick`` applied to every per-case array (the model where batched)
        and the case indices ``index``."""
        model = jax.tree.map(pick, self.model) if self.model_batched else self.model
        unmodeled = None if self.unmodeled is None else jax.tree.map(pick, self.unmodeled)
        return CaseBatch(
            jax.tree.map(pick, self.scenario),
            jax.tree.map(pick, self.vehicle),
            model,
            {k: pick(v) for k, v in self.inputs.items()},
            index,
            unmodeled,
            self.aerodynamics,
            self.position_loop,
        )

    def __getitem__(self, indices) -> CaseBatch:
        return self.take(indices)

    def case(self, i: int) -> tuple[Scenario, QuadrotorParams, QuadrotorParams]:
        """(scenario, vehicle, model) of row i, unbatched (for `afbl_jax.simulate`)."""
        pick = lambda x: x[i]  # noqa: E731
        model = jax.tree.map(pick, self.model) if self.model_batched else self.model
        return jax.tree.map(pick, self.scenario), jax.tree.map(pick, self.vehicle), model

    def unmodeled_case(self, i: int) -> UnmodeledDynamics | None:
        """The unmodeled-dynamics settings of row i, unbatched (None if not sampled)."""
        if self.unmodeled is None:
            return None
        return jax.tree.map(lambda x: x[i], self.unmodeled)


def _uniform(key, rng, shape=()):
    lo, hi = rng
    return jax.random.uniform(key, shape, minval=lo, maxval=hi)


def _scaled(u, rng):
    """A standard uniform variate u in [0, 1) mapped onto ``rng`` = [low, high], exactly as
    ``jax.random.uniform(key, shape, minval=low, maxval=high)`` maps the same bits."""
    lo, hi = (jnp.asarray(v, u.dtype) for v in rng)
    return jnp.maximum(lo, u * (hi - lo) + lo)


def _choice(u, probs: dict, names) -> Array:
    """The category of a standard uniform variate u, exactly as ``jax.random.choice(key,
    len(names), p=...)`` picks it from the same bits."""
    p = np.array([float(probs.get(n, 0.0)) for n in names])
    p_cuml = jnp.cumsum(jnp.asarray(p / p.sum()))
    return jnp.searchsorted(p_cuml, p_cuml[-1] * (1 - u)).astype(int)


def _rotate_horizontal(vectors, direction):
    """Rows (u, v, w) of ``vectors`` (3, ...) along/across the mean wind -> earth (x, y, z)."""
    c, s = jnp.cos(direction), jnp.sin(direction)
    rot = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return jnp.tensordot(rot, vectors, axes=1)


def _level_drawn(spec: dict) -> bool:
    """Whether a case draws its turbulence level (a table of levels) rather than taking its
    intensity from its mean wind."""
    turb = spec["turbulence"]
    return bool(turb["enabled"]) and turb["intensity"] == "table"


def variate_layout(spec: dict) -> tuple[tuple[str, int, bool], ...]:
    """The standard uniform variates of one case of a distribution ``spec``: (name, size,
    discrete) in the order of `flatten_variates`. Every sampled input is a function of these
    (`_case_from_variates`); ``discrete`` variates pick a category or a sign (piecewise
    constant)."""
    gust, turb, mean = spec["gust"], spec["turbulence"], spec["mean_wind"]
    n_f = int(turb["n_frequencies"])
    out = [
        ("payload_fraction", 1, False),
        ("payload_time", 1, False),
        ("inertia_scale", 1, False),
        ("thrust_coefficient_scale", 1, False),
        ("drag_coefficient_scale", 1, False),
        ("thrust_to_weight", 1, False),
        ("drag_coefficient", 1, False),
        ("cp_offset", 1, False),
        *((name, 1, False) for name in (*AERO_COEFFICIENTS, "hub_height")),
        ("pulse_torque", 3, False),
        ("pulse_force_z", 1, False),
        ("pulse_start", 2, False),
        ("pulse_duration", 2, False),
    ]
    if gust["magnitude"] != "turbulence":
        out += [("gust_horizontal_amplitude", 2, False), ("gust_vertical_amplitude", 1, False)]
    out += [("gust_sign", 3, True), ("gust_buildup", 3, False), ("gust_start", 1, False)]
    if _level_drawn(spec):
        out.append(("turbulence_level", 1, True))
    out.append(("turbulence_phase", 3 * n_f, False))
    if mean["source"] != "w20":
        out.append(("mean_wind_speed", 1, False))
    out.append(("mean_wind_direction", 1, False))
    if gust["magnitude"] == "turbulence":
        out.append(("gust_sigma_multiple", 1, False))
    out += [("initial_attitude", 3, False), ("initial_rate", 3, False), ("profile", 1, True)]
    return tuple(out)


def _draw_variates(key, spec: dict) -> dict[str, Array]:
    """The standard uniform variates of the case with PRNG key ``key`` (`variate_layout`
    names, each of shape (size,)), drawn from the same keys and bits as the sampler always
    drew its inputs."""
    k = iter(jax.random.split(key, 24))
    kw = iter(jax.random.split(jax.random.fold_in(key, _WIND_STREAM), 10))
    gust, turb, mean = spec["gust"], spec["turbulence"], spec["mean_wind"]
    uni = jax.random.uniform
    v = {}
    for name in (
        "payload_fraction",
        "payload_time",
        "inertia_scale",
        "thrust_coefficient_scale",
        "drag_coefficient_scale",
        "thrust_to_weight",
        "drag_coefficient",
        "cp_offset",
    ):
        v[name] = uni(next(k), (1,))
    for name in (*AERO_COEFFICIENTS, "hub_height"):
        v[name] = uni(next(kw), (1,))
    v["pulse_torque"] = uni(next(k), (3,))
    v["pulse_force_z"] = uni(next(k), (1,))
    v["pulse_start"] = uni(next(k), (2,))
    v["pulse_duration"] = uni(next(k), (2,))
    k_mag, k_vert, k_sign, k_build, k_start = (next(k) for _ in range(5))
    if gust["magnitude"] != "turbulence":
        v["gust_horizontal_amplitude"] = uni(k_mag, (2,))
        v["gust_vertical_amplitude"] = uni(k_vert, (1,))
    v["gust_sign"] = uni(k_sign, (3,))  # jax.random.bernoulli(k, 0.5): u < 0.5
    v["gust_buildup"] = uni(k_build, (3,))
    v["gust_start"] = uni(k_start, (1,))
    if _level_drawn(spec):
        v["turbulence_level"] = uni(next(k), (1,))
    v["turbulence_phase"] = uni(next(k), (3 * int(turb["n_frequencies"]),))
    if mean["source"] != "w20":
        v["mean_wind_speed"] = uni(next(kw), (1,))
    v["mean_wind_direction"] = uni(next(kw), (1,))
    if gust["magnitude"] == "turbulence":
        v["gust_sigma_multiple"] = uni(next(kw), (1,))
    v["initial_attitude"] = uni(next(k), (3,))
    v["initial_rate"] = uni(next(k), (3,))
    v["profile"] = uni(next(k), (1,))
    return v


def _case_from_variates(v: dict, spec: dict, tables, edges, omega, references):
    """(scenario, vehicle, inputs) of one case from its standard uniform variates ``v``
    (`variate_layout`); a pure, differentiable map (piecewise constant in the discrete
    variates): `_case_parts`, then `_complete_case` (its start and flight envelope)."""
    return _complete_case(_case_parts(v, spec, tables, edges, omega, references), spec)


def _complete_case(parts, spec: dict):
    """(scenario, vehicle, inputs) from `_case_parts`: the start (trimmed or at rest, plus the
    initial perturbation) and the flight envelope (`_start_and_envelope`)."""
    scenario, vehicle, inputs, gust_amplitude, att, rate = parts
    aerodynamics = make_aerodynamics(spec["aero"]["model"])
    scenario, margin, cause, tilt = _start_and_envelope(
        scenario, vehicle, QuadrotorParams(), aerodynamics, spec, gust_amplitude
    )
    inputs = {**inputs, "envelope_margin": margin, "envelope_cause": cause, "trim_tilt": tilt}
    initial = scenario.initial_state.at[3:6].add(att).at[9:12].add(rate)
    scenario = eqx.tree_at(lambda s: s.initial_state, scenario, initial)
    return scenario, vehicle, inputs


def _batched_cases(vs: dict, spec: dict, tables, edges, omega, references):
    """`_case_from_variates` of a batch of variates (leading axis n): the case parts
    vectorised, the start and envelope (Newton trims) case by case (`jax.lax.map`), so that a
    case's trim is bitwise the same in every batch, whatever its size."""
    parts = jax.vmap(lambda v: _case_parts(v, spec, tables, edges, omega, references))(vs)
    return jax.lax.map(lambda p: _complete_case(p, spec), parts)


def _case_parts(v: dict, spec: dict, tables, edges, omega, references):
    """(scenario at rest, vehicle, inputs, gust amplitude (3,) [m/s], initial attitude and
    rate perturbations) of one case from its standard uniform variates."""
    pay, err, aero = spec["payload"], spec["model_error"], spec["aero"]
    pul, gust, turb, ini = spec["pulses"], spec["gust"], spec["turbulence"], spec["initial"]
    mean, flight = spec["mean_wind"], spec["flight"]
    hold = bool(flight["position_hold"])
    inputs = {}
    inputs["payload_fraction"] = _scaled(v["payload_fraction"][0], pay["fraction"])
    inputs["payload_time"] = _scaled(v["payload_time"][0], pay["attach_time"])
    for name in (
        "inertia_scale",
        "thrust_coefficient_scale",
        "drag_coefficient_scale",
        "thrust_to_weight",
    ):
        inputs[name] = _scaled(v[name][0], err[name])
    for name in ("drag_coefficient", "cp_offset", *AERO_COEFFICIENTS, "hub_height"):
        inputs[name] = _scaled(v[name][0], aero[name])

    on = 1.0 if pul["enabled"] else 0.0
    torque = on * _scaled(v["pulse_torque"], pul["torque"])
    force_z = on * _scaled(v["pulse_force_z"][0], pul["vertical_force"])
    starts = _scaled(v["pulse_start"], pul["start"])
    durations = _scaled(v["pulse_duration"], pul["duration"])
    for j, ax in enumerate(("phi", "theta", "psi")):
        inputs[f"pulse_torque_{ax}"] = torque[j]
    inputs["pulse_torque_start"], inputs["pulse_torque_duration"] = starts[0], durations[0]
    inputs["pulse_force_z"] = force_z
    inputs["pulse_force_start"], inputs["pulse_force_duration"] = starts[1], durations[1]
    zero3 = jnp.zeros(3)
    pulses = PulseDisturbance(
        starts,
        durations,
        jnp.stack([torque, zero3]),
        jnp.stack([zero3, jnp.array([0.0, 0.0, 1.0]) * force_z]),
    )

    # the mean wind, the turbulence's intensities and the airspeed that carries it
    sigma_table, scale_table, w20_table, sigma_per_w20, profile_gain = tables
    if _level_drawn(spec):
        level = _choice(
            v["turbulence_level"][0], turb["intensity_probabilities"], TURBULENCE_INTENSITIES
        )
    else:
        level = jnp.asarray(0)
    if mean["source"] == "w20":
        speed = mean_wind_speed(jnp.asarray(w20_table)[level], turb["altitude"])
    else:
        speed = _scaled(v["mean_wind_speed"][0], mean["speed"])
    speed = speed if mean["enabled"] else jnp.zeros_like(speed)
    scale = jnp.asarray(scale_table)[level]
    if not turb["enabled"]:
        sigma = jnp.zeros(3)
    elif turb["intensity"] == "table":
        sigma = jnp.asarray(sigma_table)[level]
    else:  # the case's own mean wind: sigma = W20 x (sigma per W20), W20 from the log profile
        w20_case = speed * profile_gain
        sigma = w20_case * jnp.asarray(sigma_per_w20)
        level = jnp.searchsorted(jnp.asarray(w20_table), w20_case, side="left")
        level = jnp.minimum(level, len(TURBULENCE_INTENSITIES) - 1)
    direction = _scaled(v["mean_wind_direction"][0], mean["direction"])
    if turb["airspeed"] > 0:
        airspeed = jnp.asarray(float(turb["airspeed"]))
    else:  # position hold: the air passes at the mean-wind speed; drifting: with the air
        mean_airspeed = speed if hold else jnp.zeros_like(speed)
        airspeed = jnp.maximum(mean_airspeed, float(turb["min_airspeed"]))
    inputs["mean_wind_speed"] = speed
    inputs["mean_wind_direction"] = direction
    inputs["turbulence_level"] = level
    inputs["turbulence_airspeed"] = airspeed

    # one 1-cosine gust: components u, v, w along the mean wind, each with its build-up time
    g_on = 1.0 if gust["enabled"] else 0.0
    buildup = _scaled(v["gust_buildup"], gust["buildup_time"])
    sign = jnp.where(v["gust_sign"] < 0.5, 1.0, -1.0)
    if gust["magnitude"] == "turbulence":
        multiple = _scaled(v["gust_sigma_multiple"][0], gust["sigma_multiple"])
        mag = multiple * gust_magnitude(airspeed * buildup, sigma, scale)
        inputs["gust_sigma_multiple"] = multiple
    else:
        mag = jnp.concatenate(
            [
                _scaled(v["gust_horizontal_amplitude"], gust["horizontal_amplitude"]),
                _scaled(v["gust_vertical_amplitude"], gust["vertical_amplitude"]),
            ]
        )
        inputs["gust_sigma_multiple"] = jnp.asarray(jnp.nan)
    amp_uvw = g_on * mag * sign
    g_start = _scaled(v["gust_start"][0], gust["start"])
    amp = _rotate_horizontal(amp_uvw, direction)
    for j, ax in enumerate("xyz"):
        inputs[f"gust_amplitude_{ax}"] = amp[j]
        inputs[f"gust_buildup_{ax}"] = buildup[j]
    inputs["gust_speed"] = jnp.sqrt(jnp.sum(amp**2))
    inputs["gust_start"] = g_start
    gust_vectors = _rotate_horizontal(jnp.diag(amp_uvw), direction).T  # (component, axis)

    # Dryden turbulence (u, v, w) realised as sinusoids, rotated into the earth frame
    t_amp = dryden_band_amplitudes(edges, sigma, scale, airspeed)
    phase = _scaled(v["turbulence_phase"], (0.0, 2.0 * jnp.pi)).reshape(3, -1)[:, : len(omega)]
    for j, ax in enumerate("uvw"):
        inputs[f"turbulence_sigma_{ax}"] = sigma[j]
        inputs[f"turbulence_rms_{ax}"] = jnp.sqrt(0.5 * jnp.sum(t_amp[j] ** 2))
    mean_velocity = mean_wind_velocity(speed, direction)
    wind = Wind(
        jnp.full(3, g_start),
        jnp.repeat(buildup[:, None], 3, axis=1),
        gust_vectors,
        t_amp,
        jnp.asarray(omega),
        phase,
        mean_velocity,
    )
    wind = eqx.tree_at(
        lambda w: (w.turbulence_cos, w.turbulence_sin),
        wind,
        (
            _rotate_horizontal(wind.turbulence_cos, direction),
            _rotate_horizontal(wind.turbulence_sin, direction),
        ),
    )

    att = _scaled(v["initial_attitude"], ini["attitude"])
    rate = _scaled(v["initial_rate"], ini["rate"])
    for j, ax in enumerate(("phi", "theta", "psi")):
        inputs[f"initial_{ax}"] = att[j]
        inputs[f"initial_{ax}d"] = rate[j]

    profiles = _profile_names(spec)
    profile = _choice(v["profile"][0], spec["reference"]["profile_probabilities"], profiles)
    inputs["profile"] = profile
    pick = lambda *xs: jnp.stack(xs)[profile]  # noqa: E731
    attitude_refs, position_refs = references
    reference = jax.tree.map(pick, *attitude_refs)
    position = None if position_refs is None else jax.tree.map(pick, *position_refs)

    nominal = QuadrotorParams()
    omega_max = jnp.sqrt(inputs["thrust_to_weight"] * nominal.m * nominal.g / (4.0 * nominal.b))
    aero_fields = ("drag_coefficient", "cp_offset", *AERO_COEFFICIENTS, "hub_height")
    vehicle = eqx.tree_at(
        lambda p: (
            p.Ix,
            p.Iy,
            p.Iz,
            p.b,
            p.d,
            p.omega_max,
            *(getattr(p, name) for name in aero_fields),
        ),
        nominal,
        (
            nominal.Ix * inputs["inertia_scale"],
            nominal.Iy * inputs["inertia_scale"],
            nominal.Iz * inputs["inertia_scale"],
            nominal.b * inputs["thrust_coefficient_scale"],
            nominal.d * inputs["drag_coefficient_scale"],
            omega_max,
            *(inputs[name] for name in aero_fields),
        ),
    )

    scenario = Scenario(
        reference,
        pulses,
        inputs["payload_fraction"],
        inputs["payload_time"],
        jnp.zeros(12),
        0.0,
        spec["time"]["t1"],
        wind,
        position,
    )
    return scenario, vehicle, inputs, amp, att, rate


def _start_and_envelope(scenario, vehicle, model, aerodynamics, spec, gust_amplitude):
    """The case's start (trimmed, or at rest) and its flight-envelope margin, cause and trim
    tilt [rad]: the binding one of the trims at the mean wind with the mass at t0, and with the
    largest mass (a payload attached later) at the mean wind and at the wind after the gust (a
    held gust counts, a downdraft too). Drifting with the air, the vehicle's velocity follows
    the wind of each trim (no airspeed)."""
    hold = bool(spec["flight"]["position_hold"])
    limits = EnvelopeLimits(spec["envelope"]["tilt"], spec["envelope"]["rotor_reserve"])
    mass, mean, _ = trim_conditions(scenario, vehicle, position_hold=hold)
    heavy = jnp.maximum(vehicle.m * (1.0 + jnp.maximum(scenario.payload_fraction, 0.0)), mass)
    # the three trims in one batched Newton solve (one compiled solver, not three): the start
    # (mass at t0, the initial yaw), then the largest mass at the mean wind and after the gust
    winds = jnp.stack([mean, mean, mean + gust_amplitude])
    velocities = jnp.zeros_like(winds) if hold else winds  # as `trim_conditions` sets them
    masses = jnp.stack([mass, heavy, heavy])
    psis = jnp.stack([scenario.initial_state[5], 0.0, 0.0])
    solutions = jax.vmap(lambda w, v, m, p: solve_trim(vehicle, model, aerodynamics, w, v, m, p))(
        winds, velocities, masses, psis
    )
    solution = jax.tree.map(lambda x: x[0], solutions)
    trimmed = start_at_trim(scenario, vehicle, solution, position_hold=hold)
    margins = [
        envelope_margin(jax.tree.map(lambda x, i=i: x[i], solutions), vehicle, limits)
        for i in range(3)
    ]
    margin, cause = combine_margins(*margins)
    if spec["flight"]["start"] == "trimmed":
        scenario = trimmed
    return scenario, margin, cause, solution.tilt


def nominal_model(distribution: Distribution) -> QuadrotorParams:
    """The controllers' nominal model: Table 1 with the distribution's nominal T/W limit."""
    del distribution
    return QuadrotorParams()


def _case_index(index) -> np.ndarray:
    """Case indices as int64 (at most MAX_CASE_INDEX), checked to lie in [0, 2^63 - 1]."""
    try:
        index = np.asarray(index, dtype=np.int64)
    except OverflowError:
        index = np.array([-1])
    if index.size and index.min() < 0:
        raise ValueError("case indices must be integers in [0, 2^63 - 1].")
    return index


def case_keys(seed: int, index) -> Array:
    """The PRNG key of every case index (shape (n, 2)): ``fold_in(PRNGKey(seed), i)`` for
    i < 2^32 (`jax.random.fold_in` takes 32 bits), ``fold_in(fold_in(PRNGKey(seed), i mod 2^32),
    i // 2^32)`` for larger i, so indices that agree in their low 32 bits get different keys."""
    index = _case_index(index)
    lo = jax.device_put((index & 0xFFFFFFFF).astype(np.uint32))
    hi = jax.device_put((index >> 32).astype(np.uint32))
    return _keys(jax.random.PRNGKey(check_seed(seed)), lo, hi)


@jax.jit
def _keys(base, lo, hi):
    low = jax.vmap(lambda i: jax.random.fold_in(base, i))(lo)
    high = jax.vmap(jax.random.fold_in)(low, hi)
    return jnp.where((hi == 0)[:, None], low, high)


def sample_cases(distribution: Distribution, n_cases: int, seed: int, start: int = 0) -> CaseBatch:
    """Cases ``start, ..., start + n_cases - 1`` of the distribution for ``seed`` (in [0,
    2^63 - 1]; indices up to `MAX_CASE_INDEX`).

    Case i uses its own key (`case_keys`) only, so it is the same in every batch. The cases are
    drawn in the precision JAX runs in: with ``jax_enable_x64`` (as the ``afbl`` command runs)
    in float64, without it in float32, which draws slightly different cases (and can move a
    case across the flight-envelope limits).
    """
    if isinstance(n_cases, bool) or int(n_cases) < 1:
        raise ValueError(f"n_cases must be an integer >= 1, got {n_cases!r}.")
    if int(start) < 0 or int(start) + int(n_cases) - 1 > MAX_CASE_INDEX:
        raise ValueError(
            f"cases start .. start + n_cases - 1 must lie in [0, 2^63 - 1], got start {start!r}, "
            f"n_cases {n_cases!r}."
        )
    return _sample_index(
        distribution, np.arange(int(start), int(start) + int(n_cases), dtype=np.int64), seed
    )


def sample_cases_at(
    distribution: Distribution, index, seed: int, *, size: int | None = None
) -> CaseBatch:
    """The cases of the given indices (any order, in [0, 2^63 - 1]) for ``seed``, as
    `sample_cases` draws them (case i from its own key only).

    ``size``: draw a batch of ``size`` cases (the indices, then the last one repeated; the
    padding is dropped), so that the sampler compiled for a chunk of that size is used again
    instead of compiling one for ``len(index)`` cases.
    """
    index = _case_index(index).reshape(-1)
    if index.size == 0:
        raise ValueError("sample_cases_at needs at least one case index.")
    if size is not None and (isinstance(size, bool) or int(size) < index.size):
        raise ValueError(f"size must be an integer >= the {index.size} indices, got {size!r}.")
    return _sample_index(distribution, index, seed, size=size)


def _sampler_size(n: int) -> int:
    """The batch the sampler draws for ``n`` cases: the next multiple of 64, so that one
    compiled sampler serves every batch of up to 64 cases and a few serve the rest (the padding
    repeats the last case and is dropped; a case is drawn the same in every batch, to the
    rounding of its vectorised arithmetic)."""
    return max(1, -(-n // 64)) * 64


def _first_cases(batch: CaseBatch, n: int) -> CaseBatch:
    """The first ``n`` cases of ``batch``, sliced on the host and put back on the device (no
    compiled program per leaf shape)."""
    return batch._map_cases(lambda x: jax.device_put(np.asarray(x)[:n]), batch.index[:n])


def _sample_index(
    distribution: Distribution, index: np.ndarray, seed: int, *, size: int | None = None
) -> CaseBatch:
    """The cases of ``index``, drawn in a batch of `_sampler_size` of ``size`` (default: the
    number of indices) cases, the padding dropped."""
    n = index.size
    padded = np.concatenate([index, np.full(_sampler_size(max(n, int(size or n))) - n, index[-1])])
    return _first_cases(_draw_index(distribution, padded, seed), n)


def _draw_index(distribution: Distribution, index: np.ndarray, seed: int) -> CaseBatch:
    keys = case_keys(seed, index)
    scenario, vehicle, inputs = _batch_sampler(keys, distribution)
    unmodeled = None
    if distribution.spec["unmodeled"]["enabled"]:
        group_keys = case_keys(seed, (index // GROUP_SIZE) * GROUP_SIZE)
        unmodeled, extra = _sample_unmodeled(distribution, keys, group_keys)
        inputs = {**inputs, **extra}
    return CaseBatch(
        scenario,
        vehicle,
        nominal_model(distribution),
        inputs,
        index,
        unmodeled,
        make_aerodynamics(distribution.spec["aero"]["model"]),
        position_loop_of(distribution),
    )


def variate_names(distribution: Distribution) -> tuple[str, ...]:
    """Name of every standard variate (``name`` or ``name[j]`` for vector variates), in the
    order of the variate vector."""
    out = []
    for name, size, _ in variate_layout(distribution.spec):
        out += [name] if size == 1 else [f"{name}[{j}]" for j in range(size)]
    return tuple(out)


def variate_groups(distribution: Distribution) -> tuple[str, ...]:
    """Per variate, the name of its group (the variate's name without the ``[j]``)."""
    return tuple(name for name, size, _ in variate_layout(distribution.spec) for _ in range(size))


def discrete_variates(distribution: Distribution) -> np.ndarray:
    """Boolean mask (D,) of the discrete variates (category / sign choices)."""
    return np.array(
        [disc for _, size, disc in variate_layout(distribution.spec) for _ in range(size)]
    )


def fixed_variates(distribution: Distribution) -> np.ndarray:
    """Boolean mask (D,) of the variates that do not change the case: ranges [x, x] and
    disabled pulses (their draws are still made and recorded)."""
    spec = distribution.spec
    width = {
        "payload_fraction": spec["payload"]["fraction"],
        "payload_time": spec["payload"]["attach_time"],
        **{k: v for k, v in spec["model_error"].items()},
        **{k: v for k, v in spec["aero"].items() if k != "model"},
        "gust_buildup": spec["gust"]["buildup_time"],
        "gust_start": spec["gust"]["start"],
        "gust_sigma_multiple": spec["gust"]["sigma_multiple"],
        "gust_horizontal_amplitude": spec["gust"]["horizontal_amplitude"],
        "gust_vertical_amplitude": spec["gust"]["vertical_amplitude"],
        "mean_wind_speed": spec["mean_wind"]["speed"],
        "mean_wind_direction": spec["mean_wind"]["direction"],
        "initial_attitude": spec["initial"]["attitude"],
        "initial_rate": spec["initial"]["rate"],
    }
    pulses = spec["pulses"]
    if pulses["enabled"]:
        width.update(
            pulse_torque=pulses["torque"],
            pulse_force_z=pulses["vertical_force"],
            pulse_start=pulses["start"],
            pulse_duration=pulses["duration"],
        )
    else:
        width.update({k: [0, 0] for k in ("pulse_torque", "pulse_force_z")})
        width.update({k: [0, 0] for k in ("pulse_start", "pulse_duration")})
    out = []
    for name, size, _ in variate_layout(spec):
        rng = width.get(name)
        out += [rng is not None and rng[0] == rng[1]] * size
    return np.array(out)


def _check_variates_supported(distribution: Distribution) -> None:
    if distribution.spec["unmodeled"]["enabled"]:
        raise ValueError(
            "cases from standard variates need [unmodeled] enabled = false (the unmodeled "
            "inputs are drawn from their own stream, not from variates)."
        )


def draw_variates(distribution: Distribution, n_cases: int, seed: int, start: int = 0) -> Array:
    """The standard variates (n_cases, D) of cases ``start, ..., start + n_cases - 1`` of
    ``seed``: `cases_from_variates` of them is `sample_cases` of the same cases."""
    index = np.arange(int(start), int(start) + int(n_cases), dtype=np.int64)
    return _variate_sampler(distribution)(case_keys(seed, index))


def flatten_variates(v: dict, layout) -> Array:
    """Variate dict (`variate_layout` names, leading axes kept) -> vector (..., D)."""
    return jnp.concatenate([v[name] for name, _, _ in layout], axis=-1)


def unflatten_variates(u, layout) -> dict:
    """Vector (..., D) -> variate dict (`variate_layout` names, each (..., size))."""
    out, i = {}, 0
    for name, size, _ in layout:
        out[name] = u[..., i : i + size]
        i += size
    return out


@functools.lru_cache(maxsize=8)
def _variate_sampler(distribution: Distribution):
    layout = variate_layout(distribution.spec)
    return jax.jit(
        jax.vmap(lambda key: flatten_variates(_draw_variates(key, distribution.spec), layout))
    )


@functools.lru_cache(maxsize=8)
def case_map(distribution: Distribution):
    """The pure map of one case's standard variates u (D,) to ``(scenario, vehicle, inputs)``
    (the `CaseBatch` fields of one case, unbatched); differentiable in the continuous
    variates, for use inside jax.vmap / grad / jit."""
    _check_variates_supported(distribution)
    spec = distribution.spec
    layout = variate_layout(spec)
    tables, edges, omega, references = _sampler_tables(distribution)

    def one(u):
        return _case_from_variates(
            unflatten_variates(u, layout), spec, tables, edges, omega, references
        )

    return one


def cases_from_variates(distribution: Distribution, u, index=None) -> CaseBatch:
    """A `CaseBatch` from standard variates u (n, D) (``index``: the case indices recorded,
    default 0..n-1). Values of u are used as given (clip to [0, 1] to stay in the bounds)."""
    _check_variates_supported(distribution)
    u = jnp.asarray(u)
    scenario, vehicle, inputs = _map_sampler(distribution)(u)
    n = u.shape[0]
    index = np.arange(n, dtype=np.int64) if index is None else np.asarray(index, np.int64)
    return CaseBatch(
        scenario,
        vehicle,
        nominal_model(distribution),
        inputs,
        index,
        None,
        make_aerodynamics(distribution.spec["aero"]["model"]),
        position_loop_of(distribution),
    )


@functools.lru_cache(maxsize=8)
def _map_sampler(distribution: Distribution):
    spec = distribution.spec
    layout = variate_layout(spec)
    tables, edges, omega, references = _sampler_tables(distribution)
    return jax.jit(
        lambda u: _batched_cases(
            unflatten_variates(u, layout), spec, tables, edges, omega, references
        )
    )


def unmodeled_statics(distribution: Distribution) -> dict:
    """Static `UnmodeledDynamics` fields shared by all cases of an enabled distribution:
    ``plant``, ``max_samples = ceil(t1 * max control rate)`` (0 = continuous) and
    ``max_delay`` = the largest delay of the range."""
    unm = distribution.spec["unmodeled"]
    rate_hi = float(unm["control_rate"][1])
    t1 = float(distribution.spec["time"]["t1"])
    max_samples = int(math.ceil(t1 * rate_hi - 1e-9)) if rate_hi > 0 else 0
    return {
        "plant": unm["plant"],
        "max_samples": max_samples,
        "max_delay": int(unm["delay_samples"][1]),
    }


def _sample_unmodeled(
    distribution: Distribution, keys, group_keys
) -> tuple[UnmodeledDynamics, dict]:
    """Per-case unmodeled settings from ``fold_in(case key, _UNMODELED_STREAM)`` (a stream
    separate from the other inputs, which stay as without the section); the control rate from
    the group's first case (``group_keys``)."""
    draws = _unmodeled_sampler(distribution)(keys, group_keys)
    extra = {name: draws[name] for name in UNMODELED_COLUMNS}
    settings = UnmodeledDynamics(
        **unmodeled_statics(distribution),
        motor_tau=draws["motor_tau"],
        control_rate=draws["control_rate"],
        delay_samples=draws["delay_samples"],
        noise_angle=draws["noise_angle"],
        noise_rate=draws["noise_rate"],
        noise_altitude=draws["noise_altitude"],
        noise_vertical_speed=draws["noise_vertical_speed"],
        key=draws["key"],
    )
    return settings, extra


@functools.lru_cache(maxsize=8)
def _unmodeled_sampler(distribution: Distribution):
    unm = distribution.spec["unmodeled"]
    lo_d, hi_d = (int(v) for v in unm["delay_samples"])

    def one(case_key, group_key):
        k = jax.random.split(jax.random.fold_in(case_key, _UNMODELED_STREAM), 8)
        k_group = jax.random.split(jax.random.fold_in(group_key, _UNMODELED_STREAM), 8)
        out = {
            "motor_tau": _uniform(k[0], unm["motor_tau"]),
            "control_rate": _uniform(k_group[1], unm["control_rate"]),
            "delay_samples": jax.random.randint(k[2], (), lo_d, hi_d + 1, dtype=jnp.int32),
        }
        for j, name in enumerate(
            ("noise_angle", "noise_rate", "noise_altitude", "noise_vertical_speed")
        ):
            out[name] = _uniform(k[3 + j], unm[name])
        out["key"] = k[7]
        return out

    return jax.jit(jax.vmap(one))


def shared_slot_references(references: list[Reference]) -> list[Reference]:
    """The same signals with the timing of unused slots aligned across the references.

    A zero-size step slot takes the start and duration of the same slot of another reference
    where it is used, and a zero-amplitude sinusoid takes the other's frequency and phase; the
    signals (r, rd, rdd) are unchanged. Cases drawn from these references then share every
    timing leaf, which `afbl_jax.simulate_batch` evaluates once for all cases instead of per
    case (the blends are most of the vector field's cost otherwise). The unused slots add their
    (harmless) kink times to the jump times.
    """
    ref = [jax.tree.map(np.asarray, r) for r in references]
    start = np.array(ref[0].step_start, dtype=float)
    duration = np.array(ref[0].step_duration, dtype=float)
    freq = np.array(ref[0].sine_frequency, dtype=float)
    phase = np.array(ref[0].sine_phase, dtype=float)
    for r in ref[1:]:
        used, free = r.step_size != 0, ref[0].step_size == 0
        take = used & free
        start[take], duration[take] = r.step_start[take], r.step_duration[take]
        take = (r.sine_amplitude != 0) & (ref[0].sine_amplitude == 0)
        freq[take], phase[take] = r.sine_frequency[take], r.sine_phase[take]
    out = []
    for r in ref:
        slot_free, sine_free = r.step_size == 0, r.sine_amplitude == 0
        out.append(
            type(r)(
                r.offset,
                np.where(slot_free, start, r.step_start),
                r.step_size,
                np.where(slot_free, duration, r.step_duration),
                r.sine_amplitude,
                np.where(sine_free, freq, r.sine_frequency),
                np.where(sine_free, phase, r.sine_phase),
            )
        )
    return out


def _sampler_tables(distribution: Distribution):
    """Turbulence tables, band edges and frequencies, and the references of a distribution."""
    spec = distribution.spec
    turb = spec["turbulence"]
    omega, edges = turbulence_lines(turb)
    levels = [dryden_low_altitude(name, turb["altitude"]) for name in TURBULENCE_INTENSITIES]
    light_sigma, _ = dryden_low_altitude("light", turb["altitude"])
    tables = (
        np.stack([sig for sig, _ in levels]),
        np.stack([scale for _, scale in levels]),
        np.array([w20(name) for name in TURBULENCE_INTENSITIES]),
        light_sigma / w20("light"),  # sigma per W20 (the low-altitude model is linear in W20)
        1.0 / float(mean_wind_speed(1.0, turb["altitude"])),  # W20 / W(h) of the log profile
    )
    if spec["flight"]["position_hold"]:
        pairs = [mission_reference(p) for p in POSITION_PROFILES]
        references = (
            shared_slot_references([a for a, _ in pairs]),
            shared_slot_references([b for _, b in pairs]),
        )
    else:
        references = (shared_slot_references([paper_reference(p) for p in ATTITUDE_PROFILES]), None)
    return tables, edges, omega, references


def _sample_keys(keys, distribution: Distribution):
    """keys (n, 2) -> (scenario, vehicle, inputs) of one distribution's cases."""
    spec = distribution.spec
    with jax.ensure_compile_time_eval():  # constants of the program, as numbers
        tables, edges, omega, references = _sampler_tables(distribution)
    variates = jax.vmap(lambda key: _draw_variates(key, spec))(keys)
    return _batched_cases(variates, spec, tables, edges, omega, references)


_batch_sampler = CachedJit(_sample_keys, "sampler")
"""`_sample_keys` compiled per distribution and batch size (its executables kept between
processes where `afbl_jax.configure_compilation_cache` keeps them)."""
