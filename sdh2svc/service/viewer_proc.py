"""The viser 3-D view in a child process of its own (``service.viewer_process``).

Why: viser's server thread packs and sends every scene update while holding the interpreter
lock, and in the service's process that lock is the control loop's: the in-process view made
the sense→command p99 5…11 % worse. Here the control process keeps only the latest telemetry
message of each type (:meth:`ViewerProcess.handle`, as cheap as :meth:`Viewer.handle`) and
pickles the changed ones to the child a few times a second, and only while a browser watches.
The child runs the real :class:`~sdh2svc.service.viewer.Viewer` on an event loop of its own.

The link is a socketpair of length-prefixed pickles, as asyncio streams on each side's event
loop (no threads, never a blocking write). On it:

* parent → child: ``("telemetry", [msg, …])`` the changed latest messages in arrival order,
  typed (:mod:`sdh2svc.service.telemetry`): a sample with what the view draws of it (its
  contacts and their pad normals, the reconstructed outline, made here once), a tactile frame's
  matrices as arrays (pickled as bytes and shape);
  ``("result", id, error | None)`` a GUI command's outcome; ``("stop",)``.
* child → parent: ``("ready", url)`` or ``("error", text)`` once at start-up;
  ``("watched", bool)`` as browsers come and go; ``("command", id, kind, args)`` from the GUI
  panel, run through ``on_command`` on the parent's loop (read-only: the e-stop only, whatever
  the child says); ``("log", fields)``, so the child's log records go through the service's
  own handlers (JSON or text); ``("bye", reason)`` before it exits on SIGTERM (e.g. sent to
  the whole process group: not a death to warn of).

While the child is slow to read, telemetry waits in the parent as latest-per-type (stale
frames are merged, never queued). The view is not safety-critical: a child that dies is logged
once and forgotten, and the child exits when the parent does (EOF on the socket).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import struct
import sys
import traceback
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from typing import Any

from sdh2svc.config import Settings
from sdh2svc.service.pacing import paced
from sdh2svc.service.replay_feed import ReplayFeed
from sdh2svc.service.telemetry import AnyMessage, SampleMsg, kind_of

log = logging.getLogger(__name__)

# The panel's authority, as the child's Viewer applies it (viewer.py imports viser: not here).
ALWAYS_ALLOWED = frozenset({"estop"})
NEEDS_TOKEN = "needs the API token: use the dashboard"

Command = Callable[[str, dict[str, Any]], Awaitable[None]]

# The message types the view draws (Viewer's _PAYLOAD); ``hello`` is a status.
KINDS = {"sample": "sample", "pose": "pose", "tactile": "tactile", "sim": "sim",
         "status": "status", "hello": "status"}  # fmt: skip
START_TIMEOUT_S = 30.0  # the child imports viser and numpy first: seconds on a cold cache
STOP_TIMEOUT_S = 5.0  # then SIGTERM, then SIGKILL
COMMAND_TIMEOUT_S = 30.0  # a GUI command the parent never answers shows as refused
_HEADER = struct.Struct("<I")


class ViewerError(RuntimeError):
    """The 3-D view's process could not start (the message says why and what to do)."""


class CommandRefused(Exception):
    """The parent's ``on_command`` refused a GUI command (child side; str = the reason)."""


# --- the link ----------------------------------------------------------------------------------


