"""A trimmed start: the scenario's vehicle in equilibrium with its mean wind at t0."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._typing import Scalar, Vec3
from ..model import (
    AbstractAerodynamics,
    QuadrotorParams,
    Trim,
    TrimSolution,
    make_aerodynamics,
    solve_trim,
)
from ._scenario import Scenario


@eqx.filter_jit
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
    `afbl_jax.model.envelope_margin`). Pure, jitted (one compiled program per structure of
    its arguments) and vmappable over cases.
    """
    model = vehicle if model is None else model
    aero = make_aerodynamics(aerodynamics)
    mass, wind, velocity = trim_conditions(scenario, vehicle, position_hold=position_hold)
    solution = solve_trim(
        vehicle, model, aero, wind, velocity, mass, scenario.initial_state[..., 5]
    )
    return start_at_trim(scenario, vehicle, solution, position_hold=position_hold), solution


def trim_conditions(
    scenario: Scenario, vehicle: QuadrotorParams, *, position_hold: bool = True
) -> tuple[Scalar, Vec3, Vec3]:
    """The conditions `trim_scenario` trims at: the true mass at t0 [kg], the wind's steady
    mean [m/s] and the earth-frame velocity [m/s] (0 holding position, the mean wind drifting
    with the air)."""
    mass = vehicle.m * scenario.mass_factor(scenario.t0)
    wind = scenario.wind.mean
    velocity = jnp.zeros_like(wind) if position_hold else wind
    return mass, wind, velocity


def start_at_trim(
    scenario: Scenario,
    vehicle: QuadrotorParams,
    solution: TrimSolution,
    *,
    position_hold: bool = True,
) -> Scenario:
    """``scenario`` started at ``solution``, a trim solved at its `trim_conditions` (what
    `trim_scenario` returns; for callers that solve several trims in one batched call)."""
    mass, _, velocity = trim_conditions(scenario, vehicle, position_hold=position_hold)
    ok = solution.converged
    hover = jnp.zeros(4, solution.trim.command.dtype).at[3].set(mass * vehicle.g)
    trim = Trim(
        jnp.where(ok, solution.trim.attitude, 0.0),
        jnp.where(ok, solution.trim.command, hover),
    )
    state = (
        scenario.initial_state.at[3:5].set(trim.attitude).at[6:9].set(velocity).at[9:12].set(0.0)
    )
    return eqx.tree_at(
        lambda s: (s.initial_state, s.trim),
        scenario,
        (state, trim),
        is_leaf=lambda x: x is None,
    )
