"""The service's listening socket, as uvicorn serves on it (an asyncio server on that socket)."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path

from sdh2svc.config import load_config
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
