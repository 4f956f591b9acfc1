"""Worker processes that never outlive their parent (campaign cases, the service's reads).

A :class:`~concurrent.futures.ProcessPoolExecutor`'s workers wait on its pipes; killed outright
(SIGKILL, out of memory), the parent closes nothing, and the workers — and the forkserver and
resource tracker they hold open — would wait for ever. Each worker watches its parent instead.
"""

from __future__ import annotations

import os
import signal
import threading
import time

WATCH_S = 1.0  # how often a worker looks for its parent


def worker_init(parent_pid: int, nice: int = 0) -> None:
    """A pool's initializer: Ctrl-C is left to the parent (which stops the pool), the worker
    runs ``nice`` steps below the parent's CPU priority, and it ends itself once
    ``parent_pid`` is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        os.nice(nice)

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
