"""Detect a training call that stopped making progress, and say so (or restart).

jaxlib 0.10.2's CPU runtime can hang forever when vmapped network inits take batched QR decompositions
(:func:`marbler_jax_rl.networks.orthogonal` avoids them). Should another such hang appear, a run should not
idle for hours: a running XLA program keeps the CPU busy, so a call during
which the process has used almost no CPU time for ``idle_seconds`` is hung. :class:`HangGuard`
watches one call from a daemon thread and runs ``on_hang(idle_seconds)`` once when that happens;
the CLI then restarts itself with ``--resume`` (:func:`resume_argv`), which continues bit-exactly
from the last checkpoint.
"""
from __future__ import annotations

import os
import threading
import time
from typing import Callable


def cpu_seconds() -> float:
    """User + system CPU time of this process, all threads [s]."""
    t = os.times()
    return t.user + t.system


class HangGuard:
    """Context manager: call ``on_hang(idle_s)`` if the process stays idle while the block runs.

    Idle means less than ``min_busy`` CPU-seconds used in the last ``idle_seconds`` of wall time
    (polled every ``poll_seconds``). ``on_hang`` runs on the watcher thread, at most once per block.
    """

    def __init__(self, on_hang: Callable[[float], None], idle_seconds: float = 120.0,
                 poll_seconds: float = 5.0, min_busy: float = 0.5):
        if not idle_seconds > 0 or not poll_seconds > 0:
            raise ValueError(f"idle_seconds and poll_seconds must be > 0, got {idle_seconds}, {poll_seconds}")
        self.on_hang, self.idle_seconds = on_hang, idle_seconds
        self.poll_seconds, self.min_busy = min(poll_seconds, idle_seconds), min_busy
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.fired = False

    def _watch(self) -> None:
        samples = [(time.monotonic(), cpu_seconds())]
        while not self._stop.wait(self.poll_seconds):
            now, cpu = time.monotonic(), cpu_seconds()
            samples.append((now, cpu))
            while len(samples) > 1 and now - samples[1][0] >= self.idle_seconds:
                samples.pop(0)   # keep the oldest sample at least idle_seconds back
            start, start_cpu = samples[0]
            if now - start >= self.idle_seconds and cpu - start_cpu < self.min_busy:
                self.fired = True
                self.on_hang(now - start)
                return

    def __enter__(self) -> "HangGuard":
        self._stop.clear()
        self._thread = threading.Thread(target=self._watch, name="marbler-jax-hang-guard", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def hang_message(idle: float) -> str:
    """What a hung training chunk reports (the CLI and the API's warning add what they do next)."""
    return f"no CPU used for {idle:.0f} s inside a training chunk (an XLA CPU hang, see BENCHMARKS.md)"


def resume_argv(argv: list[str]) -> list[str]:
    """``argv`` of a ``train`` command with ``--resume`` added (once)."""
    return list(argv) if "--resume" in argv else list(argv) + ["--resume"]


__all__ = ["HangGuard", "cpu_seconds", "hang_message", "resume_argv"]
