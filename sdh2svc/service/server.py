"""``sdh2svc serve``: one asyncio process with uvicorn, the links, the runner, the telemetry hub,
the recorder and the viser view.

SIGINT/SIGTERM stop motion first (the running run is asked to stop at once, then uvicorn's
shutdown waits for it to release), then everything closes. Logs go to stderr, one line each —
plain ``LEVEL logger: message`` for journald, or ``--log-format json``.
"""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import socket
import sys
from typing import Any

import uvicorn

from sdh2svc.bus.joint import JointLinkError
from sdh2svc.bus.tactile import TactileError
from sdh2svc.config import Settings
from sdh2svc.connect import Where
from sdh2svc.hosts import is_loopback
from sdh2svc.service.app import Services, close_services, create_app, open_services, viewer_host
from sdh2svc.service.foxglove_live import FoxgloveStartError
from sdh2svc.service.hand_service import STOPPED_BY_SHUTDOWN
from sdh2svc.service.store import RunStore, StoreError
from sdh2svc.service.viewer_proc import bind_error

log = logging.getLogger(__name__)


class ExposureError(ValueError):
    """Refusal to listen beyond loopback without a token (a configuration error)."""


class StartError(RuntimeError):
    """The service cannot start for a reason outside it: a port is taken, the hand does not
    answer, the run database is unusable. The message names the port, device or path."""


class PortBusy(StartError):
    """A port the service must listen on is taken."""


class HandUnreachable(StartError):
    """One of the hand's two lines cannot be opened or does not answer."""


def check_exposure(cfg: Settings) -> None:
    if not is_loopback(cfg.service.host) and not cfg.service.token:
        raise ExposureError(
            f"refusing to listen on {cfg.service.host} without a token: anyone on the network "
            "could move the hand. Set SDH2SVC_SERVICE__TOKEN (or service.token), or listen on "
            "127.0.0.1."
        )


STALLED_PEER_S = 30  # a connection owed data it takes none of for this long is cut


def listen_socket(cfg: Settings) -> socket.socket:
    """The HTTP socket, with a bounded kernel send buffer (inherited by every connection).

    Linux would otherwise let a client that stopped reading hold up to 4 MB of stale telemetry
    in the kernel — tens of seconds at the tactile stream's rate — before the per-client queue
    and send timeout (service.telemetry_queue, send_timeout_s) could notice. Made as a TCP
    socket by name (IPPROTO_TCP): asyncio turns Nagle's algorithm off only on those, and with
    it on, every answer after the first on a kept-alive connection waited ≈ 40 ms for the
    client's delayed ACK.
    """
    host, port = cfg.service.host, cfg.service.port
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, cfg.service.send_buffer_kb * 1024)
    # a peer that stays connected but takes no byte for this long (a script wedged, its window
    # shut) is cut by the kernel: the telemetry hub had dropped it, but closing the WebSocket
    # waited on a send buffer that never drained, holding the connection, its task and ≈ 0.5
    # MB for as long as the peer lived (no effect on idle connections: nothing is owed)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, STALLED_PEER_S * 1000)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        if e.errno == errno.EADDRINUSE:
            raise PortBusy(
                f"cannot listen on {host}:{port}: port {port} is already in use (stop "
                "whatever uses it, or choose --port; 0 = any free port)"
            ) from None
        raise StartError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def check_viser_port(cfg: Settings) -> None:
    """Fail at once, before the hand is opened, if the 3-D view's port is taken (in a process of
    its own the view would report it late; in this one, viser would quietly move elsewhere)."""
    if cfg.service.viewer:
        port = cfg.service.viser_port
        _check_port(viewer_host(cfg), port, "the 3-D view", _viser_busy(port))


def check_foxglove_port(cfg: Settings) -> None:
    """As :func:`check_viser_port`, for the live Foxglove view's port (0: off): a taken one
    was found only once the hand's lines had been opened, and closed again."""
    host, port = viewer_host(cfg), cfg.service.foxglove_port
    if port:
        where = f"cannot serve the live Foxglove view on {host}:{port}"
        busy = f"{where}: port {port} already in use; set service.foxglove_port to a free port, "
        _check_port(host, port, "the live Foxglove view", busy + "or 0 (off)")


def _check_port(host: str, port: int, what: str, busy: str) -> None:
    """:class:`PortBusy` (``busy``) if ``port`` is taken, a :class:`StartError` if it cannot be
    had for another reason (``what`` cannot be served there)."""
    if (e := bind_error(host, port)) is None:
        return
    if e.errno == errno.EADDRINUSE:
        raise PortBusy(busy)
    raise StartError(f"cannot serve {what} on {host}:{port}: {e.strerror or e}")


def _viser_busy(port: int) -> str:
    return (f"viser port {port} is already in use (stop whatever uses it, or set --viser-port / "
            "service.viser_port; 0 = any free port, --no-viewer = none)")  # fmt: skip


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": round(record.created, 3), "level": record.levelname,
            "logger": record.name, "msg": record.getMessage(),
        }  # fmt: skip
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def setup_logging(fmt: str = "text", level: str = "INFO") -> None:
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    for name in ("uvicorn", "uvicorn.error"):
        logging.getLogger(name).handlers[:] = []
        logging.getLogger(name).propagate = True
    logging.getLogger("uvicorn.access").setLevel(logging.WARNING)


