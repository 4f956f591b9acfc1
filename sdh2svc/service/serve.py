"""``sdh2svc serve``: one asyncio process with uvicorn, the links, the runner, the telemetry hub,
the recorder and the viser view.

SIGINT/SIGTERM stop motion first (the running run is asked to stop at once, then uvicorn's
shutdown waits for it to release), then everything closes. Logs go to stderr, one line each —
plain ``LEVEL logger: message`` for journald, or ``--log-format json``.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import socket
import sys
from typing import Any

import uvicorn

from sdh2svc.config import Settings
from sdh2svc.service.app import Services, close_services, create_app, open_services

log = logging.getLogger(__name__)


class ExposureError(ValueError):
    """Refusal to listen: beyond loopback without a token, or the address is unusable."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: assume it is reachable from elsewhere


def check_exposure(cfg: Settings) -> None:
    if not is_loopback(cfg.service.host) and not cfg.service.token:
        raise ExposureError(
            f"refusing to listen on {cfg.service.host} without a token: anyone on the network "
            "could move the hand. Set SDH2SVC_SERVICE__TOKEN (or service.token), or listen on "
            "127.0.0.1."
        )


def listen_socket(cfg: Settings) -> socket.socket:
    """The HTTP socket, with a bounded kernel send buffer (inherited by every connection).

    Linux would otherwise let a client that stopped reading hold up to 4 MB of stale telemetry
    in the kernel — tens of seconds at the tactile stream's rate — before the per-client queue
    and send timeout (service.telemetry_queue, send_timeout_s) could notice.
    """
    host, port = cfg.service.host, cfg.service.port
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, cfg.service.send_buffer_kb * 1024)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise ExposureError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


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

    def handle_exit(self, sig: int, frame: Any) -> None:
        services: Services | None = getattr(self.config.app.state, "services", None)
        st = services.station if services else None
        if st is not None and st.running and st.run is not None:
            st.run.runner.request_stop()  # only sets an asyncio.Event: safe in a signal handler
        super().handle_exit(sig, frame)
        # uvicorn re-raises the signal after its graceful shutdown (the process then dies of
        # it); ours is complete and clean, so exit 0 instead
        getattr(self, "_captured_signals", []).clear()


async def serve(
    cfg: Settings,
    *,
    sim: bool,
    dsa_url: str | None = None,
    sdh_url: str | None = None,
    obj: Any = None,
    announce_json: bool = False,
) -> int:
    """Run the service until a signal; returns the exit status."""
    check_exposure(cfg)
    sock = listen_socket(cfg)  # before the hand: a taken port fails at once
    try:
        services = await open_services(cfg, sim=sim, dsa_url=dsa_url, sdh_url=sdh_url, obj=obj)
    except Exception as e:
        sock.close()
        log.error("cannot open the hand: %s (check --sdh/--dsa or links.sdh_url/dsa_url)", e)
        return 1
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
            _announce(server, services, sim, announce_json)
        try:
            await task
        except SystemExit as e:  # uvicorn's startup failure: it has logged why
            return int(e.code or 1)
        return 0
    finally:
        await close_services(services)


def _announce(server: uvicorn.Server, services: Services, sim: bool, as_json: bool) -> None:
    sock = server.servers[0].sockets[0].getsockname()
    host = server.config.host
    url = f"http://{host if ':' not in host else f'[{host}]'}:{sock[1]}"
    st = services.station
    info = {"url": url, "dashboard": f"{url}/", "docs": f"{url}/docs",
            "viewer_url": services.viewer_url, "sim": sim,
            "dsa_url": st.dsa_url, "sdh_url": st.sdh_url}  # fmt: skip
    if as_json:
        print(json.dumps(info), flush=True)
        return
    hand = "the simulated hand" if sim else f"the hand at {st.sdh_url} + {st.dsa_url}"
    print(f"sdh2svc serving {hand}\n"
          f"  dashboard  {info['dashboard']}\n"
          f"  API docs   {info['docs']}\n"
          f"  3-D view   {info['viewer_url'] or '(off)'}\n"
          "Ctrl-C stops motion, then the service.", flush=True)  # fmt: skip