class Channel:
    """Length-prefixed pickles over a socket, as asyncio streams on the running loop.

    :meth:`send` never blocks: what the socket does not take at once waits in the transport's
    buffer; :attr:`busy` says whether some does. Open one with :meth:`open`."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        on_message: Callable[[Any], None],
        on_close: Callable[[], None],
    ) -> None:
        self._reader, self._writer = reader, writer
        self._on_message, self._on_close = on_message, on_close
        self.closed = False
        self._task = asyncio.create_task(self._read_loop(), name="viewer-link")

    @classmethod
    async def open(
        cls, sock: socket.socket, on_message: Callable[[Any], None], on_close: Callable[[], None]
    ) -> Channel:
        reader, writer = await asyncio.open_connection(sock=sock)
        return cls(reader, writer, on_message, on_close)

    @property
    def busy(self) -> bool:
        return not self.closed and self._writer.transport.get_write_buffer_size() > 0

    async def drained(self) -> None:
        """Wait until the transport's buffer is below its high-water mark (or closed)."""
        with contextlib.suppress(ConnectionError):
            await self._writer.drain()

    def send(self, obj: Any) -> None:
        if self.closed:
            return
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        self._writer.write(_HEADER.pack(len(data)) + data)

    async def _read_loop(self) -> None:
        try:
            while True:
                (n,) = _HEADER.unpack(await self._reader.readexactly(_HEADER.size))
                obj = pickle.loads(await self._reader.readexactly(n))
                try:
                    self._on_message(obj)
                except Exception:
                    log.exception("3-D view link: handling %r failed", obj[:1])
        except (asyncio.IncompleteReadError, ConnectionError):  # the other side closed or died
            pass
        self.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if asyncio.current_task() is not self._task:
            self._task.cancel()
        self._writer.close()
        self._on_close()


# --- the parent's side -------------------------------------------------------------------------


