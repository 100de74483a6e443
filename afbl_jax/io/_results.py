"""Results files: parquet tables written atomically (unique temporary name, then rename), read
back as NumPy columns. pyarrow is imported on first use."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


def atomic_write_table(table, path: str | Path) -> None:
    """Write a pyarrow ``table`` to ``path`` (parquet) via a unique temporary file in the same
    folder and an atomic rename, so readers never see a partial file and concurrent writers
    never share a temporary."""
    import pyarrow.parquet as pq

    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(data: bytes, path: str | Path) -> None:
    """Write ``data`` to ``path`` via a unique temporary file and an atomic rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(text: str, path: str | Path) -> None:
    """Write ``text`` to ``path`` via a unique temporary file and an atomic rename."""
    atomic_write_bytes(text.encode(), path)


def read_table(path: str | Path):
    """A parquet file as a pyarrow table; a file that is not complete parquet (cut short,
    overwritten) raises ValueError naming it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as err:
        if isinstance(err, OSError) and err.errno is not None:
            raise  # an operating-system error (missing file, permissions), not the contents
        raise ValueError(f"{path} is not a complete parquet file ({err})") from None


def table_columns(table) -> dict[str, np.ndarray]:
    """Columns of a pyarrow table as NumPy arrays."""
    return {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}


def read_results(path: str | Path, file_name: str = "results.parquet") -> dict[str, np.ndarray]:
    """Columns of a results file (or of a folder's ``file_name``) as NumPy arrays."""
    path = Path(path)
    if path.is_dir():
        path = path / file_name
    return table_columns(read_table(path))