class _Server(uvicorn.Server):
    """uvicorn's server whose exit signal first asks the running run to stop."""

    def _services(self) -> Services | None:
        app: Any = self.config.app  # ours: a FastAPI app
        return getattr(app.state, "services", None)

    def handle_exit(self, sig: int, frame: Any) -> None:
        services = self._services()
        st = services.station if services else None
        if st is not None and st.running and st.run is not None:
            # only sets an asyncio.Event: safe in a signal handler
            st.run.runner.request_stop(STOPPED_BY_SHUTDOWN)
        super().handle_exit(sig, frame)
        # uvicorn re-raises the signal after its graceful shutdown (the process then dies of
        # it); ours is complete and clean, so exit 0 instead
        getattr(self, "_captured_signals", []).clear()

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        """Motion stopped first, while the API still answers: uvicorn's own shutdown closes
        the listener and every connection before the app's lifespan ends, and an e-stop sent
        while the run released found no one to take it."""
        services = self._services()
        if services is not None:
            await services.station.stop_motion()
        await super().shutdown(sockets=sockets)
        if self.force_exit:  # a second Ctrl-C skips the wait for clients, never our close
            await self.lifespan.shutdown()


async def serve(cfg: Settings, where: Where, *, announce_json: bool = False) -> int:
    """Run the service until a signal; returns the exit status.

    Raises :class:`ExposureError` (refusal: configuration) or a :class:`StartError` (a port is
    taken, the hand or the database cannot be opened) before anything is served.
    """
    check_exposure(cfg)
    sock = listen_socket(cfg)  # before the hand: a taken port fails at once
    try:
        check_viser_port(cfg)
        check_foxglove_port(cfg)
        RunStore(
            cfg.storage.db_path, busy_timeout_s=cfg.storage.busy_timeout_s
        ).close()  # an unusable database fails before the hand moves
        services = await open_services(cfg, where)
    except BaseException as e:
        sock.close()
        err = _start_error(e, cfg)
        if err is None:  # a bug, or Ctrl-C: as it is
            raise
        raise err from None
    try:
        app = create_app(services)
        # No permessage-deflate: it would compress every telemetry message once per client
        # (20 clients: 20 deflates of each tactile frame) on the control loop's thread, to
        # save bandwidth a lab network does not miss (a tactile frame is ~2.5 kB).
        config = uvicorn.Config(app, host=cfg.service.host, port=cfg.service.port,
                                log_config=None, lifespan="on", ws="websockets-sansio",
                                ws_per_message_deflate=False)  # fmt: skip
        server = _Server(config)
        task = asyncio.create_task(server.serve(sockets=[sock]))
        while not server.started and not task.done():
            await asyncio.sleep(0.05)
        if server.started:
            _announce(server, services, announce_json)
        try:
            await task
        except SystemExit as e:  # uvicorn's startup failure: it has logged why
            return int(e.code or 1)
        return 0
    finally:
        await close_services(services)


def _start_error(e: BaseException, cfg: Settings) -> StartError | None:
    """What an exception while opening the hand and the view means to whoever started us."""
    from sdh2svc.service.viewer_proc import ViewerError

    if isinstance(e, StartError):
        return e
    if isinstance(e, StoreError):
        return StartError(str(e))
    if isinstance(e, ViewerError):
        if "in use" in str(e):  # the port was taken between our check and viser's bind
            return PortBusy(_viser_busy(cfg.service.viser_port))
        return StartError(f"cannot start the 3-D view: {e}")
    if isinstance(e, FoxgloveStartError):
        return PortBusy(str(e)) if "in use" in str(e) else StartError(str(e))
    if isinstance(e, JointLinkError | TactileError | OSError):
        return HandUnreachable(
            f"cannot open the hand: {e} (check --sdh/--dsa or links.sdh_url/dsa_url)"
        )
    return None


def _announce(server: uvicorn.Server, services: Services, as_json: bool) -> None:
    sock = server.servers[0].sockets[0].getsockname()
    host = server.config.host
    url = f"http://{host if ':' not in host else f'[{host}]'}:{sock[1]}"
    st = services.station
    sim = st.bench is not None
    fox = services.foxglove
    info = {"url": url, "dashboard": f"{url}/", "docs": f"{url}/docs",
            "viewer_url": services.viewer_url, "foxglove_url": fox.url if fox else None,
            "sim": sim, "dsa_url": st.dsa_url, "sdh_url": st.sdh_url}  # fmt: skip
    if as_json:
        print(json.dumps(info), flush=True)
        return
    hand = "the simulated hand" if sim else f"the hand at {st.sdh_url} + {st.dsa_url}"
    print(f"sdh2svc serving {hand}\n"
          f"  dashboard  {info['dashboard']}\n"
          f"  API docs   {info['docs']}\n"
          f"  3-D view   {info['viewer_url'] or '(off)'}\n"
          f"  Foxglove   {info['foxglove_url'] or '(off: service.foxglove_port)'}\n"
          "Ctrl-C stops motion, then the service.", flush=True)  # fmt: skip