class ViewerProcess:
    """The :class:`~sdh2svc.service.viewer.Viewer`'s surface, the view in a child process."""

    def __init__(
        self,
        settings: Settings,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        on_command: Command | None = None,
        read_only: bool = False,
        max_hz: float = 30.0,
    ) -> None:
        self.settings = settings
        self._host, self._port = host, port
        self._on_command = on_command
        self._read_only = read_only
        self._max_hz = max_hz
        self._period = 1.0 / max_hz
        self._latest: dict[str, AnyMessage] = {}  # kind → latest message, arrival order
        self._changed: set[str] = set()
        self._wake = asyncio.Event()
        self._watched = False
        self._url: str | None = None
        self._proc: BaseProcess | None = None
        self._chan: Channel | None = None
        self._ready: asyncio.Future[str] | None = None
        self._task: asyncio.Task[None] | None = None
        self._commands: set[asyncio.Task[None]] = set()
        self._started = self._stopping = False
        self._bye = ""  # why the child is exiting, when it told us
        self.forwarded = 0  # messages pickled to the child (tests, diagnostics)
        self.replay = ReplayFeed(self._keep)  # a recorded iteration instead of the live state

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Spawn the child (never fork: the service has threads) and wait for its URL."""
        loop = asyncio.get_running_loop()
        ours, theirs = socket.socketpair()
        ctx = multiprocessing.get_context("spawn")
        level = logging.getLogger().getEffectiveLevel()
        spec = ChildSpec(self.settings.model_dump(), self._host, self._port, self._read_only,
                         self._max_hz, level)  # fmt: skip
        self._proc = ctx.Process(target=child_main, args=(theirs, spec), name="sdh2svc-viewer",
                                 daemon=True)  # fmt: skip
        self._ready = loop.create_future()
        try:
            self._proc.start()
        except BaseException:
            ours.close()
            self._proc = None
            raise
        finally:
            theirs.close()  # the child has its copy: its death is our EOF
        self._chan = await Channel.open(ours, self._on_message, self._on_close)
        try:
            async with asyncio.timeout(START_TIMEOUT_S):
                self._url = await self._ready
        except TimeoutError:
            await self.stop()
            raise ViewerError(f"the 3-D view's process did not start within "
                              f"{START_TIMEOUT_S:.0f} s") from None  # fmt: skip
        except BaseException:
            await self.stop()
            raise
        if self._chan.closed:  # died right after saying ready
            await self.stop()
            raise ViewerError("the 3-D view's process exited right after it started")
        self._started = True
        self._task = asyncio.create_task(self._forward_loop(), name="viewer-forward")
        log.debug("3-D view process %d ready at %s", self._proc.pid, self._url)

    @property
    def url(self) -> str | None:
        """Where the view is served; None once its process is gone."""
        return self._url

    @property
    def watched(self) -> bool:
        return self._watched

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    async def stop(self) -> None:
        """Ask the child to stop, then SIGTERM, then SIGKILL; idempotent, fine if it died."""
        self._stopping = True
        self._url, self._watched = None, False
        tasks = [self._task, *self._commands] if self._task else list(self._commands)
        self._task = None
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if self._chan is not None:
            self._chan.send(("stop",))
        for escalate in (None, proc.terminate, proc.kill):
            if escalate is not None:
                log.warning("3-D view process %d did not stop: %s", proc.pid, escalate.__name__)
                escalate()
            if await _exited(proc, STOP_TIMEOUT_S):
                break
        if self._chan is not None:
            self._chan.close()
        proc.join(0)
        with contextlib.suppress(ValueError):
            proc.close()

    # -- telemetry in: cheap ----------------------------------------------------------------

    def handle(self, msg: AnyMessage) -> None:
        """Keep the latest message of each type, in arrival order; no pickling here (while a
        replay is shown, through :attr:`replay`: the child draws what it is given)."""
        self.replay.live(msg)

    def _keep(self, msg: AnyMessage) -> None:
        kind = KINDS.get(kind_of(msg))
        if kind is None:
            return
        latest = self._latest
        latest.pop(kind, None)  # re-inserted last: the order of arrival (pose vs sample)
        latest[kind] = msg
        self._changed.add(kind)
        self._wake.set()

    async def _forward_loop(self) -> None:
        """Forward on delivery, at most ``max_hz``, only while watched (see :func:`paced`)."""
        await paced(self._wake, self._period, self._forward_now)

    async def _forward_now(self) -> bool:
        chan = self._chan
        if chan is None or chan.closed or not self._watched or not self._changed:
            return False
        if chan.busy:  # the child is behind: what arrives meanwhile replaces the stale
            await chan.drained()
        self._forward(chan)
        return True

    def _forward(self, chan: Channel) -> None:
        changed, self._changed = self._changed, set()
        geom = self.settings.hand
        batch = [
            m.with_view(geom) if isinstance(m, SampleMsg) else m
            for k, m in self._latest.items()
            if k in changed
        ]
        if batch and self._watched:
            chan.send(("telemetry", batch))
            self.forwarded += len(batch)

    # -- the child's messages ----------------------------------------------------------------

    def _on_message(self, msg: tuple[Any, ...]) -> None:
        kind = msg[0]
        if kind == "watched":
            self._watched = bool(msg[1])
            if self._watched:  # a new browser: everything, at once
                self._changed = set(self._latest)
                self._wake.set()
        elif kind == "command":
            task = asyncio.create_task(self._command(*msg[1:]), name="viewer-command")
            self._commands.add(task)
            task.add_done_callback(self._commands.discard)
        elif kind == "bye":
            self._bye = str(msg[1])
        elif kind == "log":  # the child's record, through our handlers
            record = logging.makeLogRecord(msg[1])
            logger = logging.getLogger(record.name)
            if logger.isEnabledFor(record.levelno):
                logger.handle(record)
        elif kind in ("ready", "error") and self._ready is not None and not self._ready.done():
            if kind == "ready":
                self._ready.set_result(msg[1])
            else:
                self._ready.set_exception(ViewerError(msg[1]))

    async def _command(self, ident: int, kind: str, args: dict[str, Any]) -> None:
        """A GUI command on the parent's loop; the outcome goes back for the panel's note.

        The child faces the network and its panel refuses what it may not do; read-only, the
        parent does not take its word for it either: only the e-stop is run."""
        error: str | None = None
        try:
            if self._read_only and kind not in ALWAYS_ALLOWED:
                log.warning("3-D view: %s refused: %s (read-only view)", kind, NEEDS_TOKEN)
                error = NEEDS_TOKEN
            elif self._on_command is not None:
                await self._on_command(kind, args)
        except Exception as e:
            error = str(e) or type(e).__name__
        if self._chan is not None:
            self._chan.send(("result", ident, error))

    def _on_close(self) -> None:
        """EOF: the child exited. Expected when stopping; otherwise say so once, carry on."""
        self._watched = False
        self._url = None
        if self._ready is not None and not self._ready.done():
            why = "the 3-D view's process exited before it was ready; see the log above"
            self._ready.set_exception(ViewerError(why))
        elif self._started and not self._stopping:
            pid = self._proc.pid if self._proc is not None else None
            if self._bye:  # asked to by a signal (e.g. SIGTERM to the whole process group)
                log.info("3-D view process %s stopped on %s: the service carries on without it",
                         pid, self._bye)  # fmt: skip
                return
            log.warning("3-D view process %s died: the view is gone, the service carries on "
                        "(restart the service to get it back)", pid)  # fmt: skip


async def _exited(proc: BaseProcess, timeout: float) -> bool:
    """Wait (on the loop, no thread) until ``proc`` has exited; False after ``timeout``."""
    if proc.exitcode is not None:
        return True
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()
    fd = proc.sentinel

    def exited() -> None:
        if not done.done():
            done.set_result(None)

    loop.add_reader(fd, exited)
    try:
        async with asyncio.timeout(timeout):
            await done
    except TimeoutError:
        return False
    finally:
        loop.remove_reader(fd)
    proc.join(0)  # reap
    return True


# --- the child's side --------------------------------------------------------------------------


@dataclass(frozen=True)
class ChildSpec:
    """What the child needs (picklable: the settings as ``model_dump()``, validated again)."""

    settings: dict[str, Any]
    host: str
    port: int
    read_only: bool
    max_hz: float
    log_level: int


def _yield_to_the_service() -> None:
    """Never take the service's core when the service wakes this process (Linux's
    SCHED_BATCH: a batch task does not preempt on wake-up; it still has its fair share, so
    its panel's e-stop answers on a busy machine). A normal process, woken by the telemetry the
    service sends it, took the core the service was on: the service's 1.4 kB send returned
    2–6 ms later, three to nine times a second, the control loop stopped meanwhile."""
    with contextlib.suppress(AttributeError, OSError):  # not Linux: as any process
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))


def child_main(sock: socket.socket, spec: ChildSpec) -> None:
    """The child's entry point (spawned): the viewer on an event loop of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the parent, which stops us
    _yield_to_the_service()
    sys.stdout = sys.stderr  # the service's stdout carries only its announcement
    os.dup2(2, 1)
    code = 0
    try:
        asyncio.run(_child(sock, spec))
    except Exception:  # our loop is gone, and the log handler with it: straight to stderr
        traceback.print_exc()
        code = 1
    logging.shutdown()
    sys.stderr.flush()
    os._exit(code)  # whatever viser's threads are doing: the parent is gone or asked us to go


