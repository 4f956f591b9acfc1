"""A Python client of the sdh2svc service (``sdh2svc serve``): :class:`Client` (sync) and
:class:`AsyncClient` (asyncio), over its REST API and the ``/ws/telemetry`` WebSocket.

    with Client("http://127.0.0.1:8000") as hand:
        run_id = hand.start_run(params={"cycles": 1}, object="egg")["run_id"]
        hand.wait_run(run_id)
        hand.export(run_id, "run.mcap")

Every call is one route of docs/api.md; a refusal raises :class:`ApiError` (or the subclass for
its status) carrying the service's ``{"error", "details"}``. Answers are the service's JSON as
dicts. Imports nothing of the service itself, so a lab script needs only httpx and websockets.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, TypedDict, cast
from urllib.parse import urlsplit, urlunsplit

import httpx
from websockets.asyncio.client import ClientConnection
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import (
    ConnectionClosed,
    ConnectionClosedOK,
    InvalidHandshake,
    InvalidStatus,
    InvalidURI,
)
from websockets.sync.client import ClientConnection as SyncClientConnection
from websockets.sync.client import connect as ws_connect_sync

from sdh2svc.files import whole_file
from sdh2svc.hosts import is_loopback

__all__ = [
    "ApiError",
    "AsyncClient",
    "AsyncTelemetry",
    "Client",
    "Conflict",
    "ExportFormat",
    "Forbidden",
    "InvalidRequest",
    "NotFound",
    "RunRef",
    "SamplePage",
    "StatusCheck",
    "Telemetry",
    "TelemetryMessage",
    "TooSlow",
    "Unauthorized",
    "Unavailable",
    "Unreachable",
    "run_state",
    "service_url",
]

DEFAULT_URL = "http://127.0.0.1:8000"
ExportFormat = Literal["csv", "mcap"]
JSON = dict[str, Any]
# the sdh2svc.service.telemetry messages (hello, status, sample, event, tactile, pose, sim,
# dropped) as JSON: each has a "type"
TelemetryMessage = JSON
StatusCheck = Callable[[JSON], bool]  # a condition on the status (Client.wait_status)
# The e-stop's own limit: an unanswered stop must be known soon. The service answers within
# 2.5 s at worst (1.5 s for a silent joint line, then 1 s for a locked run database).
ESTOP_TIMEOUT_S = 4.0
_WS_MAX_BYTES = 2**24  # a hello carries the whole status; a tactile frame six matrices
# Closes that end the telemetry as the service meant it: normal, going away, restarting. Any
# other end of the socket (no close frame, a keepalive ping unanswered) is a lost service.
_SERVICE_CLOSES = frozenset({1000, 1001, 1012})
_SLOW_CLOSE = 1008  # the service cut this client off: it took no message in time (docs/api.md)
# The WebSocket library's own log (a keepalive that failed, …): the client says what went wrong
# in the exception it raises; a lab script that configures logging still sees it.
_WS_LOG = logging.getLogger(__name__ + ".websocket")
_WS_LOG.addHandler(logging.NullHandler())


class RunRef(TypedDict):
    """A run as it was started or stopped; follow its state in ``status()["run"]``."""

    run_id: int
    state: str


SamplePage = TypedDict(  # (`from` is a keyword: the functional form)
    "SamplePage",
    {"run_id": int, "from": int, "offset": int, "limit": int, "every": int, "total": int,
     "next": int | None, "samples": list[JSON]},
)  # fmt: skip


# --- errors ----------------------------------------------------------------------------------


class ApiError(Exception):
    """The service refused a request: ``status`` (HTTP), ``error`` (a sentence), ``details``
    (one line per bad field, for a 422)."""

    def __init__(self, status: int, error: str, details: list[Any], method: str, url: str):
        self.status, self.error, self.details = status, error, details
        self.method, self.url = method, url
        more = "".join(f"\n  {d}" for d in details)
        super().__init__(f"{method} {url}: {status} {error}{more}")

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled and copied whole (a worker process's error reaches its parent)."""
        return (type(self), (self.status, self.error, self.details, self.method, self.url))


class InvalidRequest(ApiError):
    """400, 413, 415, 422: the request itself (a value out of range, an unknown field …)."""


class Unauthorized(ApiError):
    """401: a token is configured and this request did not carry it."""


class Forbidden(ApiError):
    """403: the Origin is not allowed."""


class NotFound(ApiError):
    """404: no such run, or not in simulation."""


class Conflict(ApiError):
    """409: a run is (not) running, the e-stop is latched (or came during a release), the hand
    is opening, a run to delete is being recorded."""


class Unavailable(ApiError):
    """503: the hand's links are not up, the run database did not take a run's start, a delete
    or a release (another program holding it locked), or the service is shutting down."""


class Unreachable(ConnectionError):
    """The service did not answer at all (not running, wrong URL, a network fault, a timeout):
    names the URL and the reason."""


class TooSlow(Unreachable):
    """The service cut this client's telemetry off: the client took no message within the
    service's send timeout (``service.send_timeout_s``); reconnect, and read faster (or ask
    for less: ``decimate``, ``tactile=False``)."""


_ERRORS: dict[int, type[ApiError]] = {
    **dict.fromkeys((400, 413, 415, 422), InvalidRequest),
    **{401: Unauthorized, 403: Forbidden, 404: NotFound, 409: Conflict, 503: Unavailable},
}


def _error_body(content: bytes | bytearray) -> tuple[str, list[Any]] | None:
    """The service's error body (``error``, ``details``), if that is what ``content`` is."""
    try:
        body = json.loads(content or b"")
    except ValueError:
        return None
    if isinstance(body, dict) and "error" in body:
        return str(body["error"]), list(body.get("details") or [])
    return None


