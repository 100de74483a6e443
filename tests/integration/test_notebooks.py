"""Execute every jupytext notebook in notebooks/ and fail if any cell raises.

Each notebook's .py (percent format) source is converted with jupytext and run with nbclient on
the ``python3`` kernel. The run happens in a temporary copy of the notebooks folder (which is
also the working directory), so nothing in the repository is modified.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import jupytext
import nbclient
import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[2] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.py"))
TIMEOUT = 600  # seconds per cell


def test_notebooks_found():
    assert NOTEBOOKS, f"no jupytext notebooks found in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("source", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(source: Path, tmp_path: Path):
    workdir = tmp_path / "notebooks"
    shutil.copytree(NOTEBOOK_DIR, workdir, ignore=shutil.ignore_patterns(".ipynb_checkpoints"))
    nb = jupytext.read(workdir / source.name)
    client = nbclient.NotebookClient(
        nb,
        timeout=TIMEOUT,
        kernel_name="python3",
        resources={"metadata": {"path": str(workdir)}},
    )
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as exc:
        pytest.fail(f"{source.name}: a cell raised an error:\n{exc}", pytrace=False)
