"""How the controller samples the loop: continuously, or digitally with a zero-order hold.

- `ContinuousControl`: the controller acts on the true state at every instant; its own state
  is part of the ODE.
- `DigitalControl`: sample k at t_k = t0 + k / f_c. The true plant state is measured (paper
  layout, plus Gaussian noise keyed by ``fold_in(key, k)``; x, y, xd, yd are not used by the
  controllers and carry no noise), pushed into a ring buffer, and the measurement from
  ``delay_samples`` samples earlier (the initial noise-free measurement before that many samples
  exist) goes to the controller with the reference r(t_k). Its command is held (zero-order
  hold) over [t_k, t_k+1); its own state is advanced by a forward-Euler step (the usual digital
  PID / adaptive law). ``max_samples`` (static) is the number of samples the run may take
  (>= (t1 - t0) f_c, else the run stops early with status ``max_steps``); ``max_delay``
  (static) is the ring buffer's capacity.

Every dynamic field is a pytree leaf (vmap over rates, delays, noise levels and keys).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Int, PlantState, Scalar
from .._validation import as_float, check_nonnegative, concrete

NOISE_FIELDS: tuple[str, ...] = (
    "noise_angle",
    "noise_rate",
    "noise_altitude",
    "noise_vertical_speed",
)


def as_int(x) -> Array:
    return jnp.asarray(x, dtype=jnp.int32)


def as_key(x) -> Array:
    """A JAX PRNG key (uint32, shape (2,)); an int is taken as a seed."""
    if isinstance(x, int | np.integer):
        return jax.random.PRNGKey(int(x))
    return jnp.asarray(x, dtype=jnp.uint32)


class AbstractSampling(eqx.Module):
    """Continuous or digital control (a static choice by type)."""

    digital: eqx.AbstractClassVar[bool]


class ContinuousControl(AbstractSampling):
    """The controller sees the true state at every instant (the paper's loop)."""

    digital: ClassVar[bool] = False


class DigitalControl(AbstractSampling):
    """Digital controller with zero-order hold, whole-sample delay and seeded noise (module
    docstring). Units: ``control_rate`` [Hz], noise standard deviations [rad], [rad/s], [m],
    [m/s]."""

    digital: ClassVar[bool] = True
    max_samples: int = eqx.field(static=True)
    control_rate: Scalar = eqx.field(default=250.0, converter=as_float)
    delay_samples: Int[Array, ""] = eqx.field(default=0, converter=as_int)
    max_delay: int = eqx.field(default=8, static=True)
    noise_angle: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_rate: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_altitude: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_vertical_speed: Scalar = eqx.field(default=0.0, converter=as_float)
    key: Array = eqx.field(default=0, converter=as_key)

    def __check_init__(self):
        owner = type(self).__name__
        if not isinstance(self.max_samples, int) or self.max_samples < 1:
            raise ValueError(f"{owner}.max_samples must be an int >= 1, got {self.max_samples!r}.")
        if not isinstance(self.max_delay, int) or self.max_delay < 0:
            raise ValueError(f"{owner}.max_delay must be an int >= 0, got {self.max_delay!r}.")
        for name in NOISE_FIELDS:
            check_nonnegative(owner, name, getattr(self, name))
        rate = concrete(self.control_rate)
        if rate is not None and not (np.all(np.isfinite(rate)) and np.all(rate > 0)):
            raise ValueError(f"{owner}.control_rate must be finite and > 0 [Hz], got {rate!r}.")
        delay = concrete(self.delay_samples)
        if delay is not None and not (np.all(delay >= 0) and np.all(delay <= self.max_delay)):
            raise ValueError(
                f"{owner}.delay_samples must be in [0, max_delay = "
                f"{self.max_delay}], got {delay!r}."
            )

    def noise_std(self) -> PlantState:
        """Per-entry measurement-noise standard deviation, paper state layout, shape (12,)."""
        return noise_std(self)

    def noise(self, k) -> PlantState:
        """The measurement noise added at sample k (`measurement_noise`)."""
        return measurement_noise(self, k)


def noise_std(settings) -> PlantState:
    """Noise standard deviations of ``settings`` (anything with the four noise fields) in the
    paper state layout, shape (12,)."""
    z = jnp.zeros_like(settings.noise_angle)
    a, r = settings.noise_angle, settings.noise_rate
    return jnp.stack(
        [z, z, settings.noise_altitude, a, a, a, z, z, settings.noise_vertical_speed, r, r, r]
    )


def measurement_noise(settings, k) -> PlantState:
    """The measurement noise added at control sample k (paper layout, shape (12,)).

    Gaussian, zero mean, standard deviations `noise_std`, drawn from
    ``jax.random.fold_in(settings.key, k)`` in JAX's default float and cast to the settings'
    dtype: the same key and k always give the same noise, in every precision.
    """
    sub = jax.random.fold_in(settings.key, k)
    std = noise_std(settings)
    return std * jax.random.normal(sub, (12,), dtype=jnp.result_type(float)).astype(std.dtype)
