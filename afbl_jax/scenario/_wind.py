"""Wind: discrete 1-cosine gusts and Dryden turbulence (the air the vehicle flies through; the
aerodynamic model that turns it into force and torque is `afbl_jax.model.LinearDrag`).

Wind velocity (earth frame, x, y, z [m/s]) at time t is the sum of

- G discrete gusts in the MIL-F-8785C "1-cosine" form, per axis j::

      w_j(t) = A_j / 2 * (1 - cos(pi * (t - start) / T_j))   for start <= t < start + T_j
             = A_j                                           for t >= start + T_j

  A_j the gust amplitude [m/s], T_j its build-up time [s] (the standard's build-up length d_m
  divided by the airspeed); 0 before ``start``. The gust stays at A_j after build-up, as in the
  standard (a step with a smooth 1-cosine front);
- Dryden turbulence realised as a deterministic sum of K sinusoids per axis::

      w_j(t) = sum_k a_jk cos(omega_k t + phase_jk),   a_jk = sqrt(2 Phi_j(omega_k) d omega_k)

  with fixed log-spaced frequencies omega_k, random phases (one per case) and Phi_j the
  one-sided temporal Dryden PSD of MIL-HDBK-1797 (low altitude, see `dryden_low_altitude`).
  A sum of sinusoids is smooth (no SDE needed: an ordinary adaptive solver handles it) and gives
  exactly the spectrum's power in each frequency band; its variance is the integral of Phi over
  the band [omega_1, omega_K] (frequencies outside the band are left out, which the tests check
  is a small fraction of sigma^2).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float, Vec3
from .._validation import as_float, check_finite, check_nonnegative, check_positive

FT = 0.3048
"""Metres per foot."""
KNOT = 0.514444
"""Metres per second per knot."""
TURBULENCE_INTENSITIES = ("none", "light", "moderate", "severe")
"""Turbulence levels; index 0..3 is the level code used in result tables."""
W20_KNOTS = {"none": 0.0, "light": 15.0, "moderate": 30.0, "severe": 45.0}
"""Wind speed at 20 ft [knots] per intensity (MIL-HDBK-1797 low-altitude model)."""


class Wind(eqx.Module):
    """Wind field of one case (see the module docstring for the model).

    Construct with ``Wind(gust_start, gust_buildup, gust_amplitude, turbulence_amplitude,
    turbulence_frequency, turbulence_phase)``. The turbulence is stored in quadrature form,
    a_jk cos(omega_k t + phase_jk) = C_jk cos(omega_k t) + S_jk sin(omega_k t) with
    C = a cos(phase), S = -a sin(phase): evaluating it needs cos/sin of omega_k t only, which
    a batch whose cases share the frequencies (Monte-Carlo cases) computes once for all cases.

    Attributes:
        gust_start: gust start times, shape (G,) [s].
        gust_buildup: build-up times per axis, shape (G, 3) [s], > 0.
        gust_amplitude: amplitudes per axis (x, y, z), shape (G, 3) [m/s].
        turbulence_frequency: sinusoid frequencies omega_k, shape (K,) [rad/s].
        turbulence_cos, turbulence_sin: C_jk, S_jk, shape (3, K) [m/s].
        turbulence_amplitude, turbulence_phase (properties): a_jk [m/s], phase_jk [rad].
    """

    gust_start: Float[Array, " G"]
    gust_buildup: Float[Array, "G 3"]
    gust_amplitude: Float[Array, "G 3"]
    turbulence_frequency: Float[Array, " K"]
    turbulence_cos: Float[Array, "3 K"]
    turbulence_sin: Float[Array, "3 K"]

    def __init__(
        self,
        gust_start,
        gust_buildup,
        gust_amplitude,
        turbulence_amplitude,
        turbulence_frequency,
        turbulence_phase,
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

    @property
    def turbulence_amplitude(self) -> Array:
        return jnp.hypot(self.turbulence_cos, self.turbulence_sin)

    @property
    def turbulence_phase(self) -> Array:
        return jnp.arctan2(-self.turbulence_sin, self.turbulence_cos)

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
        for name in ("gust_start", "gust_amplitude", "turbulence_frequency"):
            check_finite(owner, name, getattr(self, name))
        check_positive(owner, "gust_buildup", self.gust_buildup)
        check_nonnegative(owner, "turbulence_frequency", self.turbulence_frequency)

    def __call__(self, t) -> Vec3:
        """Wind velocity (x, y, z) in the earth frame at time t [s] [m/s]."""
        tau = (t - self.gust_start[..., None]) / self.gust_buildup
        shape = 0.5 * (1.0 - jnp.cos(jnp.pi * jnp.clip(tau, 0.0, 1.0)))
        gust = jnp.sum(self.gust_amplitude * shape, axis=-2)
        arg = self.turbulence_frequency * t
        turb = jnp.einsum("...jk,...k->...j", self.turbulence_cos, jnp.cos(arg)) + jnp.einsum(
            "...jk,...k->...j", self.turbulence_sin, jnp.sin(arg)
        )
        return gust + turb

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


def dryden_psd(omega, sigma, scale, airspeed: float) -> np.ndarray:
    """One-sided temporal Dryden PSDs Phi_j(omega) [(m/s)^2 / (rad/s)], shape (3, len(omega)).

    MIL-HDBK-1797 forms with Omega = omega / V::

        Phi_u = sigma_u^2 (2 L_u / pi) / (1 + (L_u Omega)^2) / V
        Phi_v = sigma_v^2 (2 L_v / pi) (1 + 12 (L_v Omega)^2) / (1 + 4 (L_v Omega)^2)^2 / V

    and Phi_w like Phi_v with (sigma_w, L_w). Each integrates to sigma_j^2 over [0, inf).
    """
    omega = np.asarray(omega, dtype=float)
    sigma, scale = np.asarray(sigma, float), np.asarray(scale, float)
    x = scale[:, None] * omega[None, :] / airspeed
    base = sigma[:, None] ** 2 * 2.0 * scale[:, None] / (np.pi * airspeed)
    long = base / (1.0 + x**2)
    lat = base * (1.0 + 12.0 * x**2) / (1.0 + 4.0 * x**2) ** 2
    return np.stack([long[0], lat[1], lat[2]])


def turbulence_grid(n_frequencies: int, omega_min: float, omega_max: float):
    """Log-spaced frequencies omega_k [rad/s] and their bandwidths d omega_k (geometric cells)."""
    if n_frequencies < 1 or not 0 < omega_min < omega_max:
        raise ValueError(
            f"turbulence grid needs n >= 1 and 0 < omega_min < omega_max, got "
            f"{n_frequencies}, {omega_min}, {omega_max}."
        )
    edges = np.geomspace(omega_min, omega_max, n_frequencies + 1)
    omega = np.sqrt(edges[:-1] * edges[1:])
    return omega, np.diff(edges)


def dryden_amplitudes(intensity: str, altitude: float, airspeed: float, omega, domega):
    """Sinusoid amplitudes a_jk = sqrt(2 Phi_j(omega_k) d omega_k), shape (3, K) [m/s]."""
    sigma, scale = dryden_low_altitude(intensity, altitude)
    if intensity == "none":
        return np.zeros((3, len(omega)))
    return np.sqrt(2.0 * dryden_psd(omega, sigma, scale, airspeed) * domega[None, :])
