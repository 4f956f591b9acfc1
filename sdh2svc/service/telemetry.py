"""The telemetry messages (docs/api.md, "WebSocket"): one typed value per message type, and its
one JSON form.

The service publishes these values to the hub as they are, so the control loop's path builds no
dict and converts no matrix: the JSON form is made once, at delivery (:func:`encode`), for the
WebSocket clients; the 3-D view takes the values themselves, and its process gets them pickled
(a tactile frame's matrices as arrays: bytes and shape, never lists).

What the view draws of a sample — the contact points A, B with their pad normals and ω, and the
reconstructed outline — is :class:`SampleView`, made here once per forwarded sample
(:func:`sample_view`), so the view draws the contacts as given and never works out a pad's
geometry itself. The reconstructed outline (:func:`estimate_outline`) is the recognition's own
(:func:`sdh2svc.control.recognition.outline`) from the sample's fields, the same for the
dashboard (a ``sample`` message's ``estimate_outline``), the 3-D view and Foxglove. It costs
milliseconds, so the live views share one, made at most every :data:`ESTIMATE_PERIOD_S` of the
run's time (:data:`live_outline`); a recorded iteration gets its own.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from sdh2svc.control.observer import EventKind
from sdh2svc.control.recognition import outline
from sdh2svc.control.sample import Sample
from sdh2svc.model.base import clean_json
from sdh2svc.model.friction import pad_tangent
from sdh2svc.model.kinematics import Finger, HandGeometry, Point, distal_joint, frame3_axes

log = logging.getLogger(__name__)

ESTIMATE_POINTS = 48  # of the reconstructed outline, everywhere it is drawn
ESTIMATE_PERIOD_S = 0.2  # live views: the reconstructed outline at most this often (run time)
_NO_OUTLINE: npt.NDArray[np.float64] = np.zeros((0, 2))


class Kind(StrEnum):
    """A message's ``type``."""

    HELLO = "hello"
    STATUS = "status"
    SAMPLE = "sample"
    EVENT = "event"
    TACTILE = "tactile"
    POSE = "pose"
    SIM = "sim"
    DROPPED = "dropped"


@dataclass(frozen=True, slots=True)
class Hello:
    """The first message on a connection: the status at that moment."""

    status: dict[str, Any]
    type: ClassVar[Kind] = Kind.HELLO

    def json(self) -> dict[str, Any]:
        return {"type": "hello", "status": self.status}


@dataclass(frozen=True, slots=True)
class Status:
    """The service's status (``GET /api/status``), periodically and on every change."""

    status: dict[str, Any]
    type: ClassVar[Kind] = Kind.STATUS

    def json(self) -> dict[str, Any]:
        return {"type": "status", "status": self.status}


@dataclass(frozen=True, slots=True)
class SampleMsg:
    """One rolling iteration's :class:`Sample` of run ``run_id``; ``view``, when made, is what
    the 3-D view draws of it (not in the JSON form). The JSON form's sample also carries
    ``estimate_outline``: the reconstructed outline, y0z0 mm (``[]``: no class yet)."""

    run_id: int | None
    sample: Sample
    view: SampleView | None = None
    type: ClassVar[Kind] = Kind.SAMPLE

    def with_view(self, geom: HandGeometry, *, live: bool = True) -> SampleMsg:
        """With what the view draws of it (``live``: the live views' shared outline,
        :data:`live_outline`; else this sample's own)."""
        if self.view is not None:
            return self
        return replace(self, view=sample_view(self.sample, geom, live=live))

    def json(self) -> dict[str, Any]:
        s = self.sample
        fields: dict[str, Any] = dict(zip(s.columns(), s.row(), strict=True))
        est = self.view.estimate if self.view is not None else _points(live_outline(s))
        fields["estimate_outline"] = [[y, z] for y, z in est]
        return {"type": "sample", "run_id": self.run_id, "sample": fields}


