"""Live viser 3-D view of the hand: pose, tactile pads, contacts A and B, friction cones, object
(in simulation the true outline) and the object as the recognition reconstructed it.

The view consumes the telemetry messages of docs/api.md (``sample``, ``tactile``, ``pose``,
``sim``, ``status``/``hello``), typed (:mod:`sdh2svc.service.telemetry`) or in their JSON form.
:meth:`Viewer.handle` only stores the latest message of each type; a render task on the
service's event loop turns the changes into one ``server.atomic()`` batch at most ``max_hz``
times a second, and only when something changed, so telemetry at loop rate never costs more than
a dictionary store. A frame is cheap because it is incremental: only the fingers
whose joints moved are posed again, only pads whose counts changed are recoloured, and a scene
property is sent only when its value differs from the one last sent (every assignment is a
message that viser's thread encodes and sends, holding the GIL the control loop needs). Nobody
watching, nothing is drawn: the changes wait, and a browser that connects gets the latest state.
While the dashboard replays a recorded run, :attr:`Viewer.replay`
(:mod:`sdh2svc.service.replay_feed`) puts the iteration it shows in the place of the live
messages, and the panel says so.

Geometry. The scene is frame 0 of hand-model.md §2 (origin at Finger 1's proximal joint O, y0
towards Finger 2, z0 along the straightened finger; x0 completes a right-handed frame and points
towards the thumb), in metres (the model's millimetres × 1e-3). Fingers 1 and 2 are posed with
the model's own functions (:func:`distal_joint`, :func:`frame3_axes`, :func:`pad_point`), so at
φ1 = 90° they lie exactly in the y0z0 plane of the planar model. The bodies and pads drawn are
the hand's URDF (:mod:`sdh2svc.model.urdf`, through viser's URDF support), posed with the same
angles; the thumb's place, the palm, the link bodies and the proximal pads are approximate (see
:data:`THUMB_BASE` and :func:`proximal_cells`).

Authority. The panel cannot authenticate anyone. ``read_only`` (the service has a token): every
control but E-STOP is disabled, its hint pointing to the dashboard, and the panel says so
(:data:`READ_ONLY_NOTE`: viser shows no hint on a disabled control). Open hand is enabled only
while the latest status shows no run, no e-stop latched and no opening under way. viser does not
enforce ``disabled`` (a client can send a disabled button's click), so every callback checks,
in our code, the kind's permission now and its control's state before anything reaches
``on_command`` (:meth:`Viewer._gate`); a refusal is logged and shown in the panel. And the
WebSocket refuses pages of other sites (:func:`start_viser`).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import math
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any, TypeVar

import numpy as np
import viser
import websockets.asyncio.server
import yourdfpy  # type: ignore[import-untyped]
from viser.extras import ViserUrdf
from websockets.asyncio.server import ServerConnection
from websockets.http11 import Request

from sdh2svc.config import Settings
from sdh2svc.hosts import accepted_hosts, origin_key
from sdh2svc.model.geometry import pad_point_from_L, pad_slope, pad_y3
from sdh2svc.model.kinematics import Finger, Point, distal_joint, frame3_axes, pad_point
from sdh2svc.model.urdf import (
    KNUCKLE_MM,
    PROXIMAL_PAD_Y_MM,
    PROXIMAL_ROW0_FROM_DISTAL_MM,
    joint_names,
    sdh2_urdf,
)
from sdh2svc.service.pacing import paced
from sdh2svc.service.replay_feed import ReplayFeed
from sdh2svc.service.telemetry import AnyMessage, SampleMsg, SampleView, as_array, sample_view

_T = TypeVar("_T")
log = logging.getLogger(__name__)

Command = Callable[[str, dict[str, Any]], Awaitable[None]]

MM = 1e-3  # scene units are metres, the model's millimetres
_Z = np.array([0.0, 0.0, 1.0])

# Where the thumb's proximal joint sits, as a fraction of the base offset d = 66 mm. SCHUNK's
# URDF (ipa320/schunk_modular_robotics, schunk_description/urdf/sdh/sdh.urdf.xacro) puts the
# knuckles at (19.05, ±33, 74.5) mm and the thumb at (−38.11, 0, 74.5) mm in the palm frame, the
# proximal joints 16.5 mm above them: an equilateral triangle of side d (SDHLibrary's `d`). In
# frame 0 the thumb is therefore at x0 = d·√3/2, y0 = d/2, closing towards −x0. Approximate:
# the view only needs it parked out of the way.
THUMB_BASE = (math.sqrt(3.0) / 2.0, 0.5)

TILE_GAP = 0.9  # a cell tile covers this fraction of the pitch, so the grid stays readable
CONE_HEIGHT_MM = 20.0
CONTACT_RADIUS_MM = 2.5

GREEN = (40, 200, 70)
YELLOW = (230, 190, 40)
RED = (230, 40, 40)
OUTLINE_HELD = (255, 150, 40)
OUTLINE_DROPPED = (230, 40, 40)
OUTLINE_RELEASED = (150, 150, 150)  # fell as the fingers let go (a run's end, Open hand): no drop
LETTING_GO = ("releasing", "done", "stopped")  # a run's states whose fingers open on purpose
ESTIMATE = (40, 190, 235)  # the reconstructed outline (recognition), over the true one

# Raw counts → colour: dark (unloaded) → blue → cyan → yellow → red at full scale.
_CMAP_T = np.array([0.0, 0.05, 0.3, 0.6, 1.0])
_CMAP_RGB = np.array(
    [[70, 70, 80], [30, 60, 200], [20, 200, 220], [250, 220, 30], [230, 30, 30]], dtype=float
)
FULL_SCALE_COUNTS = 4095.0

DARK = (90, 92, 100)
# A blue, B red, as the dashboard's sketch and plots draw them (web/sketch.js), each labelled
COLOR_A, COLOR_B = (31, 119, 180), (214, 39, 40)

COMMANDS = ("start", "stop", "open", "estop", "release")
BUTTONS: dict[str, tuple[str, Any, str | None]] = {  # kind: (label, colour, hint when enabled)
    "start": ("Grasp & roll", "green", None),
    "stop": ("Stop", "orange", None),
    "open": ("Open hand", "blue", "open the fingers to the pre-shape, releasing what they hold"),
    "estop": ("E-STOP", "red", None),
    "release": ("Release e-stop", "gray", None),
}
KINDS = frozenset({*COMMANDS, "params"})  # what the panel may ask of on_command
ALWAYS_ALLOWED = frozenset({"estop"})  # stopping is always allowed, token or not
NEEDS_TOKEN = "needs the API token: use the dashboard"
# said in the panel itself: a disabled control's hint never shows (no tooltip on a disabled
# button or slider in viser's client), so a greyed panel would not say why
READ_ONLY_NOTE = ("*Read-only view* (the service has an API token): only E-STOP acts here; "
                  "the other controls are on the dashboard, with the token.")  # fmt: skip
SLIDERS: dict[str, tuple[str, float, float, float]] = {  # field: (label, min, max, step)
    "delta_phi_deg": ("Δφ (°)", -5.0, 5.0, 0.05),
    "k": ("k", 1.05, 10.0, 0.05),
    "lambda_gain": ("λ", 0.0, 50.0, 0.5),
    "alpha_deg": ("α (°)", 1.0, 59.5, 0.5),
}
_PAYLOAD = {  # message type → the field carrying its payload (docs/api.md)
    "sample": "sample",
    "pose": "angles_deg",
    "tactile": "matrices",
    "sim": "truth",
    "status": "status",
    "hello": "status",
}
EDIT_GRACE_S = 1.5  # a slider the user just moved is not reset by a status still in flight
# a slider's value is sent once it has rested this long: viser's client reports every step of a
# drag (one drag of α: 20 changes, each logged, and in a run each applied and recorded); the
# dashboard applies a parameter once too
SETTLE_S = 0.3
NOTE_S = 10.0  # a refusal shown in the panel goes after this (not left for the next visitor)
FINISHED = {"done", "stopped", "faulted", "e-stopped"}  # a run's ends ("idle": it just began)


# --- pure geometry, shared by the renderer and the tests --------------------------------------


@dataclass(frozen=True, slots=True)
class _FingerSpec:
    """How one finger's planar model (y, z) maps into frame 0: P = base + s·(y − y_O)·d + z·ẑ."""

    model: Finger  # whose planar formulas (mirror or not) the finger follows
    base: np.ndarray  # proximal joint, frame 0, mm
    d: np.ndarray  # closing direction (unit, horizontal)
    s: float  # +1: model y grows along d; −1: Finger 2's mirror
    y_O: float  # model y of this finger's proximal joint

    def point(self, p: Point) -> np.ndarray:
        return self.base + self.s * (p.y - self.y_O) * self.d + p.z * _Z

    def vector(self, v: Point) -> np.ndarray:
        return self.s * v.y * self.d + v.z * _Z


