"""Monte-Carlo robustness engine: case distribution, sampler, chunked runner, reports."""

from ._distribution import DEFAULT_DISTRIBUTION as DEFAULT_DISTRIBUTION
from ._distribution import Distribution as Distribution
from ._distribution import default_distribution as default_distribution
from ._distribution import load_distribution as load_distribution
from ._report import format_summary as format_summary
from ._report import summarize as summarize
from ._report import wilson_interval as wilson_interval
from ._report import write_report as write_report
from ._runner import METRIC_NAMES as METRIC_NAMES
from ._runner import STRATEGIES as STRATEGIES
from ._runner import SolverSettings as SolverSettings
from ._runner import case_metrics as case_metrics
from ._runner import read_results as read_results
from ._runner import register_strategy as register_strategy
from ._runner import run_chunk as run_chunk
from ._runner import run_montecarlo as run_montecarlo
from ._runner import shard_chunk as shard_chunk
from ._runner import table_columns as table_columns
from ._sampler import INPUT_COLUMNS as INPUT_COLUMNS
from ._sampler import UNMODELED_COLUMNS as UNMODELED_COLUMNS
from ._sampler import CaseBatch as CaseBatch
from ._sampler import sample_cases as sample_cases
from ._study import run_study as run_study