@dataclass(frozen=True, slots=True)
class Event:
    """A run's event (``run_id`` None: the hand's own, e.g. opening it, an e-stop)."""

    run_id: int | None
    t: float | None
    iteration: int | None
    kind: EventKind  # a str enum: its value is its JSON form
    detail: dict[str, Any]
    type: ClassVar[Kind] = Kind.EVENT

    def json(self) -> dict[str, Any]:
        return {"type": "event", "run_id": self.run_id, "t": self.t,
                "iteration": self.iteration, "kind": self.kind, "detail": self.detail}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Tactile:
    """A tactile frame: the six matrices of raw counts, as arrays (lists only in JSON)."""

    seq: int
    t: float
    matrices: tuple[npt.NDArray[Any], ...]
    type: ClassVar[Kind] = Kind.TACTILE

    def json(self) -> dict[str, Any]:
        mats = [m.tolist() for m in self.matrices]
        return {"type": "tactile", "seq": self.seq, "t": self.t, "matrices": mats}


@dataclass(frozen=True, slots=True)
class Pose:
    """The hand's actual angles, degrees, one per wire axis."""

    angles_deg: tuple[float, ...]
    type: ClassVar[Kind] = Kind.POSE

    def json(self) -> dict[str, Any]:
        return {"type": "pose", "angles_deg": list(self.angles_deg)}


@dataclass(frozen=True, slots=True)
class Sim:
    """The simulation's truth (object, pose, outline, contacts; docs/api.md)."""

    truth: dict[str, Any]
    type: ClassVar[Kind] = Kind.SIM

    def json(self) -> dict[str, Any]:
        return {"type": "sim", "truth": self.truth}


@dataclass(frozen=True, slots=True)
class Dropped:
    """To one client: how many of its messages were dropped so far (it reads too slowly)."""

    count: int
    type: ClassVar[Kind] = Kind.DROPPED

    def json(self) -> dict[str, Any]:
        return {"type": "dropped", "count": self.count}


Message = Hello | Status | SampleMsg | Event | Tactile | Pose | Sim | Dropped
# A message, or (from code not yet publishing typed values) its JSON form as a dict.
AnyMessage = Message | dict[str, Any]


def kind_of(msg: AnyMessage) -> str:
    return str(msg.get("type")) if isinstance(msg, dict) else msg.type


def to_json(msg: AnyMessage) -> dict[str, Any]:
    return msg if isinstance(msg, dict) else msg.json()


def encode(msg: AnyMessage) -> str:
    """The one JSON text of a message (compact; NaN and infinity as null)."""
    data = to_json(msg)
    try:
        return json.dumps(data, allow_nan=False, separators=(",", ":"))
    except ValueError:
        return json.dumps(clean_json(data), allow_nan=False, separators=(",", ":"))


# --- what the 3-D view draws -----------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Contact:
    """A contact point (frame 0, mm), the outward pad normal there (unit; None without the
    finger's angles) and ω (degrees from the pad tangent; None when unknown)."""

    at: Point
    normal: Point | None
    omega_deg: float | None


@dataclass(frozen=True, slots=True)
class SampleView:
    """A sample as the 3-D view draws it: φ2…φ5 (degrees; None: not in the sample), the
    contacts A (Finger 1) and B (Finger 2), and the reconstructed outline (:func:`estimate_outline`:
    (y, z) points, mm; empty without a class), and the cones' half-angle α the sample recorded
    (degrees; None: not recorded, draw the run's α)."""

    phi_deg: tuple[float | None, float | None, float | None, float | None]
    A: Contact | None
    B: Contact | None
    estimate: tuple[tuple[float, float], ...] = ()
    alpha_deg: float | None = None


