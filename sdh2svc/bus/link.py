"""Open any pyserial URL or device path as a pair of asyncio streams.

Shared by the bus drivers (joint controller, tactile controller). pyserial-asyncio's
``open_serial_connection`` opens the port on the event loop thread, which blocks the loop for as
long as a ``socket://`` connect takes; here the blocking ``serial_for_url`` runs in a worker
thread and only the transport is built on the loop. pyserial's ``socket://`` close() is patched
(see :func:`_tune_socket`).

``unix:///path`` (the simulated hand in fast mode) is opened with asyncio's own Unix-socket
transport: the same bytes on the same socket, without pyserial's ``select()`` before every read
and write (two system calls per piece received, on a clock that never waits).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import os
import socket
import termios
import urllib.parse
from collections.abc import Callable, Iterable
from typing import Any, SupportsIndex

import serial
import serial_asyncio

from sdh2svc.protocol.line import BAUD

__all__ = [
    "URL_SCHEMES",
    "PushReader",
    "check_url",
    "close_streams",
    "is_socket_url",
    "open_streams",
]

CLOSE_WAIT_S = 2.0  # a port's transport that has not closed by then is aborted


class PushReader(asyncio.StreamReader):
    """A stream reader that can hand every piece received straight to a consumer instead
    (:meth:`push_to`), from the transport's callback: a task awaiting :meth:`read` would see it
    one event-loop round later, for nothing but a hop."""

    _buffer: bytearray  # StreamReader's own (not in typeshed)
    _maybe_resume_transport: Callable[[], None]
    _on_data: Callable[[bytes], None] | None = None
    _on_end: Callable[[BaseException | None], None] | None = None

    def push_to(
        self, on_data: Callable[[bytes], None], on_end: Callable[[BaseException | None], None]
    ) -> None:
        """From now on, ``on_data(piece)`` for every piece and ``on_end(exc)`` once at the end
        (``exc`` None: end of stream). Whatever is buffered already goes first."""
        self._on_data, self._on_end = on_data, on_end
        if self._buffer:
            data = bytes(self._buffer)
            self._buffer.clear()
            self._maybe_resume_transport()
            on_data(data)
        if (exc := self.exception()) is not None or self.at_eof():
            self._end(exc)

    def feed_data(self, data: Iterable[SupportsIndex]) -> None:
        if self._on_data is None:
            super().feed_data(data)
        elif data:
            self._on_data(bytes(data))

    def feed_eof(self) -> None:
        super().feed_eof()
        self._end(None)

    def set_exception(self, exc: Exception) -> None:
        super().set_exception(exc)
        self._end(exc)

    def _end(self, exc: BaseException | None) -> None:
        on_end, self._on_data, self._on_end = self._on_end, None, None
        if on_end is not None:
            on_end(exc)


# the pyserial URLs a line can be (the others have no file descriptor for the event loop to
# watch, or are no line to a device): socket://, and hwgrep:// and spy:// in front of a device
URL_SCHEMES = ("socket", "unix", "hwgrep", "spy")


def check_url(url: str) -> None:
    """ValueError, naming ``url``, if it cannot be a line: a scheme :func:`open_streams` cannot
    use, or none of pyserial's (a typo a patient service would retry for ever)."""
    scheme = url.strip().partition("://")[0].lower() if "://" in url else ""
    if scheme and scheme not in URL_SCHEMES:
        allowed = ", ".join(f"{s}://" for s in URL_SCHEMES)
        raise ValueError(f"{url}: a line is a device path or one of {allowed}")


def is_socket_url(url: str) -> bool:
    """Whether ``url`` is pyserial's raw TCP transport (``socket://host:port``)."""
    return url.strip().lower().startswith("socket://")


