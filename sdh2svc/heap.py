"""The garbage collector and the control loop.

CPython's cyclic collector stops the program while it looks at every object it tracks. A full
(oldest-generation) collection of the service's heap — the modules, FastAPI and pydantic, numpy,
the links and the telemetry — took 20–70 ms on the event loop, and came every half minute or so
once WebSocket clients read the telemetry: a tactile frame missed and its command late, next to
a real hand. :func:`settle` collects once while nothing moves, then freezes what is left
(:func:`gc.freeze`): later collections look only at what was allocated since, a few milliseconds
at most. A run calls it before it moves (``RecordedRun.execute``: the service's runs and
``sdh2svc run``). Each call first unfreezes: what was alive at one run's start and died since —
the run before, a client gone — is found by the next, never kept for good.
"""

from __future__ import annotations

import gc


def settle() -> None:
    """Collect every cycle now, and keep what survives out of later collections."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()