def contact_normal(
    finger: Finger, proximal: float, distal: float, at: Point, geom: HandGeometry
) -> Point:
    """Unit outward pad normal (frame 0) at the contact point ``at`` of a coupled finger (rad):
    the contact's x3 follows from its position along frame 3, the tangent from the pad profile."""
    C = distal_joint(finger, proximal, geom)
    ex, ey = frame3_axes(finger, proximal + distal)
    x3 = (at.y - C.y) * ex.y + (at.z - C.z) * ex.z
    t = pad_tangent(finger, proximal + distal, x3, geom.pad)
    n = Point(t.z, -t.y)
    return n if n.y * ey.y + n.z * ey.z >= 0.0 else Point(-n.y, -n.z)


def _num(s: Sample | Mapping[str, Any], key: str) -> float | None:
    v = getattr(s, key, None) if isinstance(s, Sample) else s.get(key)
    return float(v) if isinstance(v, int | float) and math.isfinite(v) else None


def _contact(
    s: Sample | Mapping[str, Any], finger: Finger, names: tuple[str, str, str, str, str],
    geom: HandGeometry,
) -> Contact | None:  # fmt: skip
    y, z, prox, dist, w = (_num(s, n) for n in names)
    if y is None or z is None:
        return None
    at = Point(y, z)
    normal = None
    if prox is not None and dist is not None:
        normal = contact_normal(finger, math.radians(prox), math.radians(dist), at, geom)
    return Contact(at, normal, w)


def sample_view(
    s: Sample | Mapping[str, Any], geom: HandGeometry, *, live: bool = True
) -> SampleView:
    """What the view draws of ``s`` (a :class:`Sample` or its JSON form; a missing or
    non-finite field is None); ``live``: the live views' outline (:data:`live_outline`), else
    the sample's own."""
    phis = (_num(s, "phi2"), _num(s, "phi3"), _num(s, "phi4"), _num(s, "phi5"))
    A = _contact(s, Finger.ONE, ("Ay", "Az", "phi2", "phi3", "omega_A"), geom)
    B = _contact(s, Finger.TWO, ("By", "Bz", "phi4", "phi5", "omega_B"), geom)
    est = live_outline(s) if live else estimate_outline(s)
    return SampleView(phis, A, B, _points(est), _num(s, "alpha"))


def _points(pts: npt.NDArray[np.float64]) -> tuple[tuple[float, float], ...]:
    return tuple((y, z) for y, z in pts.tolist())