def _raise_for(r: httpx.Response) -> None:
    if r.is_success:
        return
    got = _error_body(r.content)
    error, details = got or (r.reason_phrase or "error", [r.text[:200]] if r.text else [])
    raise _api_error(r.status_code, error, details, r.request.method, str(r.request.url))


def _api_error(status: int, error: str, details: list[Any], method: str, url: str) -> ApiError:
    """The :class:`ApiError` subclass for ``status``."""
    return _ERRORS.get(status, ApiError)(status, error, details, method, url)


@contextlib.contextmanager
def _answered(
    where: str, failures: tuple[type[Exception], ...] = (httpx.TransportError,)
) -> Iterator[None]:
    """Transport ``failures`` as :class:`Unreachable` naming ``where`` (the request, the URL);
    anything else (a file that cannot be written) as it is."""
    try:
        yield
    except failures as e:
        raise Unreachable(f"{where}: the service did not answer "
                          f"({str(e) or type(e).__name__})") from e  # fmt: skip


@contextlib.contextmanager
def _handshake(url: str) -> Iterator[None]:
    """A WebSocket handshake the service refused (an HTTP error), as its ApiError; one it did
    not answer, or answered with something that is no handshake, as :class:`Unreachable`."""
    with _answered(url, (OSError, TimeoutError, InvalidHandshake, InvalidURI, ConnectionClosed)):
        try:
            yield
        except InvalidStatus as e:
            r = e.response
            error, details = _error_body(r.body or b"") or (r.reason_phrase or "error", [])
            raise _api_error(r.status_code, error, details, "GET", url) from None


def _ws_options(timeout: float) -> dict[str, Any]:
    """The handshake within ``timeout``, and a keepalive ping every ``min(10, timeout)`` s that
    must be answered within ``timeout``; then the closing handshake a hung service never answers
    is waited for ``min(2, timeout)`` s (the library's 10 s default made a 1 s client learn of
    a hung service after 12 s): a hung service ends the telemetry within three times the
    client's timeout (timeout + 12 s beyond 10 s), whatever the messages' rate."""
    return {"max_size": _WS_MAX_BYTES, "open_timeout": timeout, "logger": _WS_LOG,
            "ping_interval": min(10.0, timeout), "ping_timeout": timeout,
            "close_timeout": min(2.0, timeout)}  # fmt: skip


def _direct(url: str) -> bool:
    """Whether ``url``'s service is on this machine, and so asked directly, never through the
    proxy of ``http_proxy``/``all_proxy`` (a lab PC's, a container's): that proxy would answer
    for another host or not at all, and the error would name the service."""
    return is_loopback(urlsplit(url).hostname)


def _ws_open_sync(url: str, headers: dict[str, str], timeout: float) -> SyncClientConnection:
    with _handshake(url):
        return ws_connect_sync(
            url,
            additional_headers=headers,
            proxy=None if _direct(url) else True,
            **_ws_options(timeout),
        )


async def _ws_open(url: str, headers: dict[str, str], timeout: float) -> ClientConnection:
    with _handshake(url):
        return await ws_connect(
            url,
            additional_headers=headers,
            proxy=None if _direct(url) else True,
            **_ws_options(timeout),
        )


def _lost(e: ConnectionClosed, url: str) -> Unreachable | None:
    """None when the telemetry ended as the service (or this client) closed it; else the
    :class:`Unreachable` to raise (the service died, hung, or the network went), or
    :class:`TooSlow` (the service cut this client off: it read too slowly)."""
    code = e.rcvd.code if e.rcvd is not None else None
    if code == _SLOW_CLOSE:
        return TooSlow(f"{url}: the service cut the telemetry off: this client read "
                       f"{e.rcvd.reason if e.rcvd else 'too slowly'}")  # fmt: skip
    if isinstance(e, ConnectionClosedOK) or code in _SERVICE_CLOSES:
        return None
    return Unreachable(f"{url}: the telemetry was cut off ({e})")


# --- the routes, once for both clients --------------------------------------------------------

_NONE: Any = object()  # no body at all (POST /api/estop); other commands send JSON, even {}


@dataclass(frozen=True)
class _Call:
    method: str
    path: str
    body: Any = _NONE
    query: dict[str, Any] = field(default_factory=dict)
    timeout: float | None = None  # a limit of its own, below the client's (the e-stop)

    def kwargs(self, client_timeout: float | None) -> dict[str, Any]:
        """httpx's arguments; the call's own limit, or the client's if shorter (None: none)."""
        kw: dict[str, Any] = {"params": self.query} if self.query else {}
        if self.body is not _NONE:
            kw["json"] = self.body
        if self.timeout is not None:
            kw["timeout"] = min(self.timeout, client_timeout or self.timeout)
        return kw


def _start(params: Mapping[str, Any] | None, obj: str | Mapping[str, Any] | None) -> _Call:
    body: JSON = {}
    if params is not None:
        body["params"] = dict(params)
    if obj is not None:
        body["object"] = obj if isinstance(obj, str) else dict(obj)
    return _Call("POST", "/api/runs", body)


def _samples(
    run_id: int, offset: int, limit: int | None, outline: bool = False, first: int = 0,
    every: int = 1,
) -> _Call:  # fmt: skip
    query: dict[str, Any] = {"offset": offset}
    if limit is not None:
        query["limit"] = limit
    if outline:
        query["outline"] = "true"
    if first:
        query["from"] = first
    if every != 1:
        query["every"] = every
    return _Call("GET", f"/api/runs/{run_id}/samples", query=query)


def _frames(run_id: int, first: int, limit: int, to: int | None = None, every: int = 1) -> _Call:
    query: dict[str, Any] = {"from": first, "limit": limit}
    if to is not None:
        query["to"] = to
    if every != 1:
        query["every"] = every
    return _Call("GET", f"/api/runs/{run_id}/frames", query=query)


