"""Differentiable gain tuning (optax through the diffrax closed loop): `_objective` holds the
objective and the adjoint, `_optimize` the loop, `_study` the outputs of `run_tuning`."""

from ._cases import DEFAULT_THRUST_TO_WEIGHT as DEFAULT_THRUST_TO_WEIGHT
from ._cases import TuningCases as TuningCases
from ._cases import nominal_vehicle as nominal_vehicle
from ._cases import training_cases as training_cases
from ._objective import GainSpace as GainSpace
from ._objective import ObjectiveConfig as ObjectiveConfig
from ._objective import aggregate as aggregate
from ._objective import canonical_cases as canonical_cases
from ._objective import case_costs as case_costs
from ._objective import cases_for as cases_for
from ._objective import objective as objective
from ._optimize import TuneConfig as TuneConfig
from ._optimize import Tuner as Tuner
from ._optimize import TuneResult as TuneResult
from ._optimize import make_optimizer as make_optimizer
from ._optimize import tune as tune
from ._study import TuningReport as TuningReport
from ._study import evaluate_canonical as evaluate_canonical
from ._study import evaluate_heldout as evaluate_heldout
from ._study import run_tuning as run_tuning