class OutlineEvery:
    """:func:`estimate_outline` of a stream of samples: the same sample's again at once, a
    later one's only when its run time ``t`` is ``period_s`` past the last one made and of the
    same class (else made again: a newer class, another run); in between the last one. Between
    two makings the contacts move a fraction of a millimetre; an outline costs milliseconds
    (``recognition.outline``)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.made = 0  # outlines made (tests, diagnostics)
        self._last: object = None
        self._t = -math.inf
        self._cls: Any = None
        self._pts = _NO_OUTLINE

    def __call__(self, s: Sample | Mapping[str, Any]) -> npt.NDArray[np.float64]:
        if s is self._last:
            return self._pts
        t = _num(s, "t")
        cls = s.object_class if isinstance(s, Sample) else s.get("object_class")
        if cls is None:
            return _NO_OUTLINE
        if t is not None and cls == self._cls and 0.0 < t - self._t < self.period_s:
            return self._pts
        self._last, self._cls, self._t = s, cls, (t if t is not None else -math.inf)
        self._pts = estimate_outline(s)
        self.made += 1
        return self._pts


#: The live views' (the hub's JSON, the 3-D view, Foxglove) one outline of the running run.
live_outline = OutlineEvery(ESTIMATE_PERIOD_S)


_outline_failures = 0


def estimate_outline(
    s: Sample | Mapping[str, Any], points: int = ESTIMATE_POINTS
) -> npt.NDArray[np.float64]:
    """The object as the recognition reconstructed it at sample ``s`` (a :class:`Sample`, or its
    JSON form or a recorded row): ``points`` × 2, y0z0 mm, touching A and B, turned by the
    estimated rotation (:func:`sdh2svc.control.recognition.outline`); empty (0 × 2) without a
    class or a contact. Never raises: what cannot be drawn is not drawn (logged rarely)."""
    global _outline_failures
    try:
        if not isinstance(s, Sample):
            row: dict[str, Any] = {c: s.get(c) for c in Sample.columns()}
            s = Sample(**row)
        rec, ay, az, by, bz = s.recognition(), s.Ay, s.Az, s.By, s.Bz
        if rec is None or rec.object_class is None or ay is None or az is None:
            return _NO_OUTLINE
        if by is None or bz is None:
            return _NO_OUTLINE
        pts = np.asarray(outline(rec, (ay, az), (by, bz), points), dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1:] != (2,) or not np.isfinite(pts).all():
            return _NO_OUTLINE
        return np.round(pts, 2)
    except Exception:
        _outline_failures += 1
        if _outline_failures in (1, 100) or _outline_failures % 10000 == 0:
            log.exception("the reconstructed outline failed (%d times)", _outline_failures)
        return _NO_OUTLINE


def as_array(matrix: Any) -> npt.NDArray[np.float64]:
    """A tactile matrix (array, or nested lists from JSON) as a 2-D float array (ValueError
    when it is not one)."""
    a = np.asarray(matrix, dtype=float)
    if a.ndim != 2:
        raise ValueError(f"a tactile matrix has 2 dimensions, not {a.ndim}")
    return a


# --- recorded truth: the same ``sim`` message as live ----------------------------------------

OUTLINE_POINTS = 90  # of the object's true outline, live and recorded


def outline_points(perimeter: npt.NDArray[Any], points: int = OUTLINE_POINTS) -> npt.NDArray[Any]:
    """``points`` of an outline's perimeter (object frame), picked as the live ``sim`` message
    picks them (:meth:`sdh2svc.sim.hand.Truth.scene`)."""
    return perimeter[:: max(1, len(perimeter) // points)]


def recorded_truth(outline: Mapping[str, Any], row: Mapping[str, Any]) -> dict[str, Any]:
    """A recorded iteration's truth as the live ``sim`` message's (``Truth.scene``): the run's
    outline (``RunStore.outline``: object frame) placed at the iteration's pose (a
    ``RunStore.truth`` row), hand frame, mm. No contacts: the recording holds none."""
    y, z, psi = float(row["y"]), float(row["z"]), float(row["psi"])
    pts = np.asarray(outline["points"], dtype=float).reshape(-1, 2)
    c, s = math.cos(psi), math.sin(psi)
    world = np.column_stack([y + c * pts[:, 0] - s * pts[:, 1],
                             z + s * pts[:, 0] + c * pts[:, 1]])  # fmt: skip
    return {
        "object": outline["object"], "size_mm": outline["size_mm"], "held": bool(row["held"]),
        "dropped": bool(row["dropped"]), "in_fixture": bool(row["in_fixture"]),
        "pose": [y, z, psi], "slips": int(row["slips"]), "outline": np.round(world, 2).tolist(),
        "contacts": [],
    }  # fmt: skip


# --- recorded frames: the same matrices as the live ``tactile`` message ------------------------


def frame_matrices(
    texels: npt.NDArray[Any], shapes: tuple[tuple[int, int], ...]
) -> tuple[npt.NDArray[Any], ...]:
    """A recorded frame's flat texels as the matrices a live :class:`Tactile` carries
    (ValueError when the count does not match ``shapes``)."""
    flat = np.asarray(texels)
    if flat.shape != (sum(r * c for r, c in shapes),):
        raise ValueError(f"a frame of {flat.size} texels does not fit the matrices {shapes}")
    out, start = [], 0
    for rows, cols in shapes:
        out.append(flat[start : start + rows * cols].reshape(rows, cols))
        start += rows * cols
    return tuple(out)
