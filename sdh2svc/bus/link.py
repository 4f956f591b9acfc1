"""Open any pyserial URL or device path as a pair of asyncio streams.

Shared by the bus drivers (joint controller, tactile controller). pyserial-asyncio's
``open_serial_connection`` opens the port on the event loop thread, which blocks the loop for as
long as a ``socket://`` connect takes; here the blocking ``serial_for_url`` runs in a worker
thread and only the transport is built on the loop. pyserial's ``socket://`` close() is patched
(see :func:`_tune_socket`).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from typing import Any, Final

import serial
import serial_asyncio

__all__ = ["DEFAULT_BAUD", "close_streams", "is_socket_url", "open_streams"]

DEFAULT_BAUD: Final = 115_200


def is_socket_url(url: str) -> bool:
    """Whether ``url`` is pyserial's raw TCP transport (``socket://host:port``)."""
    return url.strip().lower().startswith("socket://")


async def open_streams(
    url: str, *, baudrate: int = DEFAULT_BAUD, limit: int = 2**16, **serial_kwargs: Any
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Open ``url`` (device path or pyserial URL) raw 8N1, no flow control.

    Raises ``serial.SerialException`` (or ``OSError``) when the port cannot be opened. A lost
    port later shows as an exception (or EOF) from the reader.
    """
    loop = asyncio.get_running_loop()
    opening = asyncio.ensure_future(asyncio.to_thread(
        serial.serial_for_url, url, baudrate=baudrate, rtscts=False, xonxoff=False,
        **serial_kwargs,
    ))  # fmt: skip
    try:
        port = await asyncio.shield(opening)
    except asyncio.CancelledError:
        opening.add_done_callback(_close_orphan)  # the thread may still open it
        raise
    _tune_socket(port)
    try:
        reader = asyncio.StreamReader(limit=limit, loop=loop)
        protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
        transport, _ = await serial_asyncio.connection_for_serial(loop, lambda: protocol, port)
    except BaseException:
        port.close()
        raise
    return reader, asyncio.StreamWriter(transport, protocol, reader, loop)


def _close_orphan(opening: asyncio.Future[serial.SerialBase]) -> None:
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
    with contextlib.suppress(Exception):
        writer.close()
    with contextlib.suppress(Exception):
        await writer.wait_closed()
