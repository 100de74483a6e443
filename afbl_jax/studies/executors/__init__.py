"""Where a study's batches of simulations run: this process (`LocalExecutor`, the default) or a
Dask cluster (`DaskExecutor`: a LocalCluster on this machine or a running scheduler, e.g. one
that dask-jobqueue started on SLURM or PBS). Importing this package imports no Dask."""

from ._executor import DaskExecutor as DaskExecutor
from ._executor import Executor as Executor
from ._executor import LocalExecutor as LocalExecutor
from ._executor import Session as Session
from ._executor import map_batches as map_batches
from ._task import ClusterError as ClusterError
from ._task import TaskInfo as TaskInfo
from ._task import run_task as run_task