def _truth(run_id: int, first: int, limit: int, every: int = 1) -> _Call:
    query: dict[str, Any] = {"from": first, "limit": limit}
    if every != 1:
        query["every"] = every
    return _Call("GET", f"/api/runs/{run_id}/truth", query=query)


def _press(pad: int, x_mm: float, y_mm: float, force_n: float, radius_mm: float | None,
           duration_s: float | None) -> _Call:  # fmt: skip
    body: JSON = {"pad": pad, "x_mm": x_mm, "y_mm": y_mm, "force_n": force_n}
    if radius_mm is not None:
        body["radius_mm"] = radius_mm
    if duration_s is not None:
        body["duration_s"] = duration_s
    return _Call("POST", "/api/sim/press", body)


_ESTOP = _Call("POST", "/api/estop", timeout=ESTOP_TIMEOUT_S)
_RELEASE_PRESS = _Call("DELETE", "/api/sim/press", {})
_END_REPLAY = _Call("DELETE", "/api/viewer/replay", {})


def _runs(limit: int | None, before: int | None) -> _Call:
    query = {k: v for k, v in (("limit", limit), ("before", before)) if v is not None}
    return _Call("GET", "/api/runs", query=query)


def _replay(run_id: int, iteration: int) -> _Call:
    return _Call("PUT", "/api/viewer/replay", {"run_id": run_id, "iteration": iteration})


def _object(name: str | None, spec: Mapping[str, Any] | None) -> _Call:
    if (name is None) == (spec is None):
        raise ValueError("give an object's name or its spec")
    return _Call(
        "PUT", "/api/sim/object", {"name": name} if name is not None else {"spec": dict(spec or {})}
    )


def _export(run_id: int, fmt: ExportFormat) -> _Call:
    return _Call("GET", f"/api/runs/{run_id}/export", query={"format": fmt})


def _format_of(path: Path, fmt: ExportFormat | None) -> ExportFormat:
    if fmt is not None:
        return fmt
    if path.suffix.lower() in (".csv", ".mcap"):
        return cast(ExportFormat, path.suffix.lower()[1:])
    raise ValueError(f"{path}: say format='csv' or 'mcap' (or name it .csv / .mcap)")


def _ended(status: JSON, run_id: int) -> JSON | None:
    """The run's end (``status["last_run"]``) once it has ended, else None."""
    last = status.get("last_run")
    return cast(JSON, last) if last and last.get("id") == run_id else None


def _current(status: JSON, run_id: int) -> bool:
    """The status shows this run as the one the service runs now (its end comes as
    ``last_run``); otherwise only its recorded row can tell."""
    run = status.get("run") or {}
    return bool(run.get("id") == run_id and run.get("status") in (None, "running"))


def _row_ended(row: JSON) -> JSON | None:
    """A recorded run's end (as ``_ended``) once its row says it is no longer running: it
    ended before the wait began, or another run has ended since (``last_run`` is that one)."""
    if row.get("status") in (None, "running"):
        return None
    message = (row.get("summary") or {}).get("message", "")
    return {"id": row.get("id"), "status": row["status"], "message": message}


def _ws_url(base_url: str, decimate: int, tactile: bool, max_queue: int | None) -> str:
    url = re.sub(r"^http", "ws", base_url.rstrip("/"), count=1, flags=re.IGNORECASE)  # https → wss
    query = f"?decimate={decimate}&tactile={int(tactile)}"
    return f"{url}/ws/telemetry{query}" + (
        f"&max_queue={max_queue}" if max_queue is not None else ""
    )


def run_state(*states: str) -> StatusCheck:
    """A :meth:`Client.wait_status` check: a run is in one of ``states`` (``grasping``,
    ``rolling``, ``e-stopped`` …)."""
    return lambda st: bool(st.get("run")) and st["run"]["state"] in states


def service_url(url: str) -> str:
    """The service's base URL from what a user gave: ``http://`` when no scheme is given (as
    curl does), no trailing slash, a path prefix (behind a proxy) kept. ValueError naming the
    URL when it cannot be one (another scheme, no host, a bad port)."""
    text = url.strip()
    if "://" not in text:
        text = f"http://{text}"
    try:
        parts = urlsplit(text)
        _ = parts.port  # a ValueError if the port is not a number in range
    except ValueError as e:
        raise ValueError(f"{url!r}: {e}") from None
    if parts.scheme.lower() not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{url!r}: give the service's URL as http://HOST:PORT")
    return urlunsplit((parts.scheme, parts.netloc, parts.path.rstrip("/"), "", ""))