# what a record carries across (its message is formatted in the child, traceback included)
_RECORD_FIELDS = ("name", "levelno", "levelname", "pathname", "filename", "module", "lineno",
                  "funcName", "created", "msecs", "process", "processName")  # fmt: skip


class _ToParent(logging.Handler):
    """The child's log records, sent to the parent's log (from any thread)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, chan: Channel, level: int) -> None:
        super().__init__(level)
        self._loop, self._chan = loop, chan
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        fields = {k: getattr(record, k) for k in _RECORD_FIELDS}
        fields["msg"], fields["args"] = self.format(record), None  # message and traceback
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody to tell
            self._loop.call_soon_threadsafe(self._chan.send, ("log", fields))


async def _child(sock: socket.socket, spec: ChildSpec) -> None:
    from sdh2svc.service.viewer import Viewer

    settings = Settings.model_validate(spec.settings)
    host, port, log_level = spec.host, spec.port, spec.log_level

    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    replies: dict[int, asyncio.Future[str | None]] = {}
    viewer: Viewer | None = None

    def on_message(msg: tuple[Any, ...]) -> None:
        if msg[0] == "telemetry" and viewer is not None:
            for m in msg[1]:
                viewer.handle(m)
        elif msg[0] == "result" and (fut := replies.pop(msg[1], None)) and not fut.done():
            fut.set_result(msg[2])
        elif msg[0] == "stop":
            done.set()

    chan = await Channel.open(sock, on_message, done.set)

    def terminated() -> None:  # not a death: say so, so the parent does not warn
        chan.send(("bye", "SIGTERM"))
        done.set()

    loop.add_signal_handler(signal.SIGTERM, terminated)
    root = logging.getLogger()
    root.handlers[:] = [_ToParent(loop, chan, log_level)]
    root.setLevel(log_level)
    ids = itertools.count()

    async def on_command(kind: str, args: dict[str, Any]) -> None:
        ident = next(ids)
        replies[ident] = fut = loop.create_future()
        chan.send(("command", ident, kind, args))
        try:
            async with asyncio.timeout(COMMAND_TIMEOUT_S):
                error = await fut
        finally:
            replies.pop(ident, None)
        if error is not None:
            raise CommandRefused(error)

    viewer = Viewer(settings, host=host, port=port, on_command=on_command,
                    read_only=spec.read_only, max_hz=spec.max_hz)  # fmt: skip
    try:
        _check_port(host, port)
        await viewer.start()
        _check_moved(viewer, host, port)
    except Exception as e:
        with contextlib.suppress(Exception):
            await viewer.stop()
        text = str(e) if isinstance(e, ViewerError) else f"the 3-D view could not start: {e!r}"
        chan.send(("error", text))
        await _drain(chan)
        return
    _report_watchers(viewer, chan, loop)
    chan.send(("ready", viewer.url))
    try:
        await done.wait()
    finally:
        with contextlib.suppress(Exception):
            async with asyncio.timeout(STOP_TIMEOUT_S - 1.0):
                await viewer.stop()
        chan.close()


def _report_watchers(viewer: Any, chan: Channel, loop: asyncio.AbstractEventLoop) -> None:
    """Tell the parent when the view gains its first browser or loses its last (viser calls
    these on its own threads; the answer is read on our loop)."""
    state = {"watched": False}

    def report() -> None:
        now = viewer.watched
        if now != state["watched"]:
            state["watched"] = now
            chan.send(("watched", now))

    def cb(_client: Any) -> None:
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(report)

    viewer.server.on_client_connect(cb)
    viewer.server.on_client_disconnect(cb)


def _unavailable(host: str, port: int, why: str) -> ViewerError:
    return ViewerError(f"cannot serve the 3-D view on {host}:{port}: {why}. Stop whatever uses "
                       "it, or set service.viser_port (0 = any free port)")  # fmt: skip


def bind_error(host: str, port: int) -> OSError | None:
    """Why ``host:port`` cannot be listened on now (None: it can; port 0 always can)."""
    if port == 0:
        return None
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.create_server((host, port), family=family):
            return None
    except OSError as e:
        return e


def _check_port(host: str, port: int) -> None:
    """Fail with the system's reason rather than let viser move to the next free port."""
    if (e := bind_error(host, port)) is not None:
        raise _unavailable(host, port, e.strerror or str(e))


def _check_moved(viewer: Any, host: str, port: int) -> None:
    """The port was taken between the check and viser's bind: viser moved on; refuse too."""
    actual = viewer.server.get_port()
    if port != 0 and actual != port:
        raise _unavailable(host, port, f"in use (viser moved to {actual})")


async def _drain(chan: Channel) -> None:
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(2.0):
            await chan.drained()
