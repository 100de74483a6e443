"""The closed loop and its solves: one case (`simulate`), many cases (`simulate_batch`: vmap or
grouped ensembles on the lean loop or diffeqsolve, float32, chunks, devices), the status
enumeration, CPU devices and the compilation cache."""

from ._batch import CPU_COMPILER_OPTIONS as CPU_COMPILER_OPTIONS
from ._batch import STRATEGIES as STRATEGIES
from ._batch import batch_compiler_options as batch_compiler_options
from ._batch import case_layout as case_layout
from ._batch import ensemble_vector_field as ensemble_vector_field
from ._batch import simulate_batch as simulate_batch
from ._cache import CACHE_ENV_VAR as CACHE_ENV_VAR
from ._cache import configure_compilation_cache as configure_compilation_cache
from ._cache import default_cache_dir as default_cache_dir
from ._closed_loop import COST_LAYOUT as COST_LAYOUT
from ._closed_loop import CaseInputs as CaseInputs
from ._closed_loop import ClosedLoop as ClosedLoop
from ._closed_loop import ClosedLoopState as ClosedLoopState
from ._closed_loop import DivergenceLimits as DivergenceLimits
from ._closed_loop import Held as Held
from ._closed_loop import Signals as Signals
from ._devices import configure_cpu_devices as configure_cpu_devices
from ._digital import sample_instant as sample_instant
from ._ensemble import INTEGRATORS as INTEGRATORS
from ._ensemble import EnsembleField as EnsembleField
from ._ensemble import ensemble_rms_norm as ensemble_rms_norm
from ._ensemble import solve_group as solve_group
from ._lean import Groups as Groups
from ._lean import LoopOutcome as LoopOutcome
from ._lean import Step as Step
from ._lean import lean_loop as lean_loop
from ._solve import SAVINGS as SAVINGS
from ._solve import SOLVERS as SOLVERS
from ._solve import SimulationResult as SimulationResult
from ._solve import closed_loop_of as closed_loop_of
from ._solve import get_solver as get_solver
from ._solve import save_times as save_times
from ._solve import simulate as simulate
from ._solve import step_size_controller as step_size_controller
from ._status import STATUS_DIVERGED as STATUS_DIVERGED
from ._status import STATUS_LABELS as STATUS_LABELS
from ._status import STATUS_MAX_STEPS as STATUS_MAX_STEPS
from ._status import STATUS_MESSAGES as STATUS_MESSAGES
from ._status import STATUS_NAMES as STATUS_NAMES
from ._status import STATUS_OK as STATUS_OK
from ._status import STATUS_SOLVER_FAILED as STATUS_SOLVER_FAILED
from ._status import Status as Status
from ._status import status_from as status_from
from ._status import status_message as status_message
