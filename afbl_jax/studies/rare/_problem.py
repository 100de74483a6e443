"""The failure margin as a function of a case's standard variates (`MarginProblem`).

A case of a `Distribution` is a point u of the unit cube [0, 1]^D of standard variates
(`afbl_jax.studies.montecarlo.draw_variates`; the distribution is uniform there). `MarginProblem`
evaluates, for one controller, the margin of a controller failure of a batch of such points:
min(failure margin, envelope margin) (`afbl_jax.failure_margin` of the run, > 0 = the run
failed; the case's flight-envelope margin, >= 0 inside the envelope), > 0 exactly when a case
inside the vehicle's flight envelope failed (a case outside it is never a controller failure),
a batch of such points on the fast path (`afbl_jax.simulate_batch`, ensembles) and its
differentiable variant with gradients (`afbl_jax.smooth_margin` through ``jax.vmap`` of
`afbl_jax.simulate`, diffrax's recursive-checkpoint adjoint, float64), and counts the
simulations it ran.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...metrics import (
    FAILURE_ALTITUDE,
    FAILURE_ATTITUDE,
    BatchMetrics,
    failure_margin,
    metrics_from_result,
    smooth_margin,
)
from ...model import AbstractController, make_aerodynamics
from ...sim import simulate, simulate_batch
from ..montecarlo import (
    GROUP_SIZE,
    Distribution,
    case_map,
    cases_from_variates,
    discrete_variates,
    fixed_variates,
    nominal_model,
    position_loop_of,
    variate_names,
)


@dataclass
class MarginProblem:
    """Failure margin of ``controller`` over the variates of ``distribution``.

    Attributes:
        controller: the controller flown.
        distribution: the case distribution (``[unmodeled]`` off).
        attitude_limit [rad], altitude_limit [m]: failure limits (None: the divergence limits,
            where failed <=> status not ok).
        rtol, atol, n_save, max_steps: solver settings.
        dtype: floating dtype of the margin solves (`margin`; None: float64, the default;
            "float32" with rtol 3e-6, atol 3e-7 is the crude Monte-Carlo study's default
            ``ensemble_f32`` path); gradients are always float64.
        temperature: of `afbl_jax.smooth_margin`.
        simulations: forward simulations run so far; gradient_simulations: simulations run
            with their gradient (each costs a forward and a backward solve).
    """

    controller: AbstractController
    distribution: Distribution
    attitude_limit: float | None = None
    altitude_limit: float | None = None
    rtol: float = 1e-6
    atol: float = 1e-8
    n_save: int = 401
    max_steps: int = 16384
    temperature: float = 0.05
    dtype: str | None = None
    simulations: int = 0
    gradient_simulations: int = 0

    @property
    def dimension(self) -> int:
        return len(variate_names(self.distribution))

    @property
    def names(self) -> tuple[str, ...]:
        return variate_names(self.distribution)

    @property
    def free(self) -> np.ndarray:
        """Variates a gradient can move: continuous ones whose range is not a single value."""
        return ~discrete_variates(self.distribution) & ~fixed_variates(self.distribution)

    def _limits(self):
        return self.attitude_limit, self.altitude_limit

    def metrics(self, u) -> BatchMetrics:
        """`BatchMetrics` of the cases at variates u (n, D) (padded to whole ensemble groups;
        n = 0: empty fields, nothing solved)."""
        return self.evaluate(u)[0]

    def evaluate(self, u) -> tuple[BatchMetrics, np.ndarray]:
        """(`BatchMetrics`, envelope margins (n,)) of the cases at variates u (n, D)."""
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        if u.ndim != 2 or u.shape[1] != self.dimension:
            raise ValueError(
                f"variates must have shape (n, {self.dimension}) (one row per case), got {u.shape}."
            )
        n = u.shape[0]
        if n == 0:
            return _empty_metrics(self.dtype), np.zeros(0)
        pad = -n % GROUP_SIZE
        if pad:
            u = np.concatenate([u, np.repeat(u[-1:], pad, axis=0)])
        chunk = cases_from_variates(self.distribution, u)
        envelope = np.asarray(chunk.inputs["envelope_margin"])[:n]
        m = simulate_batch(
            self.controller,
            chunk.scenario,
            chunk.vehicle,
            chunk.model,
            aerodynamics=chunk.aerodynamics,
            position_loop=chunk.position_loop,
            strategy="ensemble",
            rtol=self.rtol,
            atol=self.atol,
            max_steps=self.max_steps,
            n_save=self.n_save,
            group_size=GROUP_SIZE,
            dtype=self.dtype,
        )
        self.simulations += n
        return jax.tree.map(lambda x: x[:n], m), envelope

    def margin(self, u) -> np.ndarray:
        """Controller-failure margins (n,) at variates u (n, D) (clipped to [0, 1]): the
        smaller of the run's failure margin and the case's envelope margin; > 0 = a case
        inside the flight envelope failed."""
        return self.margin_of(*self.evaluate(u))

    def margin_of(self, metrics: BatchMetrics, envelope: np.ndarray) -> np.ndarray:
        """`margin` from the runs' metrics and the cases' envelope margins (`evaluate`)."""
        return np.minimum(np.asarray(failure_margin(metrics, *self._limits())), envelope)

    def value_and_grad(
        self, u, output: str = "margin"
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(value (n,), its gradient (n, D) w.r.t. u, exact margin (n,)) at u (n, D) (clipped
        to [0, 1]), one float64 solve with its adjoint per point. ``output``: "margin" (the
        smooth margin) or "ise_attitude" [rad^2 s]. Non-finite gradient entries are set to 0.
        n = 0: empty arrays, nothing solved."""
        if output not in ("margin", "ise_attitude"):
            raise ValueError(f"output must be margin or ise_attitude, got {output!r}.")
        fn = _grad_function(
            self.distribution,
            self.attitude_limit,
            self.altitude_limit,
            self.rtol,
            self.atol,
            self.n_save,
            self.max_steps,
            self.temperature,
            output,
        )
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        if u.ndim != 2 or u.shape[1] != self.dimension:
            raise ValueError(
                f"variates must have shape (n, {self.dimension}) (one row per case), got {u.shape}."
            )
        if u.shape[0] == 0:
            return np.zeros(0), np.zeros((0, self.dimension)), np.zeros(0)
        value, grad, exact = fn(self.controller, jnp.asarray(u))
        self.gradient_simulations += int(u.shape[0])
        return np.asarray(value), np.asarray(grad), np.asarray(exact)


