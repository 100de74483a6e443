"""Advisory file locks, so that several processes can share one results folder.

`FileLock` holds an exclusive ``fcntl.flock`` lock on a lock file. The lock belongs to the open
file, so it is released when the holder closes it, exits or is killed (a lock never outlives its
process). Linux emulates flock on NFS with POSIX record locks, so the lock also holds between
hosts of a shared network folder. Where ``fcntl`` does not exist (Windows) locking is a no-op;
files are still written atomically (`atomic_write_table`).
"""

from __future__ import annotations

import os
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None


class FileLock:
    """An exclusive lock on the file ``path`` (created if missing, never deleted here).

    ``acquire(blocking=False)`` returns False at once when another process holds the lock;
    ``acquire()`` waits for it. Use as a context manager to wait, hold and release.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, blocking: bool = True) -> bool:
        if self._fd is not None:
            raise RuntimeError(f"lock {self.path} is already held by this object.")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
            except BlockingIOError:
                os.close(fd)
                return False
            except BaseException:
                os.close(fd)
                raise
        self._fd = fd
        return True

    def release(self, unlink: bool = False) -> None:
        """Release the lock. ``unlink``: first remove the lock file if it is still the one this
        lock holds (safe only once the guarded work is done and visible, e.g. its output file
        exists, and when every process checks for that output after acquiring)."""
        if self._fd is None:
            return
        try:
            if unlink:
                try:
                    if os.stat(self.path).st_ino == os.fstat(self._fd).st_ino:
                        self.path.unlink()
                except FileNotFoundError:
                    pass
        finally:
            os.close(self._fd)  # closing the file releases the flock
            self._fd = None

    def __enter__(self) -> FileLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
