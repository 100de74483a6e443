"""afbl-jax: quadrotor FBL+PID and adaptive FBL in JAX, with diffrax closed-loop simulation.

Source: Eltayeb, Rahmat, Basri, "Adaptive Feedback Linearization Controller for Stabilization
of Quadrotor UAV", IJIE 12(4), 2020; deviations in docs/paper_notes.md.
"""

from . import tuning as tuning
from ._disturbances import PulseDisturbance as PulseDisturbance
from ._disturbances import no_disturbance as no_disturbance
from ._mixer import actuate as actuate
from ._mixer import allocation_matrix as allocation_matrix
from ._mixer import inputs_from_rotor_speeds_sq as inputs_from_rotor_speeds_sq
from ._mixer import omega_d as omega_d
from ._mixer import rotor_speeds_sq_from_inputs as rotor_speeds_sq_from_inputs
from ._mixer import saturate_rotor_speeds_sq as saturate_rotor_speeds_sq
from ._params import QuadrotorParams as QuadrotorParams
from ._plant import CHANNELS as CHANNELS
from ._plant import STATE_LAYOUT as STATE_LAYOUT
from ._plant import feedback_linearize as feedback_linearize
from ._plant import hover_input as hover_input
from ._plant import plant_derivative as plant_derivative
from ._plant import thrust_direction as thrust_direction
from ._references import Reference as Reference
from ._references import ReferenceSample as ReferenceSample
from ._references import make_reference as make_reference
from ._references import min_jerk_blend as min_jerk_blend
from ._scenarios import PROFILES as PROFILES
from ._scenarios import SCENARIO_KINDS as SCENARIO_KINDS
from ._scenarios import Scenario as Scenario
from ._scenarios import paper_disturbance as paper_disturbance
from ._scenarios import paper_reference as paper_reference
from ._scenarios import paper_scenario as paper_scenario
from ._scenarios import stack_scenarios as stack_scenarios
from ._simulate import COST_LAYOUT as COST_LAYOUT
from ._simulate import SOLVERS as SOLVERS
from ._simulate import STATUS_MESSAGES as STATUS_MESSAGES
from ._simulate import STATUS_NAMES as STATUS_NAMES
from ._simulate import ClosedLoopState as ClosedLoopState
from ._simulate import DivergenceLimits as DivergenceLimits
from ._simulate import SimulationResult as SimulationResult
from ._simulate import closed_loop_vector_field as closed_loop_vector_field
from ._simulate import simulate as simulate
from ._simulate import status_message as status_message
from ._unmodeled import FULL_STATE_LAYOUT as FULL_STATE_LAYOUT
from ._unmodeled import PLANT_MODELS as PLANT_MODELS
from ._unmodeled import UnmodeledDynamics as UnmodeledDynamics
from ._unmodeled import UnmodeledState as UnmodeledState
from ._unmodeled import body_rates_from_euler_rates as body_rates_from_euler_rates
from ._unmodeled import euler_rates_from_body_rates as euler_rates_from_body_rates
from ._unmodeled import full_plant_derivative as full_plant_derivative
from ._unmodeled import measure as measure
from ._unmodeled import measurement_noise as measurement_noise
from ._unmodeled import stack_unmodeled as stack_unmodeled
from ._wind import Wind as Wind
from ._wind import no_wind as no_wind
from .controllers import AFBL as AFBL
from .controllers import CONTROLLERS as CONTROLLERS
from .controllers import FBLPID as FBLPID
from .controllers import AbstractController as AbstractController
from .controllers import AFBLPaper as AFBLPaper
from .controllers import make_controller as make_controller
from .tuning import TuneConfig as TuneConfig
from .tuning import run_tuning as run_tuning
from .tuning import tune as tune

__version__ = "0.1.0"

# batched solving (issue 5)
from ._batch import STRATEGIES as STRATEGIES
from ._batch import BatchMetrics as BatchMetrics
from ._batch import ensemble_rms_norm as ensemble_rms_norm
from ._batch import simulate_batch as simulate_batch
from ._devices import configure_cpu_devices as configure_cpu_devices
