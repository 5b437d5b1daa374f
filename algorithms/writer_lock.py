"""One writer at a time: an advisory lock on a run folder or a results file.

Two ``train`` processes writing one run folder, or two ``benchmark`` processes one results file, would
interleave checkpoints, metrics and cells. :func:`writer_lock` takes an exclusive ``fcntl`` lock on a lock
file (``<folder>/.lock`` or ``<results>.lock``) for as long as the writer runs; a second writer gets
:class:`Busy` at once, naming the holder (its pid and command line), and writes nothing. The lock goes with
the process that holds it (also when it is killed), so a stale lock file is never in the way.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from pathlib import Path


class Busy(RuntimeError):
    """Another process holds the lock (the message names it)."""


@contextlib.contextmanager
def writer_lock(lock_file, what: str):
    """Hold the exclusive lock on ``lock_file`` (created if missing) while the block runs; ``what`` names
    what it guards in the :class:`Busy` error."""
    path = Path(lock_file)
    handle = open(path, "a+")
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            raise Busy(f"{what} is being written by {holder}; wait for it to finish, or write elsewhere") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} ({' '.join(sys.argv) or sys.executable})")
        handle.flush()
        yield
    finally:
        handle.close()          # closing the file releases the lock


__all__ = ["writer_lock", "Busy"]
