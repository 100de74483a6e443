"""afbl-jax: quadrotor FBL+PID and adaptive FBL in JAX, with diffrax closed-loop simulation.

Source: Eltayeb, Rahmat, Basri, "Adaptive Feedback Linearization Controller for Stabilization
of Quadrotor UAV", IJIE 12(4), 2020; deviations in docs/paper_notes.md.

Packages follow the data flow: `afbl_jax.model` (vehicle, plants, actuators, aerodynamics,
controllers and their sampling) and `afbl_jax.scenario` (references, disturbances, wind) ->
`afbl_jax.sim` (the closed loop; one case or batched) -> `afbl_jax.metrics` ->
`afbl_jax.studies` (reproduce, montecarlo, tuning, unmodeled, bench) -> `afbl_jax.io`,
`afbl_jax.plotting`, `afbl_jax.cli`. Importing this package loads nothing but its own
`__init__`: every public name below is imported from its subpackage on first use (PEP 562), so
`import afbl_jax` (and the ``afbl`` command's ``--help``) starts without JAX.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and IDEs (the study names excepted)
    from .io import gains_to_dict as gains_to_dict
    from .io import load_gains as load_gains
    from .io import save_gains as save_gains
    from .metrics import FAILURE_CAUSES as FAILURE_CAUSES
    from .metrics import METRIC_NAMES as METRIC_NAMES
    from .metrics import BatchMetrics as BatchMetrics
    from .metrics import failure_margin as failure_margin
    from .metrics import metrics_from_result as metrics_from_result
    from .metrics import peaks_over_samples as peaks_over_samples
    from .metrics import sample_peaks as sample_peaks
    from .metrics import smooth_margin as smooth_margin
    from .model import AERODYNAMIC_MODELS as AERODYNAMIC_MODELS
    from .model import AFBL as AFBL
    from .model import CHANNELS as CHANNELS
    from .model import CONTROLLERS as CONTROLLERS
    from .model import ENVELOPE_CAUSES as ENVELOPE_CAUSES
    from .model import EQ14_GYRO_SIGN as EQ14_GYRO_SIGN
    from .model import FBLPID as FBLPID
    from .model import FULL_STATE_LAYOUT as FULL_STATE_LAYOUT
    from .model import PHYSICAL_GYRO_SIGN as PHYSICAL_GYRO_SIGN
    from .model import PLANT_MODELS as PLANT_MODELS
    from .model import POSITION_LOOP_LAYOUT as POSITION_LOOP_LAYOUT
    from .model import STATE_LAYOUT as STATE_LAYOUT
    from .model import AbstractActuators as AbstractActuators
    from .model import AbstractAerodynamics as AbstractAerodynamics
    from .model import AbstractController as AbstractController
    from .model import AbstractPlant as AbstractPlant
    from .model import AbstractSampling as AbstractSampling
    from .model import AFBLPaper as AFBLPaper
    from .model import ContinuousControl as ContinuousControl
    from .model import DigitalControl as DigitalControl
    from .model import EnvelopeLimits as EnvelopeLimits
    from .model import FirstOrderRotors as FirstOrderRotors
    from .model import InstantRotors as InstantRotors
    from .model import LinearDrag as LinearDrag
    from .model import PaperPlant as PaperPlant
    from .model import PositionHold as PositionHold
    from .model import QuadrotorParams as QuadrotorParams
    from .model import ReferenceSample as ReferenceSample
    from .model import RigidBodyPlant as RigidBodyPlant
    from .model import RotorDrag as RotorDrag
    from .model import Trim as Trim
    from .model import TrimSolution as TrimSolution
    from .model import UnmodeledDynamics as UnmodeledDynamics
    from .model import actuate as actuate
    from .model import allocation_matrix as allocation_matrix
    from .model import body_rates_from_euler_rates as body_rates_from_euler_rates
    from .model import envelope_margin as envelope_margin
    from .model import euler_rates_from_body_rates as euler_rates_from_body_rates
    from .model import feedback_linearize as feedback_linearize
    from .model import full_plant_derivative as full_plant_derivative
    from .model import hover_input as hover_input
    from .model import inputs_from_rotor_speeds_sq as inputs_from_rotor_speeds_sq
    from .model import make_aerodynamics as make_aerodynamics
    from .model import make_controller as make_controller
    from .model import measure as measure
    from .model import measurement_noise as measurement_noise
    from .model import omega_d as omega_d
    from .model import plant_derivative as plant_derivative
    from .model import rotation_matrix as rotation_matrix
    from .model import rotor_speeds_sq_from_inputs as rotor_speeds_sq_from_inputs
    from .model import saturate_rotor_speeds_sq as saturate_rotor_speeds_sq
    from .model import solve_trim as solve_trim
    from .model import stack_unmodeled as stack_unmodeled
    from .model import thrust_direction as thrust_direction
    from .scenario import PROFILES as PROFILES
    from .scenario import SCENARIO_KINDS as SCENARIO_KINDS
    from .scenario import PositionReference as PositionReference
    from .scenario import PulseDisturbance as PulseDisturbance
    from .scenario import Reference as Reference
    from .scenario import Scenario as Scenario
    from .scenario import Wind as Wind
    from .scenario import make_position_reference as make_position_reference
    from .scenario import make_reference as make_reference
    from .scenario import min_jerk_blend as min_jerk_blend
    from .scenario import no_disturbance as no_disturbance
    from .scenario import no_wind as no_wind
    from .scenario import paper_disturbance as paper_disturbance
    from .scenario import paper_reference as paper_reference
    from .scenario import paper_scenario as paper_scenario
    from .scenario import stack_scenarios as stack_scenarios
    from .scenario import trim_scenario as trim_scenario
    from .sim import COST_LAYOUT as COST_LAYOUT
    from .sim import SAVINGS as SAVINGS
    from .sim import SOLVERS as SOLVERS
    from .sim import STATUS_MESSAGES as STATUS_MESSAGES
    from .sim import STATUS_NAMES as STATUS_NAMES
    from .sim import STRATEGIES as STRATEGIES
    from .sim import ClosedLoop as ClosedLoop
    from .sim import ClosedLoopState as ClosedLoopState
    from .sim import DivergenceLimits as DivergenceLimits
    from .sim import SimulationResult as SimulationResult
    from .sim import Status as Status
    from .sim import configure_compilation_cache as configure_compilation_cache
    from .sim import configure_cpu_devices as configure_cpu_devices
    from .sim import ensemble_rms_norm as ensemble_rms_norm
    from .sim import ensemble_vector_field as ensemble_vector_field
    from .sim import simulate as simulate
    from .sim import simulate_batch as simulate_batch
    from .sim import status_message as status_message


_EXPORTS: dict[str, tuple[str, ...]] = {
    "afbl_jax.io": (
        "gains_to_dict",
        "load_gains",
        "save_gains",
    ),
    "afbl_jax.metrics": (
        "FAILURE_CAUSES",
        "METRIC_NAMES",
        "BatchMetrics",
        "failure_margin",
        "metrics_from_result",
        "peaks_over_samples",
        "sample_peaks",
        "smooth_margin",
    ),
    "afbl_jax.model": (
        "AERODYNAMIC_MODELS",
        "AFBL",
        "CHANNELS",
        "CONTROLLERS",
        "ENVELOPE_CAUSES",
        "EQ14_GYRO_SIGN",
        "FBLPID",
        "FULL_STATE_LAYOUT",
        "PHYSICAL_GYRO_SIGN",
        "PLANT_MODELS",
        "POSITION_LOOP_LAYOUT",
        "STATE_LAYOUT",
        "AbstractActuators",
        "AbstractAerodynamics",
        "AbstractController",
        "AbstractPlant",
        "AbstractSampling",
        "AFBLPaper",
        "ContinuousControl",
        "DigitalControl",
        "EnvelopeLimits",
        "FirstOrderRotors",
        "InstantRotors",
        "LinearDrag",
        "PaperPlant",
        "PositionHold",
        "QuadrotorParams",
        "ReferenceSample",
        "RigidBodyPlant",
        "RotorDrag",
        "Trim",
        "TrimSolution",
        "UnmodeledDynamics",
        "actuate",
        "allocation_matrix",
        "body_rates_from_euler_rates",
        "envelope_margin",
        "euler_rates_from_body_rates",
        "feedback_linearize",
        "full_plant_derivative",
        "hover_input",
        "inputs_from_rotor_speeds_sq",
        "make_aerodynamics",
        "make_controller",
        "measure",
        "measurement_noise",
        "omega_d",
        "plant_derivative",
        "rotation_matrix",
        "rotor_speeds_sq_from_inputs",
        "saturate_rotor_speeds_sq",
        "solve_trim",
        "stack_unmodeled",
        "thrust_direction",
    ),
    "afbl_jax.scenario": (
        "PROFILES",
        "SCENARIO_KINDS",
        "PositionReference",
        "PulseDisturbance",
        "Reference",
        "Scenario",
        "Wind",
        "make_position_reference",
        "make_reference",
        "min_jerk_blend",
        "no_disturbance",
        "no_wind",
        "paper_disturbance",
        "paper_reference",
        "paper_scenario",
        "stack_scenarios",
        "trim_scenario",
    ),
    "afbl_jax.sim": (
        "COST_LAYOUT",
        "SAVINGS",
        "SOLVERS",
        "STATUS_MESSAGES",
        "STATUS_NAMES",
        "STRATEGIES",
        "ClosedLoop",
        "ClosedLoopState",
        "DivergenceLimits",
        "SimulationResult",
        "Status",
        "configure_compilation_cache",
        "configure_cpu_devices",
        "ensemble_rms_norm",
        "ensemble_vector_field",
        "simulate",
        "simulate_batch",
        "status_message",
    ),
    "afbl_jax.studies.executors": ("DaskExecutor", "LocalExecutor"),
    "afbl_jax.studies.tuning": ("tune", "TuneConfig", "run_tuning"),
}
"""Subpackage -> the public names this package re-exports from it."""

_LAZY = {name: module for module, names in _EXPORTS.items() for name in names}
_SUBMODULES = ("io", "metrics", "model", "scenario", "sim")
"""Subpackages reachable as attributes (``afbl_jax.sim``) without an import statement."""

__all__ = [name for names in _EXPORTS.values() for name in names]

try:
    __version__ = importlib.metadata.version("afbl-jax")
except importlib.metadata.PackageNotFoundError:  # running from a source tree, not installed
    __version__ = "0+unknown"


def __getattr__(name: str):
    """A public name (or subpackage), imported on first use and then kept in the module."""
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"afbl_jax.{name}")
    else:
        raise AttributeError(f"module 'afbl_jax' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, *_SUBMODULES})