def _empty_metrics(dtype) -> BatchMetrics:
    """`BatchMetrics` of no cases, with the dtypes of the ensemble path's."""
    f = jnp.zeros((0,), np.dtype("float64" if dtype is None else dtype))
    i = jnp.zeros((0,), jnp.int32)
    return BatchMetrics(f, f, f, f, i, f, i, i, f, f, f, f, f, i, f)


@functools.lru_cache(maxsize=16)
def _grad_function(
    distribution, attitude_limit, altitude_limit, rtol, atol, n_save, max_steps, temperature, output
):
    """The jitted batched (value, gradient, exact margin) function of one configuration (cached:
    problems with the same settings share the compiled program; the controller is an
    argument)."""
    p = MarginProblem(
        None,
        distribution,
        attitude_limit,
        altitude_limit,
        rtol,
        atol,
        n_save,
        max_steps,
        temperature,
    )
    one_case = case_map(p.distribution)
    aero = make_aerodynamics(p.distribution.spec["aero"]["model"])
    position_loop = position_loop_of(p.distribution)
    model = nominal_model(p.distribution)
    att = FAILURE_ATTITUDE if p.attitude_limit is None else p.attitude_limit
    alt = FAILURE_ALTITUDE if p.altitude_limit is None else p.altitude_limit

    def margins(controller, u):
        scenario, vehicle, inputs = one_case(u)
        envelope = inputs["envelope_margin"]
        r = simulate(
            controller,
            scenario,
            vehicle,
            model,
            rtol=p.rtol,
            atol=p.atol,
            n_save=p.n_save,
            max_steps=p.max_steps,
            aerodynamics=aero,
            position_loop=position_loop,
        )
        m = metrics_from_result(r, vehicle, model)
        exact = jnp.minimum(failure_margin(m, *p._limits()), envelope)
        if output == "ise_attitude":
            return m.ise_attitude, exact
        return jnp.minimum(smooth_margin(m, att, alt, p.temperature), envelope), exact

    def one(controller, u):
        (value, exact), grad = jax.value_and_grad(margins, argnums=1, has_aux=True)(controller, u)
        return value, jnp.where(jnp.isfinite(grad), grad, 0.0), exact

    return eqx.filter_jit(jax.vmap(one, in_axes=(None, 0)))