def _specs(phi1: float, base_mm: float) -> dict[str, _FingerSpec]:
    """Fingers 1, 2 rotate with φ1 about the palm normal: at 90° both close within y0z0."""
    c, s = math.cos(phi1), math.sin(phi1)
    tx, ty = THUMB_BASE
    return {
        "f1": _FingerSpec(Finger.ONE, np.zeros(3), np.array([c, s, 0.0]), 1.0, 0.0),
        "f2": _FingerSpec(
            Finger.TWO, np.array([0.0, base_mm, 0.0]), np.array([c, -s, 0.0]), -1.0, base_mm
        ),
        "f3": _FingerSpec(
            Finger.ONE, np.array([tx * base_mm, ty * base_mm, 0.0]), np.array([-1.0, 0, 0]), 1, 0
        ),
    }


def _transform(origin: np.ndarray, ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """4×4 pose with x along ``ex``, y along ``ey`` (orthonormal), z = x × y."""
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = ex, ey, np.cross(ex, ey), origin
    return T


def finger_frames(
    angles_deg: Sequence[float], settings: Settings, fingers: Sequence[str] = ("f1", "f2", "f3")
) -> dict[str, np.ndarray]:
    """Link frames of the three fingers, frame 0, mm, for the 7 wire-axis angles.

    Keys ``/fN/base`` (knuckle, x up), ``/fN/proximal`` (at the proximal joint),
    ``/fN/distal`` (frame 3 at C/D: x = ex3, y = ey3 towards the pad) and ``/fN/tip`` (the pad's
    end at the fingertip) for N = 1, 2, 3 (3 = thumb) of those in ``fingers``. Each is a 4×4
    homogeneous transform.
    """
    ax, geom = settings.axes, settings.hand
    a = [math.radians(v) for v in angles_deg]
    joints = {
        "f1": (a[ax.phi2], a[ax.phi3]),
        "f2": (a[ax.phi4], a[ax.phi5]),
        "f3": (a[ax.thumb_proximal], a[ax.thumb_distal]),
    }
    tip_x3 = geom.pad.tip_end_x3_mm
    tip_y3 = pad_y3(tip_x3, geom.pad)
    d = geom.base_offset_mm
    out = {}
    for key, spec in _specs(a[ax.phi1], d).items():
        if key not in fingers:
            continue
        prox, dist = joints[key]
        f = spec.model
        out[f"/{key}/base"] = _transform(spec.base - KNUCKLE_MM * _Z, _Z, spec.d)
        ex2, ey2 = frame3_axes(f, prox)  # the proximal link: the same axes with ψ = proximal
        out[f"/{key}/proximal"] = _transform(spec.base, spec.vector(ex2), spec.vector(ey2))
        ex3, ey3 = frame3_axes(f, prox + dist)
        C = spec.point(distal_joint(f, prox, geom))
        out[f"/{key}/distal"] = _transform(C, spec.vector(ex3), spec.vector(ey3))
        tip = spec.point(pad_point(f, prox, dist, tip_x3, tip_y3, geom))
        out[f"/{key}/tip"] = _transform(tip, spec.vector(ex3), spec.vector(ey3))
    return out


def _rot_z(beta: float) -> tuple[float, float, float, float]:
    return (math.cos(beta / 2.0), 0.0, 0.0, math.sin(beta / 2.0))


def distal_cells(settings: Settings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (frame 3, mm), orientations (wxyz, tile normal +y → pad normal) and the row-major
    flat indices of the distal pad's real cells (the configured mask).

    Row r's centre lies where the contact estimate would put a centroid at S = r·pitch
    (calibration.distance: L = 49.5 − S·44/40.8 by default), so a single loaded cell and the
    contact point A computed from it coincide. Column c runs across the pad along z3.
    """
    lay, pitch, pad = settings.tactile.distal, settings.tactile.texel_pitch_mm, settings.hand.pad
    s_range = pitch * (lay.rows - 1)
    pos, rot = [], []
    for r in range(lay.rows):
        L = settings.calibration.distance.L_from_S(r * pitch, s_range, pad)
        x3, y3 = pad_point_from_L(L, pad)
        beta = math.atan(pad_slope(x3, pad))  # the tangent's angle from ex3
        n = (-math.sin(beta), math.cos(beta))  # outward normal
        for c in range(lay.cols):
            z = (c - (lay.cols - 1) / 2.0) * pitch
            pos.append((x3 + 0.3 * n[0], y3 + 0.3 * n[1], z))  # just above the surface
            rot.append(_rot_z(beta))
    idx = np.flatnonzero(lay.valid().ravel())
    return np.array(pos)[idx], np.array(rot)[idx], idx


def proximal_cells(settings: Settings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """As :func:`distal_cells` for the proximal pad, in the proximal link frame (mm). The model
    has no proximal pad geometry: a flat pad PROXIMAL_PAD_Y_MM from the link axis, row 0 (at the
    distal joint) PROXIMAL_ROW0_FROM_DISTAL_MM below it, rows a pitch apart (approximate)."""
    lay, pitch = settings.tactile.proximal, settings.tactile.texel_pitch_mm
    x0 = settings.hand.proximal_length_mm - PROXIMAL_ROW0_FROM_DISTAL_MM
    pos = [
        (x0 - r * pitch, PROXIMAL_PAD_Y_MM + 0.3, (c - (lay.cols - 1) / 2.0) * pitch)
        for r in range(lay.rows)
        for c in range(lay.cols)
    ]
    idx = np.flatnonzero(lay.valid().ravel())
    rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (len(idx), 1))
    return np.array(pos)[idx], rot, idx


def tactile_colors(counts: np.ndarray) -> np.ndarray:
    """Raw 12-bit counts → RGB (uint8, shape + (3,)); square-root scale so light touches show."""
    t = np.sqrt(np.clip(np.asarray(counts, dtype=float) / FULL_SCALE_COUNTS, 0.0, 1.0))
    rgb = [np.interp(t, _CMAP_T, _CMAP_RGB[:, i]) for i in range(3)]
    return np.stack(rgb, axis=-1).astype(np.uint8)


def cone_color(deviation_deg: float, alpha_deg: float) -> tuple[int, int, int]:
    """Green when AB lies along the pad normal (deviation 0), through yellow, red at the cone's
    edge (deviation ≥ α). The deviation is |ω − 90°| for the samples' ω (measured from the
    pad tangent, hand-model §6)."""
    r = min(1.0, max(0.0, abs(deviation_deg) / alpha_deg)) if alpha_deg > 0 else 1.0
    lo, hi, t = (GREEN, YELLOW, 2.0 * r) if r < 0.5 else (YELLOW, RED, 2.0 * r - 1.0)
    return tuple(round(a + (b - a) * t) for a, b in zip(lo, hi, strict=True))  # type: ignore[return-value]


def _cone_mesh(segments: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit cone: apex at the origin, axis +z, base circle of radius 1 at z = 1."""
    ang = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    rim = np.stack([np.cos(ang), np.sin(ang), np.ones(segments)], axis=1)
    verts = np.vstack([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], rim])
    faces = [(0, 2 + (i + 1) % segments, 2 + i) for i in range(segments)]
    faces += [(1, 2 + i, 2 + (i + 1) % segments) for i in range(segments)]
    return verts, np.array(faces, dtype=np.uint32)


