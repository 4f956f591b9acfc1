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
import collections
import heapq
import select
import selectors
import sys
from asyncio import base_events, format_helpers
from collections.abc import Callable, Coroutine
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any, TypeVar, TypeVarTuple

T = TypeVar("T")
Ts = TypeVarTuple("Ts")

_EPOLL = selectors.DefaultSelector is getattr(selectors, "EpollSelector", None)
# BaseEventLoop._run_once's constants; VirtualTimeLoop._run_once is that method written out
# (the same on Python 3.11 to 3.13), else the stock one runs
_MIN_SCHEDULED: Any = getattr(base_events, "_MIN_SCHEDULED_TIMER_HANDLES", None)
_MIN_CANCELLED_FRACTION: Any = getattr(base_events, "_MIN_CANCELLED_TIMER_HANDLES_FRACTION", None)
_MAX_TIMEOUT: Any = getattr(base_events, "MAXIMUM_SELECT_TIMEOUT", None)
_PURGE_MIN = 16  # timers in the heap before its cancelled ones are purged (stock: 100)
_LEAN = sys.version_info < (3, 14) and None not in (
    _MIN_SCHEDULED,
    _MIN_CANCELLED_FRACTION,
    _MAX_TIMEOUT,
)


def _callback_failed(handle: asyncio.Handle, exc: BaseException) -> None:
    """What ``Handle._run`` does when its callback raises."""
    cb = format_helpers._format_callback_source(handle._callback, handle._args)  # type: ignore[attr-defined]
    context: dict[str, Any] = {
        "message": f"Exception in callback {cb}", "exception": exc, "handle": handle,
    }  # fmt: skip
    if handle._source_traceback:  # type: ignore[attr-defined]
        context["source_traceback"] = handle._source_traceback  # type: ignore[attr-defined]
    handle._loop.call_exception_handler(context)  # type: ignore[attr-defined]


class _JumpingSelector(selectors.DefaultSelector):
    """Polls without blocking; an idle wait becomes a jump of the virtual clock."""

    if TYPE_CHECKING:  # EpollSelector's private state, which _poll reads (not in typeshed)
        _selector: Any
        _fd_to_key: dict[int, selectors.SelectorKey]

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

    if TYPE_CHECKING:  # BaseEventLoop's private state, which _run_once works on (not in typeshed)
        _debug: bool
        _scheduled: list[Any]  # TimerHandles, with their private _when, _cancelled, …
        _timer_cancelled_count: int
        _ready: collections.deque[Any]
        _selector: _JumpingSelector
        _stopping: bool
        _clock_resolution: float

        def _process_events(self, event_list: list[tuple[selectors.SelectorKey, int]]) -> None:
            pass

    def __init__(self, start: float = 0.0) -> None:
        self._vtime = start
        selector = _JumpingSelector()
        super().__init__(selector)
        selector.loop = self

    def time(self) -> float:
        return self._vtime

    if _LEAN:

        def _run_once(self) -> None:
            """One iteration of the loop: ``BaseEventLoop._run_once`` (Python 3.11–3.13) step
            for step — the same cancelled-timer purge, poll timeout, clock jump, timer cut-off
            and callback order — written out for this loop (no debug mode: that takes the
            stock path). A fast-mode run makes tens of thousands of these iterations."""
            if self._debug:
                super()._run_once()  # type: ignore[misc]
                return
            scheduled = self._scheduled
            sched_count = len(scheduled)
            if (
                sched_count > _PURGE_MIN
                and self._timer_cancelled_count / sched_count > _MIN_CANCELLED_FRACTION
            ):
                scheduled = self._purge()
            while scheduled and scheduled[0]._cancelled:
                self._timer_cancelled_count -= 1
                handle = heapq.heappop(scheduled)
                handle._scheduled = False
            ready = self._ready
            selector = self._selector
            if ready or self._stopping:  # select(0), without its wrapper (most iterations)
                event_list = selector._poll() if _EPOLL else selector.select(0)
            elif scheduled:
                when = scheduled[0]._when
                event_list = selector.select(min(max(0, when - self._vtime), _MAX_TIMEOUT))
            else:
                event_list = selector.select(None)
            if event_list:
                self._process_events(event_list)
            del event_list
            end_time = self._vtime + self._clock_resolution
            while scheduled:
                handle = scheduled[0]
                if handle._when >= end_time:
                    break
                handle = heapq.heappop(scheduled)
                handle._scheduled = False
                ready.append(handle)
            popleft = ready.popleft
            for _ in range(len(ready)):
                handle = popleft()
                if handle._cancelled:
                    continue
                try:  # Handle._run, inline
                    handle._context.run(handle._callback, *handle._args)
                except (SystemExit, KeyboardInterrupt):
                    raise
                except BaseException as exc:
                    _callback_failed(handle, exc)
            handle = None

    def _purge(self) -> list[Any]:
        """The stock loop's purge of cancelled timers, from a smaller heap on: a driver's
        timeouts are mostly cancelled long before they fall due (a reply came), and every
        timer pushed or popped pays for the dead ones in Python-level comparisons."""
        live = []
        for handle in self._scheduled:
            if handle._cancelled:
                handle._scheduled = False
            else:
                live.append(handle)
        heapq.heapify(live)
        self._scheduled = live
        self._timer_cancelled_count = 0
        return live

    def advance(self, seconds: float) -> None:
        self._vtime += max(0.0, seconds)

    def run_in_executor(
        self, executor: Executor | None, func: Callable[[*Ts], T], *args: *Ts
    ) -> asyncio.Future[T]:
        """Run ``func`` right here, at once: a worker thread would finish at a wall-clock moment
        the virtual clock cannot wait for, and the run would stop being deterministic. Blocking
        the loop is harmless when no time is real."""
        fut: asyncio.Future[T] = self.create_future()
        try:
            fut.set_result(func(*args))
        except BaseException as e:  # handed to the awaiting coroutine, as an executor would
            fut.set_exception(e)
        return fut


def run_fast(main: Coroutine[Any, Any, T]) -> T:
    """Run ``main`` to completion on a fresh :class:`VirtualTimeLoop`."""
    with asyncio.Runner(loop_factory=VirtualTimeLoop) as runner:
        return runner.run(main)