async def open_streams(
    url: str, *, baudrate: int = BAUD, limit: int = 2**16, **serial_kwargs: Any
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Open ``url`` (device path or pyserial URL) raw 8N1, no flow control.

    Raises ``serial.SerialException`` (or ``OSError``) when the port cannot be opened. A lost
    port later shows as an exception (or EOF) from the reader.
    """
    if url.strip().lower().startswith("unix://"):
        return await _open_unix(url, limit)
    loop = asyncio.get_running_loop()
    if "://" not in url:  # a device: ours alone (flock), as a port in use must be refused
        serial_kwargs.setdefault("exclusive", True)
    opening = asyncio.ensure_future(asyncio.to_thread(
        serial.serial_for_url, url, baudrate=baudrate, rtscts=False, xonxoff=False,
        **serial_kwargs,
    ))  # fmt: skip
    try:
        port = await asyncio.shield(opening)
    except asyncio.CancelledError:
        opening.add_done_callback(_close_orphan)  # the thread may still open it
        raise
    except serial.SerialException as e:
        if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK):  # the lock: another program has it
            raise serial.SerialException(
                e.errno, f"{url} is in use by another program (it holds the port's lock)"
            ) from None
        if e.errno == errno.EACCES:  # in a lab: a user not in the device's group
            raise serial.SerialException(
                e.errno,
                f"no permission to open {url}: add this user to the group that owns "
                f"it (usually dialout; ls -l {url}), then log in again",
            ) from None
        raise
    _need_fileno(port, url)
    _exclusive_tty(port)
    _tune_socket(port)
    try:
        reader = PushReader(limit=limit, loop=loop)
        protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
        transport, _ = await serial_asyncio.connection_for_serial(loop, lambda: protocol, port)
    except BaseException:
        port.close()
        raise
    return reader, asyncio.StreamWriter(transport, protocol, reader, loop)


async def _open_unix(url: str, limit: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    path = urllib.parse.urlsplit(url.strip()).path
    if not path:
        raise serial.SerialException(f"expected a URL like unix:///path/to/socket, got {url!r}")
    loop = asyncio.get_running_loop()
    reader = PushReader(limit=limit, loop=loop)
    protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
    try:
        transport, _ = await loop.create_unix_connection(lambda: protocol, path)
    except OSError as e:
        raise serial.SerialException(f"Could not open port {url}: {e}") from None
    return reader, asyncio.StreamWriter(transport, protocol, reader, loop)


def _need_fileno(port: serial.SerialBase, url: str) -> None:
    """The event loop watches a port's file descriptor: a pyserial URL without one (loop://,
    rfc2217://) would fail at its first write and hang as it closed."""
    try:
        port.fileno()
    except (OSError, ValueError, AttributeError):  # io.UnsupportedOperation is both of the first
        port.close()
        raise serial.SerialException(
            f"{url}: this kind of port has no file descriptor, which sdh2svc's links need "
            "(give a device path, socket://HOST:PORT or unix://PATH)"
        ) from None


def _exclusive_tty(port: serial.SerialBase) -> None:
    """A terminal device in exclusive mode (TIOCEXCL): pyserial's lock is advisory, and a
    program that opens the line plainly (SDHLibrary, a terminal, ``echo > /dev/ttyUSB0``) could
    still write into it; the kernel refuses it (EBUSY) while the line is ours — except to root.
    :func:`close_streams` ends the mode."""
    fd = getattr(port, "fd", None)
    if isinstance(fd, int) and os.isatty(fd):
        with contextlib.suppress(OSError):
            fcntl.ioctl(fd, termios.TIOCEXCL)


def _close_orphan(opening: asyncio.Future[serial.Serial]) -> None:
    if not opening.cancelled() and opening.exception() is None:
        opening.result().close()


def _tune_socket(port: serial.SerialBase) -> None:
    """Fix up pyserial's ``socket://`` port: its close() sleeps 0.3 s on the loop thread and
    skips ``socket.close()`` when ``shutdown()`` fails (peer already gone), leaking the fd. Also
    turn Nagle off: every command is one small write that should leave at once."""
    sock = getattr(port, "_socket", None)
    if not isinstance(sock, socket.socket):
        return
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def close() -> None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        port._socket = None  # type: ignore[attr-defined]
        port.is_open = False

    port.close = close  # type: ignore[method-assign]


async def close_streams(writer: asyncio.StreamWriter) -> None:
    """Close the port behind ``writer``; never raises (the port may already be gone)."""
    port = getattr(writer.transport, "serial", None)  # pyserial-asyncio's transport
    fd = getattr(port, "fd", None)
    if isinstance(fd, int) and fd >= 0 and os.isatty(fd):  # others may open it once we are done
        with contextlib.suppress(OSError):
            fcntl.ioctl(fd, termios.TIOCNXCL)
    with contextlib.suppress(Exception):
        writer.close()
    try:  # bounded: a converter that takes no more bytes must not hold us, nor keep the port
        await asyncio.wait_for(writer.wait_closed(), CLOSE_WAIT_S)
    except Exception:
        with contextlib.suppress(Exception):
            writer.transport.abort()