def _tile_mesh(size_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A square tile in the local x–z plane (normal +y), metres."""
    h = size_mm * MM / 2.0
    v = np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]])
    return v, np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)


def _wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method; viser's SO3 is
    ~10× slower and this runs a dozen times per frame on the service's event loop)."""
    m = R.tolist()
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s)
    elif m[0][0] >= m[1][1] and m[0][0] >= m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = ((m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s)
    elif m[1][1] >= m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = ((m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = ((m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s)
    return np.array(q)


def _axis_to(n: np.ndarray) -> np.ndarray:
    """wxyz of a rotation taking +z to the unit vector ``n`` (which lies in the y0z0 plane)."""
    ex = np.array([1.0, 0.0, 0.0])
    return _wxyz(np.column_stack([ex, np.cross(n, ex), n]))


def _num(d: dict[str, Any] | None, key: str) -> float | None:
    v = (d or {}).get(key)
    return float(v) if isinstance(v, int | float) and math.isfinite(v) else None


# --- who may open the view's WebSocket ------------------------------------------------------------


class ViewerSecurityError(RuntimeError):
    """The view's WebSocket could not be guarded: the view is not served."""


def origin_allowed(origin: str, settings: Settings, view_port: int) -> bool:
    """Whether a browser page of ``origin`` may open the view's WebSocket on ``view_port``.

    Allowed: http(s) on a loopback name, ``service.host`` or a ``service.allowed_hosts`` name,
    at the view's own port or the dashboard's (``service.port``, unless 0: unknown); an
    ``allowed_hosts`` entry with a port, at that port; and every ``service.allowed_origins``
    entry — the guard's rules, in :mod:`sdh2svc.hosts`'s spelling. Everything else is a page
    of some other site."""
    key = origin_key(origin)
    if key is None or key[0] not in ("http", "https"):
        return False
    svc = settings.service
    if key in {origin_key(o) for o in svc.allowed_origins}:
        return True
    names, exact = accepted_hosts(svc.host, svc.allowed_hosts)
    return (key[1] in names and key[2] in {view_port, svc.port} - {0}) or key[1:] in exact


def frame_ancestors(settings: Settings) -> str:
    """The pages that may frame the view (a CSP ``frame-ancestors`` list): the view's own and
    the dashboard's, at the names :func:`origin_allowed` allows (IPv6 literals cannot be named
    in CSP), and every ``service.allowed_origins`` entry."""
    svc = settings.service
    port = str(svc.port) if svc.port else "*"
    names, exact = accepted_hosts(svc.host, svc.allowed_hosts)
    at = [(name, port) for name in names] + [(name, str(p)) for name, p in exact]
    pages = [f"{scheme}://{name}:{p}" for name, p in at if not name.startswith("[")
             for scheme in ("http", "https")]  # fmt: skip
    return " ".join(["'self'", *pages, *svc.allowed_origins])


OriginCheck = Callable[[str, int], bool]  # (Origin header, the port it reached) → allowed?


def _checking_origin(inner: Any, allowed: OriginCheck, ancestors: str | None) -> Callable[..., Any]:
    """viser's ``process_request`` behind an Origin check of WebSocket handshakes (403); its
    pages may be framed only by ``ancestors`` (None: by anyone).

    Why both: a page of another site that framed the view would open the WebSocket with the
    view's own Origin, and a click it lured into the frame would drive the hand."""

    def process_request(connection: ServerConnection, request: Request) -> Any:
        if "websocket" in request.headers.get("Upgrade", "").lower():
            origins = request.headers.get_all("Origin")
            port = int(connection.local_address[1])
            if origins and (len(origins) > 1 or not allowed(origins[0], port)):
                log.warning("3-D view: WebSocket from origin %r refused (service.allowed_hosts, "
                            "service.allowed_origins)", ", ".join(origins))  # fmt: skip
                return connection.respond(HTTPStatus.FORBIDDEN, "Origin not allowed\n")
        response = inner(connection, request) if inner is not None else None
        if response is not None and ancestors is not None:
            response.headers["Content-Security-Policy"] = f"frame-ancestors {ancestors}"
        return response

    return process_request


class _GuardedServe(websockets.asyncio.server.serve):
    """``websockets.asyncio.server.serve`` that puts :func:`_checking_origin` in front of viser's
    ``process_request``; other servers pass through unchanged. See :func:`start_viser`."""

    check: OriginCheck | None = None  # set, under _SERVE_LOCK, while a ViserServer starts
    ancestors: str | None = None
    installed = False

    def __init__(self, handler: Any, *args: Any, **kwargs: Any) -> None:
        check = _GuardedServe.check
        if check is not None and getattr(handler, "__module__", None) == "viser.infra._infra":
            kwargs["process_request"] = _checking_origin(kwargs.get("process_request"), check,
                                                         _GuardedServe.ancestors)  # fmt: skip
            _GuardedServe.installed = True
        super().__init__(handler, *args, **kwargs)


_SERVE_LOCK = threading.Lock()


def start_viser(
    host: str, port: int, allowed: OriginCheck, ancestors: str | None = None
) -> viser.ViserServer:
    """``viser.ViserServer(host, port)`` whose WebSocket refuses a handshake carrying a foreign
    ``Origin`` with 403, and whose pages only ``ancestors`` may frame (a CSP ``frame-ancestors``
    list; None: anyone) (blocking: call it on a worker thread).

    Why: WebSockets are not covered by the same-origin policy or CORS, so without this any web
    page a person on the lab PC opens could connect to ws://127.0.0.1:8080 and click the panel's
    buttons (cross-site WebSocket hijacking, and DNS rebinding onto the view's port). A missing
    Origin (a script, not a browser) is let through: browsers always send one.

    How, tied to viser 1.1.1: viser has no hook for its handshake. Its server thread calls
    ``websockets.asyncio.server.serve(ws_handler, …, process_request=viser_http_server)``
    (viser/infra/_infra.py, ``start_server()``), looked up on the module at call time, and
    ``ViserServer()`` returns only once that server listens. So, while one is constructed (one
    at a time), that name is :class:`_GuardedServe`, which wraps viser's ``process_request``
    (recognised by its handler's module) in the check; restored right after. Should another viser
    version serve differently, the check is not installed and the view is refused here, not
    served unguarded (the tests say so at once).
    """
    ws_server = websockets.asyncio.server
    with _SERVE_LOCK:
        original = ws_server.serve
        ws_server.serve = _GuardedServe  # type: ignore[misc]
        _GuardedServe.check, _GuardedServe.installed = allowed, False
        _GuardedServe.ancestors = ancestors
        try:
            server = _quietly(viser.ViserServer, host=host, port=port, verbose=False)
        finally:
            ws_server.serve = original  # type: ignore[misc]
            _GuardedServe.check, _GuardedServe.ancestors = None, None
        installed = _GuardedServe.installed
    if not installed:
        _quietly(server.stop)
        raise ViewerSecurityError(
            f"viser {viser.__version__} does not serve its WebSocket as viser 1.1.1 does: the "
            "3-D view's Origin check could not be installed, so the view is not served "
            "(sdh2svc.service.viewer.start_viser)"
        )
    return server


# --- the view ----------------------------------------------------------------------------------


class Viewer:
    """The viser server, its scene and GUI panel, and the render task (see the module doc)."""

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
        self._read_only = read_only  # a token is set: the panel only stops (see _refusal)
        self._period = 1.0 / max_hz
        self._latest: dict[str, Any] = {}  # type → latest payload
        self._seq: dict[str, int] = {}  # type → arrival number (pose vs sample: newer wins)
        self._n = 0
        self._dirty: set[str] = set()
        self._wake = asyncio.Event()
        self._angles = [float(v) for v in settings.run.preshape_deg]
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self.server: viser.ViserServer | None = None
        self.frames = 0  # renders done (tests, diagnostics)
        self.nodes: dict[str, Any] = {}  # scene handles by name
        self.buttons: dict[str, viser.GuiButtonHandle] = {}
        self.sliders: dict[str, Any] = {}
        self._edited: dict[str, float] = {}
        self._settling: dict[str, tuple[float, asyncio.TimerHandle]] = {}  # field → value, timer
        self._tasks: set[asyncio.Future[None]] = set()  # commands under way (kept referenced)
        self._fell = self._released = False  # the sim's object: fell, and as the fingers opened
        self._applied = {f: float(getattr(settings.rolling, f)) for f in SLIDERS}  # last known
        self._sync_thread: int | None = None
        self._note, self._note_at = "", 0.0
        self._tactile_idx: dict[str, np.ndarray] = {}
        self._failures = 0
        self._sent: dict[tuple[int, str], Any] = {}  # (node id, property) → value last sent
        self._posed: dict[str, tuple[float, ...]] = {}  # finger → the angles it was posed at
        self._pad_counts: dict[str, np.ndarray] = {}  # pad node → the counts it was coloured for
        self._view: tuple[int, SampleView | None] = (-1, None)  # (sample's seq, its view)
        self.urdf: ViserUrdf | None = None
        self._urdf_axes: list[int] = []  # the wire axis of each of the URDF's actuated joints
        self.replay = ReplayFeed(self._keep)  # a recorded iteration instead of the live state

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the viser server (port 0: any free port), build the scene, start rendering."""
        self._loop = asyncio.get_running_loop()
        # The server's constructor waits for its thread: keep the event loop free meanwhile.
        settings = self.settings

        def allowed(origin: str, port: int) -> bool:
            return origin_allowed(origin, settings, port)

        # read-only (a token): the panel only stops, and the dashboard that frames it may be
        # at any name the lab's network gives the PC: framing it lures no one into driving
        ancestors = None if self._read_only else frame_ancestors(settings)
        self.server = await asyncio.to_thread(start_viser, self._host, self._port, allowed,
                                              ancestors)  # fmt: skip
        self._build_scene()
        self._build_gui()
        self._dirty |= {"pose", "status"}
        self.server.on_client_connect(self._on_watcher)
        self._wake.set()
        self._task = asyncio.create_task(self._render_loop(), name="viewer-render")

    def _on_watcher(self, _client: Any) -> None:
        """A browser connected (viser's thread): draw what waited while nobody watched."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._wake.set)

    @property
    def watched(self) -> bool:
        return self.server is not None and bool(self.server.get_clients())

    @property
    def url(self) -> str:
        port = self.server.get_port() if self.server is not None else self._port
        return f"http://{self._host}:{port}"

    async def stop(self) -> None:
        """Stop rendering and the viser server."""
        for _, timer in self._settling.values():
            timer.cancel()
        self._settling.clear()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self.server is not None:
            server, self.server = self.server, None
            await asyncio.to_thread(_quietly, server.stop)

    # -- telemetry in: cheap ----------------------------------------------------------------

    def handle(self, msg: AnyMessage) -> None:
        """Keep the latest message of each type and mark it for the next frame; no rendering
        (while a replay is shown, through :attr:`replay`)."""
        self.replay.live(msg)

    def _keep(self, msg: AnyMessage) -> None:
        if isinstance(msg, dict):
            kind, key = msg.get("type"), _PAYLOAD.get(str(msg.get("type")))
            payload = msg.get(key) if key is not None else None
        else:
            kind, key = msg.type, _PAYLOAD.get(msg.type)
            payload = getattr(msg, key) if key is not None else None
            if isinstance(msg, SampleMsg) and msg.view is not None:
                payload = msg.view  # what the sender made of the sample: drawn as given
        if key is None:
            return
        kind = "status" if kind == "hello" else str(kind)
        self._latest[kind] = payload
        self._n += 1
        self._seq[kind] = self._n
        self._dirty.add(kind)
        self._wake.set()

    # -- rendering ---------------------------------------------------------------------------

    async def _render_loop(self) -> None:
        """Draw on delivery, at most ``max_hz`` (see :func:`paced`)."""
        await paced(self._wake, self._period, self._frame)

    async def _frame(self) -> bool:
        self.render()
        return True

    def render(self) -> None:
        """Apply what changed since the last frame, as one atomic batch (nobody watching: keep
        the changes for when someone does)."""
        if self.server is None or not self._dirty or not self.watched:
            return
        dirty, self._dirty = self._dirty, set()
        parts = [
            ({"pose", "sample"}, self._render_hand),
            ({"sample", "status"}, self._render_contacts),
            ({"sample", "status"}, self._render_estimate),
            ({"tactile"}, self._render_pads),
            ({"sim"}, self._render_truth),
            ({"status"}, self._render_status),
        ]
        with self.server.atomic():
            for kinds, part in parts:
                if dirty & kinds:
                    self._guarded(part)
        self.frames += 1

    def _guarded(self, part: Callable[[], None]) -> None:
        """One part of a frame; a malformed message spoils that part only, and logs rarely."""
        try:
            part()
        except Exception:
            self._failures += 1
            if self._failures in (1, 10, 100) or self._failures % 1000 == 0:
                log.exception("3-D view: %s failed (%d times)", part.__name__, self._failures)

    def _update_angles(self) -> None:
        """φ1 and the thumb from ``pose``; φ2…φ5 from whichever of pose/sample came last."""
        pose, sample = self._latest.get("pose"), self._sample_view()
        ax = self.settings.axes
        steps: list[tuple[str, Any]] = [("pose", pose), ("sample", sample)]
        steps.sort(key=lambda s: self._seq.get(s[0], 0))
        for kind, data in steps:
            if kind == "pose" and isinstance(data, list | tuple):
                if len(data) == len(self._angles):
                    self._angles = [float(v) for v in data]
            elif kind == "sample" and data is not None:
                for axis, v in zip((ax.phi2, ax.phi3, ax.phi4, ax.phi5), data.phi_deg, strict=True):
                    if v is not None:
                        self._angles[axis] = v

    def _sample_view(self) -> SampleView | None:
        """The latest sample as drawn: as its sender made it, or made here once per sample."""
        seq, s = self._seq.get("sample", 0), self._latest.get("sample")
        if self._view[0] != seq:
            view: SampleView | None = None
            if isinstance(s, SampleView):
                view = s
            elif s is not None:
                with contextlib.suppress(Exception):  # a malformed sample: nothing to draw
                    view = sample_view(s, self.settings.hand)
            self._view = (seq, view)
        return self._view[1]

    def _set(self, node: Any, prop: str, value: Any) -> None:
        """Assign a scene property only if it differs from what was last sent."""
        key = (id(node), prop)
        last = self._sent.get(key)
        if isinstance(value, np.ndarray):
            if isinstance(last, np.ndarray) and np.array_equal(last, value):
                return
        elif last == value and key in self._sent:
            return
        self._sent[key] = value
        setattr(node, prop, value)

    def _render_hand(self) -> None:
        """Pose the fingers whose joints (or φ1) moved since they were last posed."""
        self._update_angles()
        ax, a = self.settings.axes, self._angles
        joints = {"f1": (ax.phi2, ax.phi3), "f2": (ax.phi4, ax.phi5),
                  "f3": (ax.thumb_proximal, ax.thumb_distal)}  # fmt: skip
        moved = []
        for f, (p, d) in joints.items():
            key = (a[ax.phi1], a[p], a[d])
            if self._posed.get(f) != key:
                self._posed[f] = key
                moved.append(f)
        if not moved:
            return
        if self.urdf is not None:  # the bodies: every joint of the URDF (a few dozen frames)
            self.urdf.update_cfg(np.radians([a[i] for i in self._urdf_axes]))
        for name, T in finger_frames(a, self.settings, moved).items():
            node = self.nodes.get(name)
            if node is not None:
                self._set(node, "position", np.round(T[:3, 3] * MM, 7))
                self._set(node, "wxyz", np.round(_wxyz(T[:3, :3]), 7))

    def _alpha_deg(self) -> float:
        params = (self._latest.get("status") or {}).get("params") or {}
        return _num(params, "alpha_deg") or self.settings.rolling.alpha_deg

    def _contact_sample(self) -> SampleView | None:
        """The latest sample, unless a newer status says no run is rolling: a finished run's
        contacts would otherwise linger through the release and the next grasp, and a replay's
        once it ends on a service that has had no run (``run`` null: no live sample to put
        back in its place)."""
        status = self._latest.get("status") or {}
        run = status.get("run") or {}
        newer = self._seq.get("status", 0) > self._seq.get("sample", 0)
        no_run = "run" in status and not status["run"]
        idle = no_run or run.get("state") not in (None, "rolling")
        if newer and not status.get("replay") and idle:
            return None
        return self._sample_view()

    def _render_contacts(self) -> None:
        s = self._contact_sample()
        # the cones the controller checks: as wide as the sample says the run has widened them
        alpha = s.alpha_deg if s is not None and s.alpha_deg else self._alpha_deg()
        contacts = {"A": s.A if s else None, "B": s.B if s else None}
        for label, c in contacts.items():
            sphere, cone = self.nodes[f"/contacts/{label}"], self.nodes[f"/contacts/cone_{label}"]
            self._set(sphere, "visible", c is not None)
            if c is None or c.normal is None:
                self._set(cone, "visible", False)
                continue
            at = (0.0, c.at.y * MM, c.at.z * MM)
            self._set(sphere, "position", at)
            n, w = c.normal, c.omega_deg
            r = CONE_HEIGHT_MM * math.tan(math.radians(alpha)) * MM
            self._set(cone, "position", at)
            self._set(cone, "wxyz", _axis_to(np.array([0.0, n.y, n.z])))
            self._set(cone, "scale", (r, r, CONE_HEIGHT_MM * MM))
            color = cone_color(abs(w - 90.0), alpha) if w is not None else (150, 150, 150)
            self._set(cone, "color", color)
            self._set(cone, "visible", True)
        A, B = contacts["A"], contacts["B"]
        seg = self.nodes["/contacts/AB"]
        self._set(seg, "visible", A is not None and B is not None)
        if A is not None and B is not None:
            self._set(
                seg, "points", np.array([[[0.0, A.at.y, A.at.z], [0.0, B.at.y, B.at.z]]]) * MM
            )

    def _render_estimate(self) -> None:
        """The object as the recognition reconstructed it (the sample's, made by
        :func:`~sdh2svc.service.telemetry.estimate_outline`); hidden without a class, and when
        the contacts are (no run rolling)."""
        s = self._contact_sample()
        node = self.nodes["/object/estimate"]
        pts = np.asarray(s.estimate if s is not None else (), dtype=float)
        if pts.ndim != 2 or pts.shape[0] < 2 or pts.shape[1] != 2:
            self._set(node, "visible", False)
            return
        p3 = np.column_stack([np.zeros(len(pts)), pts]) * MM
        self._set(node, "points", np.stack([p3, np.roll(p3, -1, axis=0)], axis=1))
        self._set(node, "visible", True)

    def _render_pads(self) -> None:
        mats = self._latest.get("tactile")
        if not isinstance(mats, list | tuple):
            return
        for name, index in self._pad_matrices().items():
            if index >= len(mats):
                continue
            counts, last = as_array(mats[index]), self._pad_counts.get(name)
            if last is not None and np.array_equal(last, counts):
                continue  # the same counts as drawn (idle pads: most of them)
            self._pad_counts[name] = counts
            flat = self._tactile_idx[name]
            lay = self._layout(name)
            if counts.shape != (lay.rows, lay.cols):
                continue  # a malformed frame: keep the last colours
            self.nodes[name].batched_colors = tactile_colors(counts.ravel()[flat])

    def _render_truth(self) -> None:
        truth = self._latest.get("sim") or {}
        node = self.nodes["/object/outline"]
        outline = np.asarray(truth.get("outline") or [], dtype=float)
        if outline.ndim != 2 or outline.shape[0] < 2 or outline.shape[1] != 2:
            self._set(node, "visible", False)
            return
        p3 = np.column_stack([np.zeros(len(outline)), outline]) * MM
        self._set(node, "points", np.stack([p3, np.roll(p3, -1, axis=0)], axis=1))
        self._set(node, "colors", np.array(self._outline_color(truth), dtype=np.uint8))
        self._set(node, "visible", True)

    def _outline_color(self, truth: dict[str, Any]) -> tuple[int, int, int]:
        """Held; dropped (red); or released (grey): the sim's object falls when the fingers open
        on purpose as when it slips out, its truth saying ``dropped`` both times. As on the
        dashboard (web/app.js, ``withFate``): whether the fingers were letting go when it first
        fell tells which, until it is held again. A replayed iteration is mid-roll: a drop."""
        status = self._latest.get("status") or {}
        dropped = bool(truth.get("dropped"))
        if dropped and not self._fell:
            run, hand = status.get("run") or {}, status.get("hand") or {}
            self._released = run.get("state") in LETTING_GO or bool(hand.get("opening"))
        self._fell = dropped
        if not dropped:
            return OUTLINE_HELD
        return OUTLINE_RELEASED if self._released and not status.get("replay") else OUTLINE_DROPPED

    def _render_status(self) -> None:
        st = self._latest.get("status") or {}
        run = st.get("run") or {}
        state = run.get("state", "idle")
        parts = [f"**{state}**"]
        if run.get("strokes_total"):
            parts.append(f"stroke {run.get('stroke', 0)}/{run['strokes_total']}")
        if run.get("iteration") is not None and state not in FINISHED:
            parts.append(f"it {run['iteration']}")
        if st.get("estopped"):
            parts.append("**E-STOP latched**")
        if isinstance(replay := st.get("replay"), dict):  # the scene is the replay's: it leads,
            # and the state beside it is said to be the hand's now, not the replayed iteration's
            shown = f"replay of run {replay.get('run_id')}, it {replay.get('iteration')}"
            parts = [shown, f"live: {parts[0]}", *parts[1:]]
        if self._note and time.monotonic() - self._note_at > NOTE_S:
            self._note = ""
        text = " · ".join(parts)
        if self._read_only or st.get("auth_required"):
            text += f"\n\n{READ_ONLY_NOTE}"
        text += f"\n\n{self._note}" if self._note else ""
        self._set(self.nodes["gui/state"], "content", text)
        self._sync_sliders(st.get("params") or {})
        self._sync_controls()

    def _sync_controls(self) -> None:
        """Disable what the panel may not do now, the hint saying why (the callbacks check it
        again: viser does not enforce ``disabled``)."""
        for kind, button in self.buttons.items():
            why = self._refusal(kind)
            self._set(button, "disabled", why is not None)
            self._set(button, "hint", why if why is not None else BUTTONS[kind][2])
        why = self._refusal("params")
        for slider in self.sliders.values():
            self._set(slider, "disabled", why is not None)
            self._set(slider, "hint", why)

    def _sync_sliders(self, params: dict[str, Any]) -> None:
        """Follow the applied parameters, except a slider the user is moving right now (a
        refused move is no edit: that slider goes back)."""
        now = time.monotonic()
        self._sync_thread = threading.get_ident()  # our own assignments are not user edits
        try:
            for field, slider in self.sliders.items():
                v = _num(params, field)
                if v is not None:
                    self._applied[field] = v
                v = self._applied.get(field)
                if v is not None and now - self._edited.get(field, -math.inf) > EDIT_GRACE_S:
                    slider.value = v
        finally:
            self._sync_thread = None

    # -- GUI → commands (viser calls these on its own threads) -------------------------------

    def _refusal(self, kind: str) -> str | None:
        """Why the panel may not do ``kind`` now; None: it may. With a token (ours, or the
        service's status says one is set) only the e-stop: the view cannot authenticate.
        Otherwise as the dashboard: the others need a known status; Grasp & roll and Open hand
        no run, no e-stop latched and no opening under way; Stop a run or an opening to stop;
        Release a latched e-stop. Read on viser's threads too (dictionary reads)."""
        if kind not in KINDS:
            return "not a control of this panel"
        if kind in ALWAYS_ALLOWED:
            return None
        st = self._latest.get("status")
        st = st if isinstance(st, dict) else None
        if self._read_only or (st is not None and st.get("auth_required")):
            return NEEDS_TOKEN
        if kind == "params":
            return None
        if st is None:
            return "waiting for the service's status"
        run, hand = st.get("run") or {}, st.get("hand") or {}
        running = not isinstance(run, dict) or (bool(run) and run.get("state") not in FINISHED)
        opening = not isinstance(hand, dict) or bool(hand.get("opening"))
        if kind == "release":
            return None if st.get("estopped") else "the e-stop is not latched"
        if kind == "stop":
            return None if running or opening else "no run is active"
        if st.get("estopped"):
            return "the e-stop is latched: release it first"
        if running:
            return "a run is running: stop it first"
        return "the hand is opening" if opening else None

    def _gate(self, kind: str, handle: Any) -> bool:
        """Whether a click or a slider's move may become a command (viser's threads).

        viser does not enforce ``disabled`` server-side: a client can send the update of a
        disabled control, and it reaches the callbacks. So every callback asks here first: the
        kind's permission now (:meth:`_refusal`) and the control's own state as we last set it
        (anything but ``disabled == False``, e.g. props a client's update replaced: refused).
        A refusal is logged and shown in the panel; nothing goes to ``on_command``."""
        why = self._refusal(kind)
        if why is None:
            try:
                disabled = handle.disabled is not False
            except Exception:
                disabled = True
            why = "disabled in this panel" if disabled else None
        if why is None:
            return True
        log.warning("3-D view: %s refused in the panel (%s): not sent", kind, why)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # closed meanwhile: nobody to show it to
                loop.call_soon_threadsafe(self._show_note, f"{kind}: {why}")
        return False

    def _show_note(self, note: str) -> None:
        """A short line under the state (the last refusal; empty after a command succeeds);
        redrawing the status also puts a refused slider back to the parameter in force."""
        self._note, self._note_at = note, time.monotonic()
        self._dirty.add("status")
        self._wake.set()

    def _submit(self, kind: str, args: dict[str, Any]) -> None:
        if self._loop is None or self._loop.is_closed():
            return
        asyncio.run_coroutine_threadsafe(self._command(kind, args), self._loop)

    async def _command(self, kind: str, args: dict[str, Any]) -> None:
        """Run one command on the loop; a refusal (409, 422, …) becomes a note in the panel."""
        if self._on_command is None:
            return
        try:
            await self._on_command(kind, args)
            note = ""
        except Exception as e:
            log.warning("3-D view: %s %s refused: %s", kind, args, e)
            note = f"{kind}: {e}"
        if note != self._note:
            self._show_note(note)

    def _button_cb(self, kind: str) -> Callable[[Any], None]:
        def cb(_event: Any) -> None:
            if self._gate(kind, self.buttons[kind]):
                self._submit(kind, {})

        return cb

    def _slider_cb(self, field: str) -> Callable[[Any], None]:
        def cb(event: Any) -> None:
            if threading.get_ident() == self._sync_thread:
                return
            if not self._gate("params", self.sliders[field]):
                return
            value = float(event.target.value)
            if field == "delta_phi_deg" and value == 0.0:
                return  # Δφ's sign is the direction: 0 is not a value
            self._edited[field] = time.monotonic()
            loop = self._loop
            if loop is not None and not loop.is_closed():
                with contextlib.suppress(RuntimeError):  # closed meanwhile: nobody to apply it
                    loop.call_soon_threadsafe(self._settle, field, value)

        return cb

    def _settle(self, field: str, value: float) -> None:
        """A slider moved (on the loop): send its value once it has rested :data:`SETTLE_S`
        (a newer move restarts the wait)."""
        if (pending := self._settling.get(field)) is not None:
            pending[1].cancel()
        assert self._loop is not None
        self._settling[field] = (value, self._loop.call_later(SETTLE_S, self._settled, field))

    def _settled(self, field: str) -> None:
        value, _ = self._settling.pop(field)
        if (why := self._refusal("params")) is not None:  # refused meanwhile (e.g. a token)
            self._show_note(f"params: {why}")
            return
        self._loop_task(self._command("params", {field: value}))

    def _loop_task(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- scene and panel, built once ----------------------------------------------------------

    def _pad_matrices(self) -> dict[str, int]:
        ax = self.settings.axes
        return {
            "/f1/proximal/cells": ax.finger1_proximal_matrix,
            "/f1/distal/cells": ax.finger1_distal_matrix,
            "/f3/proximal/cells": ax.thumb_proximal_matrix,
            "/f3/distal/cells": ax.thumb_distal_matrix,
            "/f2/proximal/cells": ax.finger2_proximal_matrix,
            "/f2/distal/cells": ax.finger2_distal_matrix,
        }

    def _layout(self, name: str) -> Any:
        t = self.settings.tactile
        return t.distal if "/distal/" in name else t.proximal

    def _build_scene(self) -> None:
        assert self.server is not None
        cfg = self.settings
        d = cfg.hand.base_offset_mm
        # from the thumb's side and a little from Finger 1's back: both pads and AB in view
        self.server.initial_camera.position = (0.27, d / 2 * MM - 0.15, 0.18)
        self.server.initial_camera.look_at = (0.0, d / 2 * MM, 0.08)
        self.urdf = self._load_urdf()
        for f in ("f1", "f2", "f3"):
            self._build_finger(f)
        self._build_contacts()
        self._render_hand()  # the pre-shape until the first pose arrives

    def _load_urdf(self) -> ViserUrdf:
        """The hand's bodies and pads: its URDF (:mod:`sdh2svc.model.urdf`), the palm placed in
        frame 0, the scene's frame."""
        assert self.server is not None
        cfg = self.settings
        text = sdh2_urdf(cfg.hand, cfg.axes, cfg.limits, cfg.tactile)
        robot = yourdfpy.URDF.load(io.StringIO(text), build_collision_scene_graph=False)
        T = robot.get_transform("palm", "frame0")  # a fixed joint: the same in every pose
        self.nodes["/hand"] = self.server.scene.add_frame(
            "/hand", show_axes=False, position=T[:3, 3], wxyz=_wxyz(T[:3, :3])
        )
        axis = {name: a for a, name in joint_names(cfg.axes).items()}
        self._urdf_axes = [axis[name] for name in robot.actuated_joint_names]
        return ViserUrdf(self.server, robot, root_node_name="/hand")

    def _build_finger(self, f: str) -> None:
        """Link frames (posed every frame) and their constant children: the tip and the cells."""
        assert self.server is not None
        sc, cfg = self.server.scene, self.settings
        for link in ("base", "proximal", "distal"):
            self.nodes[f"/{f}/{link}"] = sc.add_frame(f"/{f}/{link}", show_axes=False)
        pad = cfg.hand.pad
        tip = np.array([pad.tip_end_x3_mm, pad_y3(pad.tip_end_x3_mm, pad), 0.0]) * MM
        self.nodes[f"/{f}/distal/tip"] = sc.add_icosphere(
            f"/{f}/distal/tip", radius=1.5 * MM, color=DARK, position=tip
        )
        tile_v, tile_f = _tile_mesh(cfg.tactile.texel_pitch_mm * TILE_GAP)
        for link, (pos, rot, idx) in (
            ("distal", distal_cells(cfg)),
            ("proximal", proximal_cells(cfg)),
        ):
            name = f"/{f}/{link}/cells"
            self._tactile_idx[name] = idx
            self.nodes[name] = sc.add_batched_meshes_simple(
                name,
                tile_v,
                tile_f,
                batched_wxyzs=rot,
                batched_positions=pos * MM,
                batched_colors=tactile_colors(np.zeros(len(idx))),
                side="double",
                lod="off",
                cast_shadow=False,
                receive_shadow=False,
            )

    def _build_contacts(self) -> None:
        assert self.server is not None
        sc = self.server.scene
        cone_v, cone_f = _cone_mesh()
        for label, color in (("A", COLOR_A), ("B", COLOR_B)):
            self.nodes[f"/contacts/{label}"] = sc.add_icosphere(
                f"/contacts/{label}", radius=CONTACT_RADIUS_MM * MM, color=color, visible=False
            )
            # a child: it follows the point, and is hidden with it
            self.nodes[f"/contacts/{label}/label"] = sc.add_label(
                f"/contacts/{label}/label", label, position=(0.0, 0.0, 2 * CONTACT_RADIUS_MM * MM),
                anchor="bottom-center",
            )  # fmt: skip
            self.nodes[f"/contacts/cone_{label}"] = sc.add_mesh_simple(
                f"/contacts/cone_{label}",
                cone_v,
                cone_f,
                color=GREEN,
                opacity=0.45,
                side="double",
                cast_shadow=False,
                receive_shadow=False,
                visible=False,
            )
        none = np.zeros((1, 2, 3))
        self.nodes["/contacts/AB"] = sc.add_line_segments(
            "/contacts/AB", none, (250, 250, 250), thickness=1.2 * MM, visible=False
        )
        self.nodes["/object/outline"] = sc.add_line_segments(
            "/object/outline", none, OUTLINE_HELD, thickness=1.0 * MM, visible=False
        )
        self.nodes["/object/estimate"] = sc.add_line_segments(
            "/object/estimate", none, ESTIMATE, thickness=1.4 * MM, visible=False
        )

    def _build_gui(self) -> None:
        assert self.server is not None
        gui, p = self.server.gui, self.settings.rolling
        # no "Share" button: it asks viser's public tunnel for a URL on the internet, which a
        # lab PC next to a hand must not offer (and nothing here downloads or uploads)
        gui.configure_theme(show_share_button=False)
        with gui.add_folder("sdh2svc"):
            self.nodes["gui/state"] = gui.add_markdown("**idle**")
            for kind in COMMANDS:
                label, color, hint = BUTTONS[kind]
                why = self._refusal(kind)
                b = gui.add_button(label, color=color, disabled=why is not None, hint=why or hint)
                b.on_click(self._button_cb(kind))
                self.buttons[kind] = b
        with gui.add_folder("Rolling parameters"):
            why = self._refusal("params")
            for field, (label, lo, hi, step) in SLIDERS.items():
                v = getattr(p, field)
                s = gui.add_slider(label, min=lo, max=hi, step=step, initial_value=v,
                                   disabled=why is not None, hint=why)  # fmt: skip
                s.on_update(self._slider_cb(field))
                self.sliders[field] = s


def _quietly(fn: Callable[..., _T], *args: Any, **kwargs: Any) -> _T:
    """Call ``fn`` with what it prints logged (DEBUG), not printed: viser prints a banner and
    "Server stopped" even with ``verbose=False``; the service's stdout carries only its
    announcement, and its stderr only log records (with ``--log-format json``, one JSON object
    a line: a box drawn there is a line a log collector cannot read). The service logs the
    view's URL itself."""
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            return fn(*args, **kwargs)
    finally:
        if text := out.getvalue().strip():
            log.debug("viser printed: %s", text)