def _headers(token: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


# --- sync --------------------------------------------------------------------------------------


class Client:
    """The service over HTTP, blocking. ``token``: the service's bearer token, if it has one;
    ``timeout``: seconds a request (or the telemetry's keepalive) may go unanswered before
    :class:`Unreachable`. Closing it (or leaving ``with``) also disconnects its telemetry.

    Each method is one route of docs/api.md and answers its JSON as dicts and lists (degrees,
    millimetres, seconds, forces in library units). Besides the errors each names, any call
    raises :class:`Unreachable` when the service does not answer, and any refusal its
    :class:`ApiError`: :class:`Unauthorized` for a command without the service's token,
    :class:`Forbidden` for another origin, :class:`InvalidRequest` for a value out of range,
    :class:`Unavailable` when a route that reads the run database cannot open it."""

    def __init__(self, url: str = DEFAULT_URL, token: str | None = None, timeout: float = 30.0):
        self.url, self.token, self.timeout = service_url(url), token, timeout
        self._http = httpx.Client(base_url=self.url, headers=_headers(token), timeout=timeout,
                                  trust_env=not _direct(self.url))  # fmt: skip
        self._sockets: set[SyncClientConnection] = set()  # open telemetry, closed with it
        self._sockets_lock = threading.Lock()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect every telemetry stream of this client (a reader blocked on one ends) and
        close its HTTP connections; leaving ``with`` does it."""
        with self._sockets_lock:
            sockets, self._sockets = list(self._sockets), set()
        for ws in sockets:  # a generator blocked on it ends
            ws.close()
        self._http.close()

    def _call(self, call: _Call) -> Any:
        return self._send(call).json()

    def _send(self, call: _Call) -> httpx.Response:
        """The service's answer to ``call``; a refusal raised (ApiError), no answer too."""
        with _answered(f"{call.method} {self.url}{call.path}"):
            r = self._http.request(call.method, call.path, **call.kwargs(self.timeout))
        _raise_for(r)
        return r

    # the hand
    def status(self) -> JSON:
        """``GET /api/status``: the status object (docs/api.md, *The status object*): ``sim``,
        ``estopped`` and ``estop`` (the latch, None when released), ``hand`` (``connected``,
        ``opening``, ``angles_deg``: the seven actual joint angles, degrees, wire axes 0…6),
        ``links``, ``run`` (None before the first run; ``run["state"]`` ``idle`` … ``e-stopped``),
        ``last_run``, ``params``, ``object`` (None on a real hand), ``telemetry``."""
        return cast(JSON, self._call(_Call("GET", "/api/status")))

    def open_hand(self) -> JSON:
        """``POST /api/hand/open``: open the fingers to the pre-shape pose; answers
        ``{"state": "opening"}`` at once (``status()["hand"]["opening"]`` is true meanwhile).
        :class:`Conflict` while a run runs, the hand is already opening or the e-stop is latched;
        :class:`Unavailable` while the joint line is down or the service shuts down."""
        return cast(JSON, self._call(_Call("POST", "/api/hand/open", {})))

    def estop(self) -> JSON:
        """``POST /api/estop`` (needs no token): latch the e-stop, motors off;
        answers ``{"estopped": True, "hand_reached": bool, "recorded": bool}``, with a ``detail``
        when the hand has not confirmed it or the latch is not on disk yet. :class:`Unreachable`
        within :data:`ESTOP_TIMEOUT_S` (or the client's timeout, if shorter) when the service does
        not answer — stop the hand another way then."""
        return cast(JSON, self._call(_ESTOP))

    def release_estop(self) -> JSON:
        """``POST /api/estop/release``: the latch cleared on disk, then in the hand; answers
        ``{"estopped": False}`` (at once when the service is not e-stopped). :class:`Conflict` when
        an e-stop came during the release, :class:`Unavailable` when the run database or the joint
        line did not take it: it stays latched either way. With the database locked by another
        program the answer may take 2 × ``storage.busy_timeout_s`` (20 s by default)."""
        return cast(JSON, self._call(_Call("POST", "/api/estop/release", {})))

    # parameters and configuration
    def params(self) -> JSON:
        """``GET /api/params``: the rolling parameters in force (``mode``, ``route``,
        ``delta_phi_deg``, ``k``, …, ``cycles``: degrees, millimetres, library force units)."""
        return cast(JSON, self._call(_Call("GET", "/api/params")))

    def patch_params(self, changes: Mapping[str, Any]) -> JSON:
        """``PATCH /api/params``: change some rolling parameters (for the running run from
        its next grasp frame or iteration, and for later runs); answers the whole new set.
        :class:`InvalidRequest` naming each bad field, or a value the safety limits would void."""
        return cast(JSON, self._call(_Call("PATCH", "/api/params", dict(changes))))

    def params_schema(self) -> JSON:
        """``GET /api/params/schema``: the parameters' JSON schema, each field's range,
        description and ``default`` (this configuration's value); its ranges are those
        :meth:`patch_params` takes."""
        return cast(JSON, self._call(_Call("GET", "/api/params/schema")))

    def config(self) -> JSON:
        """``GET /api/config``: the service's effective configuration (``hand``, ``axes``,
        ``limits``, ``tactile``, ``safety``, …; the token masked; ``rolling`` the parameters in
        force, ``links`` the lines in use)."""
        return cast(JSON, self._call(_Call("GET", "/api/config")))

    def viewer(self) -> JSON:
        """``GET /api/viewer``: where the 3-D view is, ``{"url": …}`` (None when it is off)."""
        return cast(JSON, self._call(_Call("GET", "/api/viewer")))

    # runs
    def start_run(
        self, params: Mapping[str, Any] | None = None, object: str | Mapping[str, Any] | None = None
    ) -> RunRef:
        """``POST /api/runs``: start a run with ``params`` (a subset of the rolling
        parameters; else those in force) and, in simulation, ``object`` (a preset name or a spec;
        else the current one); answers ``{"run_id", "state"}`` (follow it in ``status()["run"]``).
        :class:`Conflict` while a run runs, the hand opens or the e-stop is latched;
        :class:`Unavailable` while a line is down, the run database is locked or the service
        shuts down; :class:`InvalidRequest` for a bad parameter or object (or any object on a
        real hand)."""
        return cast(RunRef, self._call(_start(params, object)))

    def stop_run(self) -> RunRef:
        """``POST /api/runs/stop``: the running run stops, opens the hand to the pre-shape and
        ends ``stopped``; answers ``{"run_id", "state"}`` (``{"run_id": None, "state":
        "stopping"}`` when it stops an :meth:`open_hand` instead: the hand holds where it is).
        :class:`Conflict` when neither is under way."""
        return cast(RunRef, self._call(_Call("POST", "/api/runs/stop", {})))

    def runs(self, limit: int | None = None, before: int | None = None) -> list[JSON]:
        """``GET /api/runs``: recorded runs, newest first, each ``{"id", "started_at",
        "ended_at", "status", "iterations", "meta", "summary"}``: ``limit`` of them (the service's
        default: 100, at most 1000), of ids below ``before`` (the next page: the last id of this
        one). :class:`InvalidRequest` for a ``limit`` out of range; :class:`Unavailable` when the
        run database cannot be read."""
        return cast(list[JSON], self._call(_runs(limit, before)))

    def delete_run(self, run_id: int) -> JSON:
        """``DELETE /api/runs/{id}``: delete a recorded run and everything recorded with it;
        answers ``{"deleted": run_id}``. :class:`NotFound` for no such run; :class:`Conflict` while
        it is being recorded; :class:`Unavailable` when the run database did not take it (another
        program holding it locked)."""
        return cast(JSON, self._call(_Call("DELETE", f"/api/runs/{run_id}", {})))

    def run(self, run_id: int) -> JSON:
        """``GET /api/runs/{id}``: one run as :meth:`runs` lists it, with its ``summary`` and
        ``events``. :class:`NotFound` for no such run."""
        return cast(JSON, self._call(_Call("GET", f"/api/runs/{run_id}")))

    def events(self, run_id: int) -> list[JSON]:
        """A run's events, ``[{"t", "iteration", "kind", "detail"}, …]`` (``t`` in seconds
        since the run's start), from :meth:`run` (``GET /api/runs/{id}``). :class:`NotFound` for
        no such run."""
        return cast(list[JSON], self.run(run_id)["events"])

    def samples(
        self, run_id: int, offset: int = 0, limit: int | None = None, outline: bool = False,
        *, first: int = 0, every: int = 1,
    ) -> SamplePage:  # fmt: skip
        """``GET /api/runs/{id}/samples``: a page of a run's samples in iteration order from
        iteration ``first`` on, ``offset`` of them skipped, ``limit`` of them (default 1000, or 100
        with ``outline``: each with its ``estimate_outline``; ``limit`` then at most 100);
        ``every``: one iteration in that many. The page's ``next`` is the ``first`` of the next
        page (None: none); ``total`` counts all the run's samples; a sample's angles are degrees,
        its lengths millimetres. :class:`NotFound` for no such run; :class:`InvalidRequest` for a
        value out of range."""
        call = _samples(run_id, offset, limit, outline, first, every)
        return cast(SamplePage, self._call(call))

    def iter_samples(self, run_id: int, page: int = 1000, every: int = 1) -> Iterator[JSON]:
        """Every sample of a run (``every``: one iteration in that many), a page of ``page``
        at a time through :meth:`samples`, following ``next``; raises as it does, when the page
        that fails is fetched."""
        first: int | None = 0
        while first is not None:
            got = self.samples(run_id, 0, page, first=first, every=every)
            yield from got["samples"]
            first = got["next"]

    def frames(
        self, run_id: int, first: int = 0, limit: int = 500, to: int | None = None,
        every: int = 1,
    ) -> JSON:  # fmt: skip
        """``GET /api/runs/{id}/frames``: a page of a run's tactile frames of iterations
        ``first`` … ``to`` (follow ``next``); ``texels`` is base64 of little-endian uint16 counts,
        the matrices of ``shapes`` one after the other; ``every``: one iteration in that many, as
        :meth:`samples`. :class:`NotFound` for no such run; :class:`Conflict` for a run recorded
        with a configuration this version cannot read; :class:`InvalidRequest` for ``to`` below
        ``first`` or a value out of range."""
        return cast(JSON, self._call(_frames(run_id, first, limit, to, every)))

    def truth(self, run_id: int, first: int = 0, limit: int = 2000, every: int = 1) -> JSON:
        """``GET /api/runs/{id}/truth``: in simulation, the object's truth recorded with each
        iteration from ``first`` on (its ``outline`` and ``truth`` rows, ``y``/``z`` in mm, ``psi``
        in rad; follow ``next``); a real hand's run has ``outline`` None and no rows; ``every`` as
        :meth:`samples`. :class:`NotFound` for no such run."""
        return cast(JSON, self._call(_truth(run_id, first, limit, every)))

    def export_bytes(self, run_id: int, format: ExportFormat = "csv") -> bytes:
        """``GET /api/runs/{id}/export?format=…``: the whole file in memory (CSV, UTF-8, or
        MCAP); :meth:`export` streams a long run to a file instead. :class:`NotFound` for no such
        run; :class:`Conflict` for a run recorded with a configuration this version cannot read;
        :class:`Unavailable` when the run database cannot be read."""
        return self._send(_export(run_id, format)).content

    def export(self, run_id: int, path: str | Path, format: ExportFormat | None = None) -> Path:
        """Write a run to a file (CSV or MCAP, from ``format`` or the file's suffix) as
        :meth:`export_bytes` fetches it, streamed, written whole or not at all (a dropped
        connection leaves an earlier file as it was); answers the path. ValueError when no
        ``format`` is given and the suffix is neither ``.csv`` nor ``.mcap``; raises as
        :meth:`export_bytes`, and OSError when the file cannot be written."""
        path = Path(path)
        call = _export(run_id, _format_of(path, format))
        with (
            _answered(f"{call.method} {self.url}{call.path}"),
            self._http.stream(call.method, call.path, **call.kwargs(self.timeout)) as r,
        ):
            if not r.is_success:
                r.read()
                _raise_for(r)
            with whole_file(path, binary=True) as f:  # a dropped connection: no partial file
                for chunk in r.iter_bytes():
                    f.write(chunk)
        return path

    def wait_run(self, run_id: int, timeout: float = 300.0, poll_s: float = 0.2) -> JSON:
        """Wait until the run has ended (at once if it already has), polling
        ``GET /api/status`` every ``poll_s`` s (and the run's row once the status no longer shows
        it); answers its end ``{"id", "status", "message"}``, as ``status()["last_run"]`` has it.
        :class:`NotFound` for a run the service never had; TimeoutError after ``timeout``
        seconds."""
        deadline = time.monotonic() + timeout
        while (end := self._end_of(self.status(), run_id)) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"run {run_id} did not end within {timeout} s")
            time.sleep(poll_s)
        return end

    def _end_of(self, status: JSON, run_id: int) -> JSON | None:
        if (end := _ended(status, run_id)) is not None or _current(status, run_id):
            return end
        return _row_ended(self.run(run_id))

    def wait_status(self, ok: StatusCheck, timeout: float = 60.0, poll_s: float = 0.05) -> JSON:
        """Poll ``GET /api/status`` every ``poll_s`` s until ``ok(status)`` holds (e.g.
        :func:`run_state` ``("rolling")``); answers that status. TimeoutError after ``timeout``
        seconds."""
        deadline = time.monotonic() + timeout
        while not ok(st := self.status()):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the status did not come to pass within {timeout} s")
            time.sleep(poll_s)
        return st

    # the simulated object (NotFound on a real hand)
    def sim_object(self) -> JSON:
        """``GET /api/sim/object``: ``{"object": spec, "presets": [names]}``, the spec with its
        ``kind``, sizes in mm and ``material``. :class:`NotFound` on a real hand."""
        return cast(JSON, self._call(_Call("GET", "/api/sim/object")))

    def set_sim_object(
        self, name: str | None = None, spec: Mapping[str, Any] | None = None
    ) -> JSON:
        """``PUT /api/sim/object``: place a preset (``name``, e.g. ``"egg"``) or an object
        ``spec`` (docs/api.md, *Object specs*) between the fingertips; answers as
        :meth:`sim_object`. ValueError unless exactly one of ``name`` and ``spec`` is given;
        :class:`NotFound` on a real hand; :class:`Conflict` while a run runs;
        :class:`InvalidRequest` for an unknown preset or a spec outside the limits."""
        return cast(JSON, self._call(_object(name, spec)))

    def press(self, pad: int, x_mm: float, y_mm: float, force_n: float,
              radius_mm: float | None = None, duration_s: float | None = None) -> JSON:  # fmt: skip
        """``POST /api/sim/press``: press matrix ``pad`` (0…5) as a person would, centred
        ``x_mm`` across it (from column 0) and ``y_mm`` along it (from row 0), ``force_n`` (0 < F ≤
        50) over a disc of ``radius_mm`` (default 3) for ``duration_s`` s (default 1, at most 60);
        answers the accepted press, defaults filled in. :class:`NotFound` on a real hand;
        :class:`InvalidRequest` off the pad or out of range."""
        return cast(JSON, self._call(_press(pad, x_mm, y_mm, force_n, radius_mm, duration_s)))

    def release_press(self) -> JSON:
        """``DELETE /api/sim/press``: lift every press that is on; answers
        ``{"released": n}``. :class:`NotFound` on a real hand."""
        return cast(JSON, self._call(_RELEASE_PRESS))

    # the 3-D view
    def show_replay(self, run_id: int, iteration: int) -> JSON:
        """``PUT /api/viewer/replay``: the 3-D view shows a recorded iteration instead of the
        live hand (until :meth:`end_replay`, or 60 s without a newer one); answers ``{"replay":
        {"run_id", "iteration", "t"}, "live_again_in_s": 60}``. :class:`NotFound` for no such run
        or iteration; :class:`Conflict` when the view is off or the run was recorded with a
        configuration this version cannot read."""
        return cast(JSON, self._call(_replay(run_id, iteration)))

    def end_replay(self) -> JSON:
        """``DELETE /api/viewer/replay``: the 3-D view shows the live hand again; answers
        ``{"replay": None, "live_again_in_s": None}``. :class:`Conflict` when the view is off."""
        return cast(JSON, self._call(_END_REPLAY))

    def telemetry(
        self, decimate: int = 1, tactile: bool = True, max_queue: int | None = None
    ) -> Telemetry:
        """``/ws/telemetry``: ``with client.telemetry() as live: for msg in live: …`` (see
        :class:`Telemetry`); ``decimate``: every N-th sample, ``tactile``: the tactile frames or
        not, ``max_queue``: the service's queue for this client. On connecting, a refused handshake
        raises its :class:`ApiError` (:class:`InvalidRequest` for a bad option), no answer
        :class:`Unreachable`."""
        url = _ws_url(self.url, decimate, tactile, max_queue)
        return Telemetry(url, _headers(self.token), self.timeout, self._opened, self._ended)

    def _opened(self, ws: SyncClientConnection) -> None:
        with self._sockets_lock:
            self._sockets.add(ws)

    def _ended(self, ws: SyncClientConnection) -> None:
        with self._sockets_lock:
            self._sockets.discard(ws)


