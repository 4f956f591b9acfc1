"""The API's reads of the run database, in worker processes of their own.

A page of 10 000 samples or a run's MCAP export is 0.1–1 s of Python. In a thread of the service
it shares the GIL with the control loop, and FastAPI encodes a returned dict on the loop
itself: with two clients reading pages of 10 000 samples, or exporting MCAP, during a run
(simulated hand, 2 cores), the grasp closed at 0.55–0.79°/s of the 3°/s commanded and the run
faulted (``python -m bench reads``, on the code before). With the reads here, in worker
processes below the service's CPU priority (``nice``), the loop keeps its 29.5 Hz and the
tactile frame's way to its joint command its 0.6 ms median (p99 4.2 ms, alone 1.3 ms): a
read takes nothing from the loop but the CPU the loop leaves.

A read is a module-level function (picklable by name) of plain arguments that returns a
:class:`Payload`, or raises :class:`~sdh2svc.service.hand_service.ServiceError`.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import sys
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any

from sdh2svc.service.hand_service import ServiceError
from sdh2svc.workers import stop_pool, worker_init

READ_WORKERS = 2  # reads at once (a long export does not hold up a page of samples)
READ_NICE = 10  # CPU priority steps below the service's


@dataclass(frozen=True, slots=True)
class Payload:
    """A read's answer: the bytes of a response (or the file the worker wrote them to, for a
    large one: ``path``), their media type and headers."""

    content: bytes
    media_type: str = "application/json"
    headers: dict[str, str] = field(default_factory=dict)
    path: str | None = None  # the answer is this file's (the service streams it, then it goes)


class ReadPool:
    """The worker processes, started at the first read (forked from a server process that has
    imported ``preload``: the reads' modules are imported once, not once per worker); a pool
    broken by a dead worker is replaced (the read that found it broken answers 503)."""

    def __init__(self, workers: int = READ_WORKERS, preload: tuple[str, ...] = ()) -> None:
        self.workers, self.preload = workers, preload
        self._pool: ProcessPoolExecutor | None = None

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            ctx: Any = multiprocessing.get_context("spawn")
            if sys.platform != "win32":
                ctx = multiprocessing.get_context("forkserver")
                ctx.set_forkserver_preload(list(self.preload))
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                             initializer=worker_init,
                                             initargs=(os.getpid(), READ_NICE, True))  # fmt: skip
        return self._pool

    async def __call__(self, fn: Callable[..., Payload], *args: Any) -> Payload:
        pool = self._executor()
        try:
            # submitted from a thread: a submit may start a worker, which waits for the
            # processes' server (at the first read, for its imports: a second or more) —
            # never on the event loop, where the control loop runs
            future = await asyncio.to_thread(pool.submit, fn, *args)
            return await asyncio.wrap_future(future)
        except BrokenProcessPool:
            if self._pool is pool:
                self._pool = None
                pool.shutdown(wait=False, cancel_futures=True)
            raise ServiceError(503, "the read's worker process died: try again") from None

    def close(self) -> None:
        """End the workers now (a read still going is abandoned); idempotent."""
        pool, self._pool = self._pool, None
        if pool is not None:
            stop_pool(pool)
