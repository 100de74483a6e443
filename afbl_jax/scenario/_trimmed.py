"""A trimmed start: the scenario's vehicle in equilibrium with its mean wind at t0."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..model import (
    AbstractAerodynamics,
    QuadrotorParams,
    Trim,
    TrimSolution,
    make_aerodynamics,
    solve_trim,
)
from ._scenario import Scenario


def trim_scenario(
    scenario: Scenario,
    vehicle: QuadrotorParams,
    model: QuadrotorParams | None = None,
    aerodynamics: AbstractAerodynamics | str | None = None,
    *,
    position_hold: bool = True,
) -> tuple[Scenario, TrimSolution]:
    """``scenario`` started in equilibrium with its mean wind, and the trim solution.

    The trim (`afbl_jax.model.solve_trim`) is taken at the true mass at t0, the yaw of the
    initial state and the wind's steady mean (gusts and turbulence are what the controller
    then rejects): with ``position_hold`` the vehicle holds its position (velocity 0, tilted
    into the wind), without it the vehicle moves with the air (velocity = the mean wind, no
    airspeed). The returned scenario's initial state has the trim attitude, that velocity and
    zero body rates (position, altitude and yaw as given), and its ``trim`` sets the
    controllers' initial states. Where no trim exists (``converged`` False) the start is level
    with the hover thrust m g commanded (the case is outside the flight envelope:
    `afbl_jax.model.envelope_margin`). Pure and jittable (vmap over cases).
    """
    model = vehicle if model is None else model
    aero = make_aerodynamics(aerodynamics)
    mass = vehicle.m * scenario.mass_factor(scenario.t0)
    wind = scenario.wind.mean
    velocity = jnp.zeros_like(wind) if position_hold else wind
    solution = solve_trim(
        vehicle, model, aero, wind, velocity, mass, scenario.initial_state[..., 5]
    )
    ok = solution.converged
    hover = jnp.zeros(4, solution.trim.command.dtype).at[3].set(mass * vehicle.g)
    trim = Trim(
        jnp.where(ok, solution.trim.attitude, 0.0),
        jnp.where(ok, solution.trim.command, hover),
    )
    state = (
        scenario.initial_state.at[3:5].set(trim.attitude).at[6:9].set(velocity).at[9:12].set(0.0)
    )
    trimmed = eqx.tree_at(
        lambda s: (s.initial_state, s.trim),
        scenario,
        (state, trim),
        is_leaf=lambda x: x is None,
    )
    return trimmed, solution
