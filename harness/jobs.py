"""Set-up of a spawned worker process (a run's model job or a training worker): its threads, an end
once the process that started it is gone, and Ctrl-C handling. ``harness.run`` and ``harness.train``
both start such processes; neither imports the other for it."""
from __future__ import annotations

import os
import signal
import threading
import time

_INTERRUPTED = False  # set in a job process by its first SIGINT


def interrupted() -> bool:
    """Whether this process has had a SIGINT since :func:`job_init` (a job then takes no further work)."""
    return _INTERRUPTED


def _on_interrupt(signum, frame) -> None:
    """A job process's SIGINT: the first raises KeyboardInterrupt in the job and marks the
    process as interrupted; a second one (the run forwards Ctrl-C) lets the job's clean-up run."""
    global _INTERRUPTED
    if not _INTERRUPTED:
        _INTERRUPTED = True
        raise KeyboardInterrupt


def job_init(threads: int, parent: int | None = None) -> None:
    """Set up a spawned job or training-worker process: ``threads`` threads, freed memory kept,
    an end once ``parent`` (the pid that started it; default: its parent now) is gone, and
    :func:`_on_interrupt` for SIGINT."""
    signal.signal(signal.SIGINT, _on_interrupt)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parent = os.getppid() if parent is None else parent
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    from harness.malloc import keep_freed_memory
    keep_freed_memory()
    import torch
    torch.set_num_threads(threads)


def _exit_with_parent(parent: int, poll_s: float = 0.5) -> None:
    """End this job process once the run's process is gone: a run killed by a signal (``kill``,
    ``timeout``) would otherwise leave its jobs training on for many minutes. What they wrote
    stays (atomic writes), and the next run resumes from it."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(1)
