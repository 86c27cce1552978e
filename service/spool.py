"""Each server's own directory for spooled request bodies, and removal of those crashed servers left.

Bodies over ``spool_bytes`` are written to files in ``$TMPDIR/shadowcorr-spool-<pid>-<random>/``,
a directory of this server alone.  The server holds an exclusive ``flock`` on the file
``lock`` in it for as long as it runs, and the kernel releases that lock when the process
ends, however it ends (SIGKILL, the out-of-memory killer).  At start, every
``shadowcorr-spool-*`` directory whose lock can be taken belongs to no running server and
is removed with the bodies in it.

The lock, not the pid in the name (which is there for people), says whether a directory's
server still runs: pids are reused, a container's server is often pid 1 after every
restart, and servers in separate pid namespaces may share one temporary directory.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["SpoolDir", "remove_stale_spool_dirs", "SPOOL_DIR_PREFIX"]

SPOOL_DIR_PREFIX = "shadowcorr-spool-"
_LOCK_NAME = "lock"


class SpoolDir:
    """This server's spool directory, locked while it exists (see the module docstring)."""

    def __init__(self, parent: str | Path | None = None) -> None:
        parent = Path(parent if parent is not None else tempfile.gettempdir())
        # Made under a name the start-up sweep does not look at, locked, then renamed:
        # another server starting meanwhile never sees it unlocked.
        building = Path(tempfile.mkdtemp(prefix="." + SPOOL_DIR_PREFIX, dir=parent))
        self._lock_fd = os.open(building / _LOCK_NAME, os.O_CREAT | os.O_RDWR, 0o600)
        fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.path = parent / f"{SPOOL_DIR_PREFIX}{os.getpid()}-{building.name.rsplit('-', 1)[-1]}"
        os.rename(building, self.path)

    def close(self) -> None:
        """Remove the directory (with any body left in it) and release the lock; safe to call twice."""
        if self._lock_fd >= 0:
            shutil.rmtree(self.path, ignore_errors=True)
            os.close(self._lock_fd)
            self._lock_fd = -1


def remove_stale_spool_dirs(parent: str | Path | None = None) -> list[Path]:
    """Remove the spool directories in ``parent`` (default: the temporary directory) that no running server holds."""
    parent = Path(parent if parent is not None else tempfile.gettempdir())
    removed = []
    for path in parent.glob(SPOOL_DIR_PREFIX + "*"):
        if path.is_symlink() or not path.is_dir():
            continue  # not made by a server: never follow a link out of the temporary directory
        try:
            fd = os.open(path / _LOCK_NAME, os.O_RDWR)
        except OSError:  # removed meanwhile, or another user's
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # its server is running
            continue
        else:
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
        finally:
            os.close(fd)
    return removed