class Telemetry:
    """The live messages of ``/ws/telemetry`` (``hello`` first), blocking, until the service
    closes the socket (or the client is closed). A service that dies, hangs (no keepalive
    answer within the client's ``timeout``) or goes off the network raises
    :class:`Unreachable`. Connects on entering ``with`` or at the first message; leaving the
    ``with`` block, :meth:`close`, or dropping it disconnects. One reader at a time."""

    def __init__(
        self, url: str, headers: dict[str, str], timeout: float,
        opened: Callable[[SyncClientConnection], None],
        ended: Callable[[SyncClientConnection], None],
    ) -> None:  # fmt: skip
        """``opened``/``ended``: the client's note of the open socket (its close closes it)."""
        self._url, self._headers, self._timeout = url, headers, timeout
        self._opened, self._ended = opened, ended
        self._ws: SyncClientConnection | None = None
        self._closed = False

    def __enter__(self) -> Telemetry:
        self._connect()
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __iter__(self) -> Iterator[TelemetryMessage]:
        return self

    def __next__(self) -> TelemetryMessage:
        if self._closed:
            raise StopIteration
        ws = self._connect()
        try:
            text = ws.recv()
        except ConnectionClosed as e:
            self.close()
            if (lost := _lost(e, self._url)) is not None:
                raise lost from e
            raise StopIteration from None
        return cast(TelemetryMessage, json.loads(text))

    def close(self) -> None:
        """Disconnect (the iteration ends); idempotent."""
        self._closed = True
        ws, self._ws = self._ws, None
        if ws is not None:
            try:
                ws.close()
            finally:
                self._ended(ws)

    def __del__(self) -> None:  # dropped unclosed: disconnected, as a generator's end did
        with contextlib.suppress(Exception):
            self.close()

    def _connect(self) -> SyncClientConnection:
        if self._ws is None:
            self._ws = _ws_open_sync(self._url, self._headers, self._timeout)
            self._opened(self._ws)
        return self._ws


