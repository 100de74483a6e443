"""Unmodeled dynamics: the settings bundle that makes the simulated vehicle and loop differ from
the paper's model (full rigid-body plant, motor lag, digital control with noise and delay).

The controllers stay designed on the paper's eq. (15) model. ``simulate(..., unmodeled=None)``
is the paper's closed loop; ``unmodeled=UnmodeledDynamics(...)`` composes the closed loop from
the parts it names (`UnmodeledDynamics.plant_model`, `.actuator_model`, `.sampling_model`).

Per-case settings (`UnmodeledDynamics`, an `equinox.Module`)
------------------------------------------------------------
=================  =======  ===============================================================
field              kind     meaning
=================  =======  ===============================================================
plant              static   ``"paper"`` (`PaperPlant`, eq. 15) or ``"full"`` (`RigidBodyPlant`)
motor_tau          dynamic  rotor time constant tau_m [s] (`FirstOrderRotors`); 0 =
                            instantaneous rotors
max_samples        static   0 = continuous controller; > 0 = digital controller
                            (`DigitalControl`), number of control samples the run may take
                            (>= (t1 - t0) * control_rate, else the run stops early with status
                            ``max_steps``)
control_rate       dynamic  controller rate f_c [Hz] (used when max_samples > 0)
delay_samples      dynamic  transport delay of the measurements, in whole samples (int)
max_delay          static   capacity of the delay ring buffer (delay_samples <= max_delay)
noise_angle        dynamic  std of the measured phi, theta, psi [rad]
noise_rate         dynamic  std of the measured phid, thetad, psid [rad/s]
noise_altitude     dynamic  std of the measured z [m]
noise_vertical_    dynamic  std of the measured zd [m/s]
  speed
key                dynamic  jax PRNG key (uint32, shape (2,)); an int seed is converted
=================  =======  ===============================================================

Every dynamic field is a pytree leaf: a batch of settings is one `UnmodeledDynamics` whose
leaves have a leading batch axis (build it with `stack_unmodeled`). The static fields must agree
within a batch (the number of samples and the buffer size are static; cases with a lower f_c
finish early and idle). In `afbl_jax.simulate_batch`'s ensemble strategy the cases of one
ensemble group share their sample instants, so they must share ``control_rate`` (the
Monte-Carlo sampler draws one rate per group).

Cost: a digital loop of T seconds at f_c takes T f_c sample intervals (5000 for a 20 s run at
250 Hz), each at least one solver step, where a continuous loop takes the steps its tolerance
needs.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Int, PlantState, Scalar
from .._validation import as_float, check_nonnegative, concrete
from ._actuators import FirstOrderRotors
from ._plant import PLANT_MODELS, AbstractPlant, make_plant
from ._sampling import (
    NOISE_FIELDS,
    AbstractSampling,
    ContinuousControl,
    DigitalControl,
    as_int,
    as_key,
    measurement_noise,
    noise_std,
)


class UnmodeledDynamics(eqx.Module):
    """Per-case unmodeled-dynamics settings; layout and meaning in the module docstring.

    The default instance is the paper's model with a continuous controller (equivalent to
    ``simulate(..., unmodeled=None)`` up to round-off).
    """

    plant: str = eqx.field(default="paper", static=True)
    motor_tau: Scalar = eqx.field(default=0.0, converter=as_float)
    max_samples: int = eqx.field(default=0, static=True)
    control_rate: Scalar = eqx.field(default=1000.0, converter=as_float)
    delay_samples: Int[Array, ""] = eqx.field(default=0, converter=as_int)
    max_delay: int = eqx.field(default=8, static=True)
    noise_angle: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_rate: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_altitude: Scalar = eqx.field(default=0.0, converter=as_float)
    noise_vertical_speed: Scalar = eqx.field(default=0.0, converter=as_float)
    key: Array = eqx.field(default=0, converter=as_key)

    def __check_init__(self):
        owner = type(self).__name__
        if self.plant not in PLANT_MODELS:
            raise ValueError(
                f"{owner}.plant must be one of {', '.join(PLANT_MODELS)}, got {self.plant!r}."
            )
        if not isinstance(self.max_samples, int) or self.max_samples < 0:
            raise ValueError(f"{owner}.max_samples must be an int >= 0, got {self.max_samples!r}.")
        if not isinstance(self.max_delay, int) or self.max_delay < 0:
            raise ValueError(f"{owner}.max_delay must be an int >= 0, got {self.max_delay!r}.")
        check_nonnegative(owner, "motor_tau", self.motor_tau)
        for name in NOISE_FIELDS:
            check_nonnegative(owner, name, getattr(self, name))
        tau = concrete(self.motor_tau)
        if tau is not None and not np.all(np.isfinite(tau)):
            raise ValueError(f"{owner}.motor_tau must be finite [s], got {tau!r}.")
        delay = concrete(self.delay_samples)
        if delay is not None and not (np.all(delay >= 0) and np.all(delay <= self.max_delay)):
            raise ValueError(
                f"{owner}.delay_samples must be in [0, max_delay = {self.max_delay}], got "
                f"{delay!r}."
            )
        rate = concrete(self.control_rate)
        if self.max_samples > 0:
            if rate is not None and not (np.all(np.isfinite(rate)) and np.all(rate > 0)):
                raise ValueError(f"{owner}.control_rate must be finite and > 0 [Hz], got {rate!r}.")
        else:
            extra = [
                n
                for n in NOISE_FIELDS
                if (v := concrete(getattr(self, n))) is not None and np.any(v != 0)
            ]
            if delay is not None and np.any(delay != 0):
                extra.append("delay_samples")
            if extra:
                raise ValueError(
                    f"{owner}: {', '.join(extra)} need a digital controller (max_samples > 0; "
                    "use UnmodeledDynamics.make(control_rate=..., duration=...))."
                )

    @property
    def digital(self) -> bool:
        return self.max_samples > 0

    @classmethod
    def make(
        cls,
        plant: str = "paper",
        motor_tau: float = 0.0,
        control_rate: float | None = None,
        duration: float = 20.0,
        delay_samples: int = 0,
        noise_angle: float = 0.0,
        noise_rate: float = 0.0,
        noise_altitude: float = 0.0,
        noise_vertical_speed: float = 0.0,
        seed: int = 0,
        max_delay: int | None = None,
        max_samples: int | None = None,
    ) -> UnmodeledDynamics:
        """Convenience constructor: ``control_rate`` None = continuous controller, else a
        digital controller at that rate [Hz] with ``max_samples = ceil(duration * rate)``
        (``duration`` = t1 - t0 of the scenarios it will run [s]) unless given (a common
        ``max_samples`` lets settings with different rates share one batch / compilation)."""
        if control_rate is None:
            max_samples = 0
        elif max_samples is None:
            max_samples = int(math.ceil(duration * control_rate - 1e-9))
        return cls(
            plant=plant,
            motor_tau=motor_tau,
            max_samples=max_samples,
            control_rate=1000.0 if control_rate is None else control_rate,
            delay_samples=delay_samples,
            max_delay=max(8, delay_samples) if max_delay is None else max_delay,
            noise_angle=noise_angle,
            noise_rate=noise_rate,
            noise_altitude=noise_altitude,
            noise_vertical_speed=noise_vertical_speed,
            key=seed,
        )

    def noise_std(self) -> PlantState:
        """Per-entry measurement-noise standard deviation, paper state layout, shape (12,)."""
        return noise_std(self)

    def plant_model(self) -> AbstractPlant:
        """The plant these settings name (`PaperPlant` or `RigidBodyPlant`)."""
        return make_plant(self.plant)

    def actuator_model(self) -> FirstOrderRotors:
        """`FirstOrderRotors` with ``tau_m = motor_tau`` (0: instantaneous)."""
        return FirstOrderRotors(self.motor_tau)

    def sampling_model(self) -> AbstractSampling:
        """`ContinuousControl` (max_samples = 0) or the `DigitalControl` these settings name."""
        if not self.digital:
            return ContinuousControl()
        return DigitalControl(
            max_samples=self.max_samples,
            control_rate=self.control_rate,
            delay_samples=self.delay_samples,
            max_delay=self.max_delay,
            noise_angle=self.noise_angle,
            noise_rate=self.noise_rate,
            noise_altitude=self.noise_altitude,
            noise_vertical_speed=self.noise_vertical_speed,
            key=self.key,
        )


def unmodeled_config(settings: UnmodeledDynamics) -> dict:
    """Plain-JSON description of (unbatched) settings, for result-file metadata."""
    out: dict = {
        "plant": settings.plant,
        "max_samples": settings.max_samples,
        "max_delay": settings.max_delay,
    }
    for name in ("motor_tau", "control_rate", "delay_samples", *NOISE_FIELDS):
        out[name] = np.asarray(getattr(settings, name)).tolist()
    out["key"] = np.asarray(settings.key).tolist()
    out["digital"] = settings.digital
    return out


def stack_unmodeled(settings: list[UnmodeledDynamics]) -> UnmodeledDynamics:
    """Stack settings with equal static fields along a new leading axis (for `jax.vmap`)."""
    if not settings:
        raise ValueError("stack_unmodeled needs at least one UnmodeledDynamics.")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *settings)


def measure(settings: UnmodeledDynamics, state: PlantState, k) -> PlantState:
    """What the digital controller measures at sample k: paper-layout state plus noise."""
    return settings.plant_model().to_paper_layout(state) + measurement_noise(settings, k)
