"""Files: the one gains schema, results tables (parquet, written atomically), provenance."""

from ._gains import GAINS_SCHEMA as GAINS_SCHEMA
from ._gains import controller_from_dict as controller_from_dict
from ._gains import gains_to_dict as gains_to_dict
from ._gains import load_gains as load_gains
from ._gains import save_gains as save_gains
from ._lock import FileLock as FileLock
from ._provenance import git_revision as git_revision
from ._provenance import package_versions as package_versions
from ._provenance import run_metadata as run_metadata
from ._results import atomic_write_bytes as atomic_write_bytes
from ._results import atomic_write_table as atomic_write_table
from ._results import atomic_write_text as atomic_write_text
from ._results import read_results as read_results
from ._results import read_table as read_table
from ._results import table_columns as table_columns
