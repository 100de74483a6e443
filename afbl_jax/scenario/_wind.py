"""Wind: a steady mean wind, discrete 1-cosine gusts and Dryden turbulence (the air the vehicle
flies through; the aerodynamic model that turns it into force and torque is chosen in
`afbl_jax.model`: `LinearDrag` or `RotorDrag`).

Wind velocity (earth frame, x, y, z [m/s]) at time t is the sum of

- a steady mean wind ``mean`` (3,), horizontal in practice: speed `mean_wind_speed` from the
  wind at 20 ft (W20) through the MIL-F-8785C low-altitude logarithmic profile
  W(h) = W20 ln(h / z0) / ln(20 ft / z0) (z0 = 0.15 ft, flight phase category C), in the
  direction `mean_wind_velocity` gives (the air moves towards the azimuth measured from the
  earth x axis towards y);
- G discrete gusts in the MIL-F-8785C "1-cosine" form, per axis j::

      w_j(t) = A_j / 2 * (1 - cos(pi * (t - start) / T_j))   for start <= t < start + T_j
             = A_j                                           for t >= start + T_j

  A_j the gust magnitude [m/s], T_j its build-up time [s] (the gust length d_m divided by the
  airspeed V that carries it past the vehicle); 0 before ``start``. The gust stays at A_j after
  build-up, as in the standard (a step with a smooth 1-cosine front). `gust_magnitude` ties A_j
  to the length, the Dryden scale length and sigma (see there);
- Dryden turbulence realised as a deterministic sum of K sinusoids per axis::

      w_j(t) = sum_k a_jk cos(omega_k t + phase_jk),   a_jk^2 / 2 = int_{cell k} Phi_j d omega

  with fixed log-spaced frequencies omega_k (geometric means of K log-spaced cells), random
  phases (one per case) and Phi_j the one-sided temporal Dryden PSD of MIL-HDBK-1797 (low
  altitude, `dryden_low_altitude`) carried past the vehicle at the airspeed V (for a hovering
  vehicle, the mean-wind speed). Each line carries exactly the spectrum's power in its cell
  (`dryden_band_amplitudes`, closed-form cell integrals), so the realised variance is the
  integral of Phi over [omega_min, omega_max]; what lies outside the band is lost and
  `Wind.turbulence_rms` / `dryden_band_fraction` say how much. A sum of sinusoids is smooth (an
  ordinary adaptive solver handles it).

PSD conventions (MIL-HDBK-1797 forms): Phi_j(omega) is one-sided in the temporal angular
frequency omega [rad/s], in (m/s)^2 / (rad/s): int_0^inf Phi_j(omega) d omega = sigma_j^2. It is
the one-sided spatial PSD Phi_j(Omega) [(m/s)^2 / (rad/m)] at the spatial frequency
Omega = omega / V [rad/m] divided by V (Taylor's frozen-field hypothesis). A two-sided PSD
over (-inf, inf) would be half as large.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float, Vec3
from .._validation import as_float, check_finite, check_nonnegative, check_positive, concrete

FT = 0.3048
"""Metres per foot."""
KNOT = 0.514444
"""Metres per second per knot."""
TURBULENCE_INTENSITIES = ("none", "light", "moderate", "severe")
"""Turbulence levels; index 0..3 is the level code used in result tables."""
W20_KNOTS = {"none": 0.0, "light": 15.0, "moderate": 30.0, "severe": 45.0}
"""Wind speed at 20 ft [knots] per intensity (MIL-HDBK-1797 low-altitude model)."""
ROUGHNESS_LENGTH = 0.15 * FT
"""Surface roughness length z0 of the MIL-F-8785C low-altitude wind profile [m] (category C)."""


class Wind(eqx.Module):
    """Wind field of one case (see the module docstring for the model).

    Construct with ``Wind(gust_start, gust_buildup, gust_amplitude, turbulence_amplitude,
    turbulence_frequency, turbulence_phase, mean)`` (``mean`` default (0, 0, 0)). The
    turbulence is stored in quadrature form,
    a_jk cos(omega_k t + phase_jk) = C_jk cos(omega_k t) + S_jk sin(omega_k t) with
    C = a cos(phase), S = -a sin(phase): evaluating it needs cos/sin of omega_k t only, which
    a batch whose cases share the frequencies (Monte-Carlo cases) computes once for all cases.

    Attributes:
        gust_start: gust start times, shape (G,) [s].
        gust_buildup: build-up times per axis, shape (G, 3) [s], > 0.
        gust_amplitude: amplitudes per axis (x, y, z), shape (G, 3) [m/s].
        turbulence_frequency: sinusoid frequencies omega_k, shape (K,) [rad/s].
        turbulence_cos, turbulence_sin: C_jk, S_jk, shape (3, K) [m/s].
        mean: steady mean wind, shape (3,) [m/s] (earth frame).
        turbulence_amplitude, turbulence_phase (properties): a_jk [m/s], phase_jk [rad].
        turbulence_rms (property): RMS of the realised turbulence per axis, shape (3,) [m/s]
            (sqrt(sum_k a_jk^2 / 2): the band-limited sigma).
    """

    gust_start: Float[Array, " G"]
    gust_buildup: Float[Array, "G 3"]
    gust_amplitude: Float[Array, "G 3"]
    turbulence_frequency: Float[Array, " K"]
    turbulence_cos: Float[Array, "3 K"]
    turbulence_sin: Float[Array, "3 K"]
    mean: Float[Array, " 3"]

    def __init__(
        self,
        gust_start,
        gust_buildup,
        gust_amplitude,
        turbulence_amplitude,
        turbulence_frequency,
        turbulence_phase,
        mean=None,
    ):
        self.gust_start = as_float(gust_start)
        self.gust_buildup = as_float(gust_buildup)
        self.gust_amplitude = as_float(gust_amplitude)
        self.turbulence_frequency = as_float(turbulence_frequency)
        amp, phase = as_float(turbulence_amplitude), as_float(turbulence_phase)
        owner = type(self).__name__
        if np.shape(amp) != np.shape(phase):
            raise ValueError(
                f"{owner}: turbulence_amplitude and turbulence_phase must have one "
                f"shape (3, K), got {np.shape(amp)} and {np.shape(phase)}."
            )
        check_finite(owner, "turbulence_amplitude", amp)
        check_finite(owner, "turbulence_phase", phase)
        self.turbulence_cos = amp * jnp.cos(phase)
        self.turbulence_sin = -amp * jnp.sin(phase)
        self.mean = as_float(np.zeros(3) if mean is None else mean)

    @property
    def turbulence_amplitude(self) -> Array:
        return jnp.hypot(self.turbulence_cos, self.turbulence_sin)

    @property
    def turbulence_phase(self) -> Array:
        return jnp.arctan2(-self.turbulence_sin, self.turbulence_cos)

    @property
    def turbulence_rms(self) -> Array:
        return jnp.sqrt(0.5 * jnp.sum(self.turbulence_cos**2 + self.turbulence_sin**2, axis=-1))

    def __check_init__(self):
        owner = type(self).__name__
        g = np.shape(self.gust_start)
        k = np.shape(self.turbulence_frequency)
        shapes = (
            np.shape(self.gust_buildup),
            np.shape(self.gust_amplitude),
            np.shape(self.turbulence_cos),
            np.shape(self.turbulence_sin),
        )
        if (
            len(g) < 1
            or len(k) < 1
            or shapes != ((*g, 3), (*g, 3), (*k[:-1], 3, k[-1]), (*k[:-1], 3, k[-1]))
        ):
            raise ValueError(
                f"{owner}: expected gust_start (G,), gust_buildup (G, 3), gust_amplitude (G, 3), "
                f"turbulence_frequency (K,), turbulence_amplitude (3, K), turbulence_phase "
                f"(3, K); got {g}, {shapes[0]}, {shapes[1]}, {k}, {shapes[2]}, {shapes[3]}."
            )
        if np.shape(self.mean) != (*g[:-1], 3):
            raise ValueError(f"{owner}: mean must have shape (3,), got {np.shape(self.mean)}.")
        for name in ("gust_start", "gust_amplitude", "turbulence_frequency", "mean"):
            check_finite(owner, name, getattr(self, name))
        check_positive(owner, "gust_buildup", self.gust_buildup)
        check_nonnegative(owner, "turbulence_frequency", self.turbulence_frequency)

    def __call__(self, t) -> Vec3:
        """Wind velocity (x, y, z) [m/s] in the earth frame at time t [s]."""
        tau = (t - self.gust_start[..., None]) / self.gust_buildup
        shape = 0.5 * (1.0 - jnp.cos(jnp.pi * jnp.clip(tau, 0.0, 1.0)))
        gust = jnp.sum(self.gust_amplitude * shape, axis=-2)
        arg = self.turbulence_frequency * t
        turb = jnp.einsum("...jk,...k->...j", self.turbulence_cos, jnp.cos(arg)) + jnp.einsum(
            "...jk,...k->...j", self.turbulence_sin, jnp.sin(arg)
        )
        return self.mean + gust + turb

    def jump_times(self) -> Array:
        """Gust start and end of build-up [s] (the wind's second derivative jumps there)."""
        ends = self.gust_start[..., None] + self.gust_buildup
        return jnp.concatenate([self.gust_start, ends.reshape(*ends.shape[:-2], -1)], axis=-1)


def no_wind(n_gusts: int = 0, n_frequencies: int = 0) -> Wind:
    """Calm air with the given structure (zero amplitudes)."""
    return Wind(
        np.zeros(n_gusts),
        np.ones((n_gusts, 3)),
        np.zeros((n_gusts, 3)),
        np.zeros((3, n_frequencies)),
        np.zeros(n_frequencies),
        np.zeros((3, n_frequencies)),
    )


def dryden_low_altitude(intensity: str, altitude: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(sigma, L): RMS intensities [m/s] and scale lengths [m] of the (u, v, w) components.

    MIL-HDBK-1797 low-altitude model (h < 1000 ft), h clipped to >= 10 ft:
    sigma_w = 0.1 W20, sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4,
    L_u = 2 L_v = h / (0.177 + 0.000823 h)^1.2, 2 L_w = h (h, L in ft; returned in m).
    ``intensity`` is one of `TURBULENCE_INTENSITIES`; ``altitude`` in m.
    """
    if intensity not in W20_KNOTS:
        raise ValueError(
            f"unknown turbulence intensity {intensity!r}; allowed: "
            f"{', '.join(TURBULENCE_INTENSITIES)}."
        )
    h = max(altitude / FT, 10.0)
    sigma_w = 0.1 * W20_KNOTS[intensity] * KNOT
    sigma_u = sigma_w / (0.177 + 0.000823 * h) ** 0.4
    lu = h / (0.177 + 0.000823 * h) ** 1.2
    sigma = np.array([sigma_u, sigma_u, sigma_w])
    scale = np.array([lu, lu / 2.0, h / 2.0]) * FT
    return sigma, scale


def w20(intensity: str) -> float:
    """Wind speed at 20 ft, W20 [m/s], of a turbulence intensity (`W20_KNOTS`)."""
    if intensity not in W20_KNOTS:
        raise ValueError(
            f"unknown turbulence intensity {intensity!r}; allowed: "
            f"{', '.join(TURBULENCE_INTENSITIES)}."
        )
    return W20_KNOTS[intensity] * KNOT


def mean_wind_speed(w20_speed, altitude, roughness: float = ROUGHNESS_LENGTH):
    """Mean wind speed at ``altitude`` [m] from the wind at 20 ft ``w20_speed`` [m/s]:
    the MIL-F-8785C low-altitude logarithmic profile W20 ln(h / z0) / ln(20 ft / z0), z0 =
    ``roughness`` [m] (default 0.15 ft, category C); ``altitude`` must exceed z0."""
    h = concrete(altitude)
    if h is not None and not np.all(h > roughness):
        raise ValueError(
            f"mean_wind_speed: altitude must exceed the roughness length {roughness} m, got {h}."
        )
    return w20_speed * jnp.log(altitude / roughness) / jnp.log(20.0 * FT / roughness)


def mean_wind_velocity(speed, direction) -> Array:
    """Horizontal mean-wind vector (x, y, 0) [m/s]: ``speed`` [m/s] towards the azimuth
    ``direction`` [rad] (from the earth x axis towards y; the air moves that way)."""
    speed = jnp.asarray(speed, dtype=float)
    return jnp.stack(
        [speed * jnp.cos(direction), speed * jnp.sin(direction), jnp.zeros_like(speed)], axis=-1
    )


def dryden_psd(omega, sigma, scale, airspeed) -> Array:
    """One-sided temporal Dryden PSDs Phi_j(omega) [(m/s)^2 / (rad/s)], shape (3, len(omega)).

    MIL-HDBK-1797 forms with Omega = omega / V::

        Phi_u = sigma_u^2 (2 L_u / pi) / (1 + (L_u Omega)^2) / V
        Phi_v = sigma_v^2 (2 L_v / pi) (1 + 12 (L_v Omega)^2) / (1 + 4 (L_v Omega)^2)^2 / V

    and Phi_w like Phi_v with (sigma_w, L_w). Each integrates to sigma_j^2 over [0, inf).
    """
    omega = jnp.asarray(omega, dtype=float)
    sigma, scale = jnp.asarray(sigma, dtype=float), jnp.asarray(scale, dtype=float)
    x = scale[:, None] * omega[None, :] / airspeed
    base = sigma[:, None] ** 2 * 2.0 * scale[:, None] / (jnp.pi * airspeed)
    long = base / (1.0 + x**2)
    lat = base * (1.0 + 12.0 * x**2) / (1.0 + 4.0 * x**2) ** 2
    return jnp.stack([long[0], lat[1], lat[2]])


def dryden_cumulative(omega, sigma, scale, airspeed) -> Array:
    """int_0^omega Phi_j [(m/s)^2], shape (3, len(omega)) (closed form of `dryden_psd`'s
    integral): sigma_u^2 (2/pi) atan(x_u) with x_u = L_u omega / V, and
    sigma^2 (2 atan(x) - x / (1 + x^2)) / pi with x = 2 L omega / V for v and w."""
    omega = jnp.asarray(omega, dtype=float)
    sigma, scale = jnp.asarray(sigma, dtype=float), jnp.asarray(scale, dtype=float)
    x = scale[:, None] * omega[None, :] / airspeed
    long = sigma[0] ** 2 * (2.0 / jnp.pi) * jnp.arctan(x[0])
    xl = 2.0 * x[1:]
    lat = sigma[1:, None] ** 2 * (2.0 * jnp.arctan(xl) - xl / (1.0 + xl**2)) / jnp.pi
    return jnp.concatenate([long[None], lat])


def dryden_correlation(separation, scale) -> Array:
    """Autocorrelation coefficients rho_j(r) of the Dryden u, v, w fields at the separation
    ``separation`` [m] (shape (3,) or broadcastable), shape (3,): exp(-r / L_u) and
    (1 - r / (4 L)) exp(-r / (2 L)) for v and w (the cosine transforms of `dryden_psd`'s
    spatial forms)."""
    r = jnp.asarray(separation, dtype=float) * jnp.ones(3)
    scale = jnp.asarray(scale, dtype=float)
    long = jnp.exp(-r[0] / scale[0])
    lat = (1.0 - r[1:] / (4.0 * scale[1:])) * jnp.exp(-r[1:] / (2.0 * scale[1:]))
    return jnp.concatenate([long[None], lat])


def gust_magnitude(length, sigma, scale) -> Array:
    """Discrete-gust magnitudes tied to the turbulence, per axis (u, v, w) [m/s], shape (3,):
    the RMS change of the Dryden field over the gust length d_m,
    sigma_j sqrt(2 (1 - rho_j(d_m))) (``length`` [m], shape (3,) or scalar; ``sigma`` [m/s]
    and ``scale`` [m] as `dryden_low_altitude` returns them).

    MIL-F-8785C gives the gust magnitude as a function of d_m / L and sigma in a chart (its
    figure 8), which is not reproduced numerically here; this is the standard's dependence on
    (d_m, L, sigma) written with the velocity-increment statistics of the same Dryden field
    (docs/paper_notes.md, wind section). A Monte-Carlo case scales it by a sampled number of
    standard deviations."""
    rho = dryden_correlation(length, scale)
    return jnp.asarray(sigma, dtype=float) * jnp.sqrt(jnp.maximum(2.0 * (1.0 - rho), 0.0))


def turbulence_grid(n_frequencies: int, omega_min: float, omega_max: float):
    """Log-spaced frequencies omega_k [rad/s] (geometric means of K log-spaced cells over
    [omega_min, omega_max]) and the cell widths d omega_k."""
    edges = turbulence_edges(n_frequencies, omega_min, omega_max)
    omega = np.sqrt(edges[:-1] * edges[1:])
    return omega, np.diff(edges)


def turbulence_edges(n_frequencies: int, omega_min: float, omega_max: float) -> np.ndarray:
    """The K + 1 cell edges [rad/s] of `turbulence_grid`."""
    if n_frequencies < 1 or not 0 < omega_min < omega_max:
        raise ValueError(
            f"turbulence grid needs n >= 1 and 0 < omega_min < omega_max, got "
            f"{n_frequencies}, {omega_min}, {omega_max}."
        )
    return np.geomspace(omega_min, omega_max, n_frequencies + 1)


def dryden_band_amplitudes(edges, sigma, scale, airspeed) -> Array:
    """Sinusoid amplitudes a_jk = sqrt(2 int_{cell k} Phi_j d omega), shape (3, K) [m/s], for
    the cells between ``edges`` (K + 1) [rad/s]; all zero where ``airspeed`` <= 0 or sigma = 0
    (calm air)."""
    v = jnp.asarray(airspeed, dtype=float)
    safe_v = jnp.where(v > 0, v, 1.0)
    cum = dryden_cumulative(edges, sigma, scale, safe_v)
    power = jnp.maximum(jnp.diff(cum, axis=-1), 0.0)
    return jnp.where(v > 0, jnp.sqrt(2.0 * power), 0.0)


def dryden_band_fraction(edges, scale, airspeed) -> Array:
    """Fraction of sigma_j^2 the band [edges[0], edges[-1]] realises, shape (3,)."""
    band = dryden_cumulative(jnp.asarray([edges[0], edges[-1]]), jnp.ones(3), scale, airspeed)
    return band[:, 1] - band[:, 0]


def dryden_amplitudes(intensity: str, altitude: float, airspeed: float, omega, domega):
    """Sinusoid amplitudes a_jk, shape (3, K) [m/s], of an intensity at ``altitude`` [m]
    carried at ``airspeed`` [m/s] (`dryden_band_amplitudes` on the geometric cells whose
    means and widths are ``omega``, ``domega``, e.g. from `turbulence_grid`)."""
    sigma, scale = dryden_low_altitude(intensity, altitude)
    omega, domega = np.asarray(omega, float), np.asarray(domega, float)
    lower = 0.5 * (np.sqrt(domega**2 + 4.0 * omega**2) - domega)
    edges = np.append(lower, lower[-1] + domega[-1])
    return np.asarray(dryden_band_amplitudes(edges, sigma, scale, airspeed))
