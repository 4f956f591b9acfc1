"""Fast mode: an asyncio event loop on a virtual clock.

``loop.time()`` is virtual. When the loop would sleep — no callback ready, no I/O readable —
the clock jumps straight to the next timer instead of waiting, so paced serial lines, push-mode
frame periods, servo ticks and driver timeouts all run as fast as the CPU allows, in the same
order as in real time. Everything above (emulators, endpoints, drivers, controller) runs
unmodified: they only ever use ``loop.time()``, ``asyncio.sleep`` and timeouts.

I/O still goes through the kernel. The clock may only jump when nothing is in flight, so fast
mode needs transports that deliver synchronously: Unix-domain sockets (``unix://`` URLs) do —
a write is readable by the peer before ``send`` returns. (A pty's line discipline delivers
later, from a kernel worker, so real time is the only safe clock there.) For the same reason,
work sent to an executor (``asyncio.to_thread``) runs inline, on the loop's thread.
"""

from __future__ import annotations

import asyncio
import select
import selectors
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")

_EPOLL = selectors.DefaultSelector is getattr(selectors, "EpollSelector", None)


class _JumpingSelector(selectors.DefaultSelector):  # type: ignore[misc,valid-type]
    """Polls without blocking; an idle wait becomes a jump of the virtual clock."""

    def __init__(self) -> None:
        super().__init__()
        self.loop: VirtualTimeLoop | None = None

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        events = self._poll() if _EPOLL else super().select(0)
        if events or timeout == 0 or self.loop is None:
            return events
        if timeout is None:  # no timer at all: only I/O can wake us, so wait for it for real
            return super().select(None)
        self.loop.advance(timeout)
        return events

    def _poll(self) -> list[tuple[selectors.SelectorKey, int]]:
        """``EpollSelector.select(0)`` without its Python wrapper around the system call: the
        loop polls once per iteration, tens of thousands of times a run, nearly always to find
        nothing."""
        try:
            fd_events = self._selector.poll(0, max(len(self._fd_to_key), 1))
        except InterruptedError:
            return []
        ready = []
        for fd, event in fd_events:
            key = self._fd_to_key.get(fd)
            if key:
                events = (selectors.EVENT_WRITE if event & ~select.EPOLLIN else 0) | (
                    selectors.EVENT_READ if event & ~select.EPOLLOUT else 0
                )
                ready.append((key, events & key.events))
        return ready


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    """A selector event loop whose clock is virtual and jumps over idle waits."""

    def __init__(self, start: float = 0.0) -> None:
        self._vtime = start
        selector = _JumpingSelector()
        super().__init__(selector)
        selector.loop = self

    def time(self) -> float:
        return self._vtime

    def advance(self, seconds: float) -> None:
        self._vtime += max(0.0, seconds)

    def run_in_executor(self, executor: Any, func: Any, *args: Any) -> asyncio.Future[Any]:
        """Run ``func`` right here, at once: a worker thread would finish at a wall-clock moment
        the virtual clock cannot wait for, and the run would stop being deterministic. Blocking
        the loop is harmless when no time is real."""
        fut: asyncio.Future[Any] = self.create_future()
        try:
            fut.set_result(func(*args))
        except BaseException as e:  # handed to the awaiting coroutine, as an executor would
            fut.set_exception(e)
        return fut


def run_fast(main: Coroutine[Any, Any, T]) -> T:
    """Run ``main`` to completion on a fresh :class:`VirtualTimeLoop`."""
    with asyncio.Runner(loop_factory=VirtualTimeLoop) as runner:
        return runner.run(main)
