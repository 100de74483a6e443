"""Gain tuning through the batched closed loop: `_cases` the realistic training and held-out
cases, `_objective` the normalised objective with limits, `_optimize` L-BFGS / Adam / CMA-ES with
a time budget and checkpoints, `_study` the outputs of `run_tuning`, `_compare` the comparison
studies (optimisers; tuned FBL+PID vs tuned AFBL) and the gradient-cost measurement."""

from ._cases import DEFAULT_THRUST_TO_WEIGHT as DEFAULT_THRUST_TO_WEIGHT
from ._cases import TUNING_UNMODELED as TUNING_UNMODELED
from ._cases import TuningCases as TuningCases
from ._cases import nominal_vehicle as nominal_vehicle
from ._cases import training_cases as training_cases
from ._cases import tuning_distribution as tuning_distribution
from ._cases import without_noise as without_noise
from ._compare import compare_controllers as compare_controllers
from ._compare import compare_optimizers as compare_optimizers
from ._compare import format_controllers as format_controllers
from ._compare import gradient_cost as gradient_cost
from ._objective import GainSpace as GainSpace
from ._objective import ObjectiveConfig as ObjectiveConfig
from ._objective import Reference as Reference
from ._objective import aggregate as aggregate
from ._objective import canonical_cases as canonical_cases
from ._objective import case_costs as case_costs
from ._objective import case_losses as case_losses
from ._objective import cases_for as cases_for
from ._objective import objective as objective
from ._objective import reference_terms as reference_terms
from ._optimize import METHODS as METHODS
from ._optimize import TuneConfig as TuneConfig
from ._optimize import Tuner as Tuner
from ._optimize import TuneResult as TuneResult
from ._optimize import abandoned_work as abandoned_work
from ._optimize import chunked_value_and_grad as chunked_value_and_grad
from ._optimize import gradient_chunks as gradient_chunks
from ._optimize import make_optimizer as make_optimizer
from ._optimize import tune as tune
from ._study import TuningReport as TuningReport
from ._study import evaluate_canonical as evaluate_canonical
from ._study import evaluate_heldout as evaluate_heldout
from ._study import run_tuning as run_tuning
