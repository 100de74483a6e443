"""Rare failures: worst-case search (falsification), rare-event failure probabilities and
global sensitivities of the failure margin over a Monte-Carlo distribution's standard
variates."""

from .._stats import wilson_interval as wilson_interval
from ._estimators import Estimate as Estimate
from ._estimators import MixtureProposal as MixtureProposal
from ._estimators import cross_entropy as cross_entropy
from ._estimators import cross_entropy_mixture as cross_entropy_mixture
from ._estimators import crude as crude
from ._estimators import fit_mixture as fit_mixture
from ._estimators import importance_sampling as importance_sampling
from ._estimators import normal_tail as normal_tail
from ._estimators import select_coordinates as select_coordinates
from ._estimators import to_normal as to_normal
from ._estimators import to_unit as to_unit
from ._falsify import DesignPoint as DesignPoint
from ._falsify import SearchResult as SearchResult
from ._falsify import cmaes_search as cmaes_search
from ._falsify import design_point_search as design_point_search
from ._falsify import gradient_ascent as gradient_ascent
from ._falsify import most_likely_failure as most_likely_failure
from ._problem import MarginProblem as MarginProblem
from ._sensitivity import dgsm as dgsm
from ._sensitivity import sobol_indices as sobol_indices
from ._sensitivity import sobol_indices_outputs as sobol_indices_outputs
from ._study import ESTIMATORS as ESTIMATORS
from ._study import FalsifyConfig as FalsifyConfig
from ._study import RareEventConfig as RareEventConfig
from ._study import run_falsify as run_falsify
from ._study import run_rare_event as run_rare_event
from ._subset import subset_simulation as subset_simulation
