"""The service's listening socket, as uvicorn serves on it (an asyncio server on that socket)."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path

import pytest

from sdh2svc.config import load_config
from sdh2svc.service import server
from sdh2svc.service.server import listen_socket


def test_the_connections_send_at_once(tmp_path: Path) -> None:
    """Nagle's algorithm off on every accepted connection: asyncio turns it off only on sockets
    made as IPPROTO_TCP, and with it on each answer after the first on a kept-alive connection
    waited ≈ 40 ms for the client's delayed ACK."""
    cfg = load_config(overrides=["service.host='127.0.0.1'", "service.port=0"], use_env=False)

    async def main() -> int:
        sock = listen_socket(cfg)
        accepted: asyncio.Future[int] = asyncio.get_running_loop().create_future()

        async def serve(_reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            conn = writer.get_extra_info("socket")
            accepted.set_result(conn.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            writer.close()

        server = await asyncio.start_server(serve, sock=sock)
        async with server:
            _, w = await asyncio.open_connection(*sock.getsockname()[:2])
            nodelay = await asyncio.wait_for(accepted, 10)
            w.close()
        return nodelay

    assert asyncio.run(main()) == 1


def test_a_peer_that_takes_nothing_is_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A telemetry client that stays connected but never reads: the hub dropped it, but the
    WebSocket's close waited on a send buffer that never drained, and the connection, its task
    and ≈ 0.5 MB stayed as long as the peer lived (the keep-alive's 1011 close never went out).
    Every accepted connection now has TCP_USER_TIMEOUT: the kernel cuts a peer that takes no
    byte of what it is owed for that long (1 s here; STALLED_PEER_S in the service)."""
    monkeypatch.setattr(server, "STALLED_PEER_S", 1, raising=False)
    cfg = load_config(overrides=["service.host='127.0.0.1'", "service.port=0"], use_env=False)

    async def main() -> tuple[int, str]:
        sock = listen_socket(cfg)
        cut: asyncio.Future[str] = asyncio.get_running_loop().create_future()

        async def flood(_reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            timeout = writer.get_extra_info("socket").getsockopt(
                socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT
            )
            try:
                while True:
                    writer.write(b"x" * 65536)
                    await writer.drain()
            except OSError as e:
                cut.set_result(f"{timeout} {type(e).__name__}")

        server_ = await asyncio.start_server(flood, sock=sock)
        async with server_:
            peer = socket.socket()
            peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            peer.connect(sock.getsockname()[:2])  # and never reads
            try:
                said = await asyncio.wait_for(cut, 30)  # (a guard: the cut comes in ≈ 1 s)
            finally:
                peer.close()
        timeout, error = said.split()
        return int(timeout), error

    assert asyncio.run(main()) == (1000, "TimeoutError")
