"""A TCP cable between a host and a device that can be cut and plugged back in (fault tests).

Every connection the host opens to :attr:`Cable.url` is forwarded, byte for byte, to the
device's TCP port. :meth:`Cable.cut` drops every connection on both sides at once and refuses
new ones until :meth:`Cable.plug` — what pulling the RS-232 plug looks like through a
serial-to-TCP adapter. :meth:`Cable.hold` keeps the connections open but carries nothing either
way until :meth:`Cable.resume` (then what was held back goes on, or, with ``lose=True``, what
was sent meanwhile is lost): a line that falls silent — a converter that stalls, a controller
that hangs and forgets its input — while the port stays open.

:meth:`Cable.unix` is the same cable between Unix sockets, for the simulated hand in fast mode
(its virtual clock needs a transport that delivers at once, :mod:`sdh2svc.sim.clock`).
"""

from __future__ import annotations

import asyncio
import contextlib


class Cable:
    def __init__(self, device_host: str, device_port: int, *, host: str = "127.0.0.1") -> None:
        self.device_host, self.device_port, self.host = device_host, device_port, host
        self.port = 0
        self.device_path: str | None = None  # a Unix socket's device and host ends (unix())
        self.path: str | None = None
        self.cuts = 0
        self._server: asyncio.Server | None = None
        self._pipes: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._flowing = asyncio.Event()
        self._flowing.set()
        self._losing = False  # held with lose=True: bytes are dropped, not held back

    @classmethod
    def unix(cls, device_url: str, path: str) -> Cable:
        """A cable from ``unix://path`` (its :attr:`url`) to a device served at ``device_url``
        (``unix:///…``)."""
        cable = cls("", 0)
        cable.device_path, cable.path = device_url.removeprefix("unix://"), path
        return cable

    @property
    def url(self) -> str:
        return f"unix://{self.path}" if self.path else f"socket://{self.host}:{self.port}"

    async def plug(self) -> None:
        """Listen (again, on the same port once it had one)."""
        if self._server is not None:
            return
        if self.path is not None:
            self._server = await asyncio.start_unix_server(self._connection, self.path)
        else:
            self._server = await asyncio.start_server(self._connection, self.host, self.port)
            self.port = self._server.sockets[0].getsockname()[1]

    async def cut(self) -> None:
        """Drop every connection now and refuse new ones until :meth:`plug`."""
        self.cuts += 1
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for w in list(self._writers):
            w.transport.abort()
        for task in list(self._pipes):
            task.cancel()
        if server is not None:
            with contextlib.suppress(Exception):
                await server.wait_closed()

    def hold(self, *, lose: bool = False) -> None:
        """Carry nothing either way (the connections stay open) until :meth:`resume`; what is
        sent meanwhile goes on then, or with ``lose`` is lost."""
        self._losing = lose
        if not lose:
            self._flowing.clear()

    def resume(self) -> None:
        self._losing = False
        self._flowing.set()

    async def close(self) -> None:
        await self.cut()

    async def _connection(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        try:
            if self.device_path is not None:
                dr, dw = await asyncio.open_unix_connection(self.device_path)
            else:
                dr, dw = await asyncio.open_connection(self.device_host, self.device_port)
        except OSError:
            w.transport.abort()
            return
        self._writers |= {w, dw}
        pipes = [asyncio.create_task(self._pump(r, dw)),
                 asyncio.create_task(self._pump(dr, w))]  # fmt: skip
        self._pipes.update(pipes)
        try:
            await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in pipes:
                task.cancel()
                self._pipes.discard(task)
            for writer in (w, dw):
                writer.transport.abort()
                self._writers.discard(writer)

    async def _pump(self, src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError, asyncio.IncompleteReadError):
            while data := await src.read(65536):
                await self._flowing.wait()
                if self._losing:
                    continue
                dst.write(data)
                await dst.drain()