# --- async -------------------------------------------------------------------------------------


class AsyncTelemetry:
    """The live messages of ``/ws/telemetry`` (``hello`` first) as an async iterator, until the
    service closes the socket (a service that dies, hangs or goes off the network raises
    :class:`Unreachable`). Connects on first use; use it as ``async with`` to disconnect as
    soon as the block is left (its client's ``aclose`` disconnects it too). Tasks may share
    it: each message goes to one of them."""

    def __init__(
        self, url: str, headers: dict[str, str], timeout: float = 30.0,
        ended: Callable[[AsyncTelemetry], None] | None = None,
    ) -> None:  # fmt: skip
        """``ended``: told once the stream is closed or its connection over (its client keeps
        every open stream, dropped by the program or not, to close it with itself)."""
        self._url, self._headers, self._timeout = url, headers, timeout
        self._ws: ClientConnection | None = None
        self._lock = asyncio.Lock()  # one connection, one reader at a time
        self._closed = False
        self._ended = ended

    async def __aenter__(self) -> AsyncTelemetry:
        async with self._lock:
            await self._connect()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Disconnect (a task waiting for a message gets the end of the iteration)."""
        self._closed = True
        try:
            if self._ws is not None:
                await self._ws.close()
        finally:
            self._end()

    def _end(self) -> None:
        if self._ended is not None:
            self._ended(self)

    def __aiter__(self) -> AsyncIterator[TelemetryMessage]:
        return self

    async def __anext__(self) -> TelemetryMessage:
        async with self._lock:
            if self._closed:
                raise StopAsyncIteration
            ws = await self._connect()
            try:
                text = await ws.recv()
            except ConnectionClosed as e:
                self._end()
                if (lost := _lost(e, self._url)) is not None and not self._closed:
                    raise lost from e
                raise StopAsyncIteration from None
        return cast(TelemetryMessage, json.loads(text))

    async def _connect(self) -> ClientConnection:
        """The connection, opened once (callers hold the lock, or are the only user)."""
        if self._ws is None:
            self._ws = await _ws_open(self._url, self._headers, self._timeout)
            if self._closed:  # closed while the handshake was out
                await self._ws.close()
        return self._ws


class AsyncClient:
    """The service over HTTP and its WebSocket, for asyncio. Same calls as :class:`Client`;
    closing it also disconnects its telemetry."""

    def __init__(self, url: str = DEFAULT_URL, token: str | None = None, timeout: float = 30.0):
        self.url, self.token, self.timeout = service_url(url), token, timeout
        self._http = httpx.AsyncClient(
            base_url=self.url,
            headers=_headers(token),
            timeout=timeout,
            trust_env=not _direct(self.url),
        )
        # every stream not yet ended, held here: one the program dropped still has its
        # connection (its keepalive and reader tasks hold it), which aclose must close
        self._telemetry: set[AsyncTelemetry] = set()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Disconnect every telemetry stream of this client and close its HTTP connections;
        leaving ``async with`` does it."""
        for tm in list(self._telemetry):
            await tm.aclose()
        await self._http.aclose()

    async def _call(self, call: _Call) -> Any:
        return (await self._send(call)).json()

    async def _send(self, call: _Call) -> httpx.Response:
        with _answered(f"{call.method} {self.url}{call.path}"):
            r = await self._http.request(call.method, call.path, **call.kwargs(self.timeout))
        _raise_for(r)
        return r

    # the hand
    async def status(self) -> JSON:
        """As :meth:`Client.status`."""
        return cast(JSON, await self._call(_Call("GET", "/api/status")))

    async def open_hand(self) -> JSON:
        """As :meth:`Client.open_hand`."""
        return cast(JSON, await self._call(_Call("POST", "/api/hand/open", {})))

    async def estop(self) -> JSON:
        """As :meth:`Client.estop`."""
        return cast(JSON, await self._call(_ESTOP))

    async def release_estop(self) -> JSON:
        """As :meth:`Client.release_estop`."""
        return cast(JSON, await self._call(_Call("POST", "/api/estop/release", {})))

    # parameters and configuration
    async def params(self) -> JSON:
        """As :meth:`Client.params`."""
        return cast(JSON, await self._call(_Call("GET", "/api/params")))

    async def patch_params(self, changes: Mapping[str, Any]) -> JSON:
        """As :meth:`Client.patch_params`."""
        return cast(JSON, await self._call(_Call("PATCH", "/api/params", dict(changes))))

    async def params_schema(self) -> JSON:
        """As :meth:`Client.params_schema`."""
        return cast(JSON, await self._call(_Call("GET", "/api/params/schema")))

    async def config(self) -> JSON:
        """As :meth:`Client.config`."""
        return cast(JSON, await self._call(_Call("GET", "/api/config")))

    async def viewer(self) -> JSON:
        """As :meth:`Client.viewer`."""
        return cast(JSON, await self._call(_Call("GET", "/api/viewer")))

    # runs
    async def start_run(
        self, params: Mapping[str, Any] | None = None, object: str | Mapping[str, Any] | None = None
    ) -> RunRef:
        """As :meth:`Client.start_run`."""
        return cast(RunRef, await self._call(_start(params, object)))

    async def stop_run(self) -> RunRef:
        """As :meth:`Client.stop_run`."""
        return cast(RunRef, await self._call(_Call("POST", "/api/runs/stop", {})))

    async def runs(self, limit: int | None = None, before: int | None = None) -> list[JSON]:
        """As :meth:`Client.runs`."""
        return cast(list[JSON], await self._call(_runs(limit, before)))

    async def delete_run(self, run_id: int) -> JSON:
        """As :meth:`Client.delete_run`."""
        return cast(JSON, await self._call(_Call("DELETE", f"/api/runs/{run_id}", {})))

    async def run(self, run_id: int) -> JSON:
        """As :meth:`Client.run`."""
        return cast(JSON, await self._call(_Call("GET", f"/api/runs/{run_id}")))

    async def events(self, run_id: int) -> list[JSON]:
        """As :meth:`Client.events`."""
        return cast(list[JSON], (await self.run(run_id))["events"])

    async def samples(
        self, run_id: int, offset: int = 0, limit: int | None = None, outline: bool = False,
        *, first: int = 0, every: int = 1,
    ) -> SamplePage:  # fmt: skip
        """As :meth:`Client.samples`."""
        call = _samples(run_id, offset, limit, outline, first, every)
        return cast(SamplePage, await self._call(call))

    async def iter_samples(
        self, run_id: int, page: int = 1000, every: int = 1
    ) -> AsyncIterator[JSON]:
        """As :meth:`Client.iter_samples`, an async iterator."""
        first: int | None = 0
        while first is not None:
            got = await self.samples(run_id, 0, page, first=first, every=every)
            for s in got["samples"]:
                yield s
            first = got["next"]

    async def frames(
        self, run_id: int, first: int = 0, limit: int = 500, to: int | None = None,
        every: int = 1,
    ) -> JSON:  # fmt: skip
        """As :meth:`Client.frames`."""
        return cast(JSON, await self._call(_frames(run_id, first, limit, to, every)))

    async def truth(self, run_id: int, first: int = 0, limit: int = 2000, every: int = 1) -> JSON:
        """As :meth:`Client.truth`."""
        return cast(JSON, await self._call(_truth(run_id, first, limit, every)))

    async def export_bytes(self, run_id: int, format: ExportFormat = "csv") -> bytes:
        """As :meth:`Client.export_bytes`."""
        return (await self._send(_export(run_id, format))).content

    async def export(
        self, run_id: int, path: str | Path, format: ExportFormat | None = None
    ) -> Path:
        """As :meth:`Client.export`."""
        path = Path(path)
        call = _export(run_id, _format_of(path, format))
        with _answered(f"{call.method} {self.url}{call.path}"):
            async with self._http.stream(call.method, call.path, **call.kwargs(self.timeout)) as r:
                if not r.is_success:
                    await r.aread()
                    _raise_for(r)
                with whole_file(path, binary=True) as f:
                    async for chunk in r.aiter_bytes():
                        f.write(chunk)
        return path

    async def wait_run(self, run_id: int, timeout: float = 300.0, poll_s: float = 0.2) -> JSON:
        """As :meth:`Client.wait_run`."""
        deadline = time.monotonic() + timeout
        while (end := await self._end_of(await self.status(), run_id)) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"run {run_id} did not end within {timeout} s")
            await asyncio.sleep(poll_s)
        return end

    async def _end_of(self, status: JSON, run_id: int) -> JSON | None:
        if (end := _ended(status, run_id)) is not None or _current(status, run_id):
            return end
        return _row_ended(await self.run(run_id))

    async def wait_status(
        self, ok: StatusCheck, timeout: float = 60.0, poll_s: float = 0.05
    ) -> JSON:
        """As :meth:`Client.wait_status`."""
        deadline = time.monotonic() + timeout
        while not ok(st := await self.status()):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the status did not come to pass within {timeout} s")
            await asyncio.sleep(poll_s)
        return st

    # the simulated object
    async def sim_object(self) -> JSON:
        """As :meth:`Client.sim_object`."""
        return cast(JSON, await self._call(_Call("GET", "/api/sim/object")))

    async def set_sim_object(
        self, name: str | None = None, spec: Mapping[str, Any] | None = None
    ) -> JSON:
        """As :meth:`Client.set_sim_object`."""
        return cast(JSON, await self._call(_object(name, spec)))

    async def press(
        self, pad: int, x_mm: float, y_mm: float, force_n: float,
        radius_mm: float | None = None, duration_s: float | None = None,
    ) -> JSON:  # fmt: skip
        """As :meth:`Client.press`."""
        return cast(JSON, await self._call(_press(pad, x_mm, y_mm, force_n, radius_mm, duration_s)))

    async def release_press(self) -> JSON:
        """As :meth:`Client.release_press`."""
        return cast(JSON, await self._call(_RELEASE_PRESS))

    # the 3-D view
    async def show_replay(self, run_id: int, iteration: int) -> JSON:
        """As :meth:`Client.show_replay`."""
        return cast(JSON, await self._call(_replay(run_id, iteration)))

    async def end_replay(self) -> JSON:
        """As :meth:`Client.end_replay`."""
        return cast(JSON, await self._call(_END_REPLAY))

    def telemetry(
        self, decimate: int = 1, tactile: bool = True, max_queue: int | None = None
    ) -> AsyncTelemetry:
        """As :meth:`Client.telemetry`: ``async with client.telemetry() as tm: async for msg in
        tm: …`` (see :class:`AsyncTelemetry`)."""
        url = _ws_url(self.url, decimate, tactile, max_queue)
        tm = AsyncTelemetry(url, _headers(self.token), self.timeout, self._telemetry.discard)
        self._telemetry.add(tm)
        return tm
