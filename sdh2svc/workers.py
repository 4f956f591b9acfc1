"""Worker processes that never outlive their parent (campaign cases, the service's reads), and
how to stop them at once.

A :class:`~concurrent.futures.ProcessPoolExecutor`'s workers wait on its pipes; killed outright
(SIGKILL, out of memory), the parent closes nothing, and the workers — and the forkserver and
resource tracker they hold open — would wait for ever. Each worker watches its parent instead.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

WATCH_S = 1.0  # how often a worker looks for its parent


def worker_init(parent_pid: int, nice: int = 0, oom_first: bool = False) -> None:
    """A pool's initializer: Ctrl-C is left to the parent (which stops the pool), the worker
    runs ``nice`` steps below the parent's CPU priority, and it ends itself once
    ``parent_pid`` is gone. ``oom_first``: a machine out of memory ends this worker before
    anything else (an export of a run of thousands of strokes takes gigabytes: the kernel
    would otherwise pick the largest process, which may be the service driving the hand)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        os.nice(nice)
    if oom_first:
        with contextlib.suppress(OSError):  # (not Linux: the OS's own choice)
            Path("/proc/self/oom_score_adj").write_text("1000")

    def watch() -> None:
        while True:
            time.sleep(WATCH_S)
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except OSError:  # alive, and not ours to signal
                pass

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what has not started and end the workers now (what they were doing is lost)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(timeout=5)
