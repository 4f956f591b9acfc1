"""Recognition while rolling (thesis §5.2): what touches the pads, what the object is, how far
it turned — from the tactile frames and the joint angles only, never the simulation's truth.

Pure and sans-I/O like :mod:`sdh2svc.control.rolling`: a :class:`Recognizer` per run takes
each iteration's :class:`~sdh2svc.model.observe.Observation` and the two distal pads' raw counts
and returns a :class:`Recognition`. The runner calls it after the rolling step; what it returns
goes into the run's :class:`~sdh2svc.control.sample.Sample`, telemetry and recordings.

How (rolling kinematics, no model of the object):

* **Rotation.** The object is rigid and rolls on the pads without slipping, so its material
  points at A and B move as the pads' material points there: between two iterations the pad
  points under the old contacts move by δA, δB (forward kinematics of the new pose at the old
  virtual joints), and the object turns by dψ = (AB × (δB − δA)) / |AB|².
* **Contact kind and radius.** At a contact the object's normal is the pad's, ν (frame 0, from
  the pose and where on the pad the contact is). Rolling moves the contact along the pad by as
  much as along the object, and turns the object's normal relative to the object by
  κ·ds: the slope of ν − ψ against the pad's curved distance L over the last iterations is the
  object's local curvature there. No relative turn while the contact travels: a **flat** face;
  a relative turn while the contact stays put (a pivot): an **edge** or corner; in between a
  **curved** surface of radius 1/κ. A small learned model (multinomial logistic,
  :class:`Softmax`) weighs this against how well ν − ψ fits a line over the window (a
  transition does not), the same line over a longer window (about a half stroke: a radius of
  a few millimetres moves the contact too little in the short one to tell it from a pivot),
  where the window breaks best into two lines and the later line alone (:meth:`_Line.split`:
  a contact that just went from a face onto a corner or a rounding, or back), how the
  footprint changed over the last few iterations, the pressure footprint and its profile
  along the pad (:func:`pressure_profile`: a flat face loads the rows under it alike or in a
  ramp, a curved surface in a hump), how soft the object
  reads over the run (the pad rubber's compression against Hertz's F^⅔: a soft object takes
  part of the squeeze, and its flat face wraps the pad like a curved one) and the other contact
  (:func:`contact_features`); without one, :meth:`_ContactTrack._rules` decide. A curved
  contact's radius is the kinematic one times a learned correction (:class:`Linear`, on the
  same features but the break and the footprint's changes), which undoes the window's bias on
  large radii and soft objects.
* **Class and sizes** from what the contacts were over the run (:func:`class_features`, a
  second learned model; without one, :func:`classify`'s rules; sizes by :func:`sizes`),
  among it the touched outline in the object frame: the flat faces' directions ν − ψ and the
  pads' sweeps about the edges they pivot on, against a box's (:func:`box_misfit`: faces at
  right angles, corners turning the pad within one).

The learned parts are fitted by ``python -m experiments.recognition.fit`` and shipped in
``recognition_model.json`` beside this module. From the raw counts it takes the pressure's
profile along each pad; the rest comes from the observation's contact estimates.
"""

from __future__ import annotations

import bisect
import itertools
import json
import math
import operator
from collections import deque
from dataclasses import dataclass, field, replace
from enum import StrEnum
from functools import lru_cache
from importlib import resources
from typing import Any, Self

import numpy as np

from sdh2svc.model.base import clean_json
from sdh2svc.model.contact import ContactEstimate
from sdh2svc.model.geometry import pad_slope
from sdh2svc.model.kinematics import Finger, HandPose, Point, frame3_axes
from sdh2svc.model.observe import ModelContext, Observation, rolling_turn

MODEL_FILE = "recognition_model.json"


class ContactKind(StrEnum):
    """What part of the object touches a pad."""

    FLAT = "flat"  # a flat face lying along the pad
    EDGE = "edge"  # an edge or corner of the object
    CURVED = "curved"  # a curved surface (its local radius is estimated)


class ObjectClass(StrEnum):
    """The object families a lab meets (the campaign generator's, sdh2svc.campaign)."""

    BOX = "box"
    POLYGON = "polygon"
    ELLIPSE = "ellipse"
    CIRCLE = "circle"
    STICK = "stick"


@dataclass(frozen=True, slots=True)
class Recognition:
    """What the rolling revealed so far (lengths in mm, angles in degrees).

    ``size_a``/``size_b`` by class: circle (radius, None); ellipse (semi-axes a ≥ b, from the
    widest and narrowest caliper widths seen and the product a·b the curved contacts' radii
    give: :func:`ellipse_axes`); box
    (the side held between the pads, None: the other is not measured); stick (length,
    diameter); polygon (circumradius, None).
    ``side``: the side of A→B the object's centre lies on (:func:`centre_side`), which places
    the reconstructed outline.
    ``axis``: the direction of the outline's first axis (``size_a``'s) at the grasp, deg: σ₀,
    the inclination of AB at the grasp, or σ₀ + 90° for an ellipse held across its minor axis;
    the reconstructed outline's orientation is ``axis + rotation`` (:func:`outline`).
    """

    kind1: ContactKind | None = None  # Finger 1's contact (None: no contact)
    kind2: ContactKind | None = None  # Finger 2's contact
    radius1: float | None = None  # local radius of curvature at a curved contact, mm
    radius2: float | None = None
    object_class: ObjectClass | None = None  # None until the evidence decides
    confidence: float = 0.0  # of object_class, 0…1
    size_a: float | None = None
    size_b: float | None = None
    rotation: float = 0.0  # the object's rotation since the grasp (rolling kinematics), deg
    axis: float | None = None  # the outline's first axis at the grasp, deg
    # the side of A→B the object's centre lies on, from the pads' normals (:func:`centre_side`)
    side: int = 0


@dataclass(frozen=True, slots=True)
class _Affine:
    """Standardised features (``mean``, ``scale``), optionally with their pairwise products
    appended (``quadratic``), then ``weights`` · z + ``bias``."""

    mean: np.ndarray
    scale: np.ndarray
    weights: np.ndarray  # (outputs, features) or (features,)
    bias: np.ndarray  # (outputs,) or a scalar
    quadratic: bool = False
    # the standardisation folded into the weights and bias: one product per call
    _w: np.ndarray = field(init=False, repr=False, compare=False)
    _b: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        w = self.weights / self.scale
        object.__setattr__(self, "_w", w.T)
        object.__setattr__(self, "_b", self.bias - w @ self.mean)

    @classmethod
    def load(cls, data: dict[str, Any]) -> Self:
        return cls(
            np.asarray(data["mean"], float),
            np.asarray(data["scale"], float),
            np.asarray(data["weights"], float),
            np.asarray(data["bias"], float),
            bool(data.get("quadratic", False)),
        )

    def dump(self) -> dict[str, Any]:
        return {
            "mean": self.mean.tolist(),
            "scale": self.scale.tolist(),
            "weights": self.weights.tolist(),
            "bias": self.bias.tolist(),
            "quadratic": self.quadratic,
        }

    def scores(self, x: np.ndarray, expanded: np.ndarray | None = None) -> np.ndarray:
        """The outputs for one sample (features on the last axis) or many (one per row);
        ``expanded``: ``expand(x)``, when the caller has it already."""
        if self.quadratic:
            x = expand(x) if expanded is None else expanded
        out: np.ndarray = x @ self._w + self._b
        return out


@dataclass(frozen=True, slots=True)
class Softmax(_Affine):
    """A multinomial logistic model."""

    def probabilities(self, x: np.ndarray, expanded: np.ndarray | None = None) -> np.ndarray:
        s = self.scores(x, expanded)
        e = np.exp(s - s.max(axis=-1, keepdims=True))
        p: np.ndarray = e / e.sum(axis=-1, keepdims=True)
        return p


@dataclass(frozen=True, slots=True)
class Linear(_Affine):
    """A linear model (one output)."""

    def predict(self, x: np.ndarray, expanded: np.ndarray | None = None) -> float:
        return float(self.scores(x, expanded))


def expand(x: np.ndarray) -> np.ndarray:
    """``x`` followed by the products of every pair of its entries (with themselves)."""
    n = x.shape[-1]
    i, j = _pairs(n)
    # the products straight into their place (no concatenation); np.take: a fancy index on the
    # last axis of many rows is slower by half
    out = np.empty((*x.shape[:-1], n + len(i)), dtype=x.dtype)
    out[..., :n] = x
    np.multiply(np.take(x, i, axis=-1), np.take(x, j, axis=-1), out=out[..., n:])
    return out


@lru_cache(maxsize=8)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(n)
    return i, j


@lru_cache(maxsize=8)
def _sub_expansion(n: int) -> np.ndarray:
    """Where ``expand(x[:RADIUS_FEATURES])``'s entries are in ``expand(x)``, x of ``n``
    features: the same products of the same entries, so the same values to the last bit."""
    i, j = _pairs(n)
    at = {(a, b): n + k for k, (a, b) in enumerate(zip(i.tolist(), j.tolist(), strict=True))}
    si, sj = _pairs(RADIUS_FEATURES)
    products = [at[a, b] for a, b in zip(si.tolist(), sj.tolist(), strict=True)]
    return np.array([*range(RADIUS_FEATURES), *products])


@dataclass(frozen=True, slots=True)
class RecognitionModel:
    """The estimators' parameters (fitted by ``python -m experiments.recognition.fit``)."""

    window: int = 20  # iterations in the curvature regression
    long_window: int = 120  # iterations in the long one (about a half stroke)
    min_travel_mm: float = 0.3  # contact travel below which a relative turn is a pivot
    min_turn_deg: float = 0.6  # relative turn below which a travelling contact is flat
    edge_radius_mm: float = 4.0  # a curved contact sharper than this is an edge
    flat_radius_mm: float = 150.0  # flatter than this is a flat face
    circle_tol: float = 0.2  # |R − Λ/2| / (Λ/2) of a circle's contacts
    stick_ratio: float = 0.2  # a stick's ends: R below this × Λ
    parallel_deg: float = 6.0  # a box's two faces: pad normals antiparallel within this
    smoothing: float = 0.0  # of the kind's probabilities per iteration (exponential, 0: none)
    kind: Softmax | None = None  # contact kind from contact_features (else the rules above)
    object_class: Softmax | None = None  # class from class_features (else classify's rules)
    # log(true radius / kinematic radius) at a curved contact, from contact_features: the
    # window's line is biased on large radii (a few mm of travel per degree) and soft objects
    radius: Linear | None = None

    @classmethod
    def load(cls, data: dict[str, Any]) -> RecognitionModel:
        kw = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        for key, kind in _LEARNED.items():
            if kw.get(key) is not None:
                kw[key] = kind.load(kw[key])
        return cls(**kw)

    def dump(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for key in _LEARNED:
            if out[key] is not None:
                out[key] = out[key].dump()
        return out


# RecognitionModel's learned parts, by field
_LEARNED: dict[str, type[_Affine]] = {"kind": Softmax, "object_class": Softmax, "radius": Linear}


KINDS = (ContactKind.FLAT, ContactKind.EDGE, ContactKind.CURVED)  # the kind model's order
CLASSES = tuple(ObjectClass)  # the class model's order


@lru_cache(maxsize=1)
def packaged_model() -> RecognitionModel:
    """The shipped parameters (the package's ``control/recognition_model.json``)."""
    try:
        text = resources.files("sdh2svc.control").joinpath(MODEL_FILE).read_text()
    except FileNotFoundError:
        return RecognitionModel()
    return RecognitionModel.load(json.loads(text))


def pad_normal_angle(finger: Finger, pose: HandPose, x3: float, ctx: ModelContext) -> float:
    """Direction (frame 0, rad) of the pad's tangent at frame-3 x ``x3``: the object's surface
    direction there; it turns with the object's normal."""
    prox, dist = pose.finger(finger)
    ex, ey = frame3_axes(finger, prox + dist)
    m = pad_slope(x3, ctx.geom.pad)
    return math.atan2(ex.z + m * ey.z, ex.y + m * ey.y)


MAX_RADIUS_MM = 1000.0  # a kinematic radius beyond this (or a curvature ≤ 0) is flat
# the radius model's correction stays within ×/÷ 10: its fit suites need at most ≈ ×9 (99.8 % of
# them within ×/÷ 7), and far outside them its pairwise products extrapolate without bound
MAX_LOG_CORRECTION = math.log(10.0)


class _ContactTrack:
    """One pad's recent (L, ν − ψ): the kinematic curvature, the rules' kind, the features."""

    def __init__(self, finger: Finger, model: RecognitionModel) -> None:
        self.finger = finger
        self.model = model
        # Finger 2 is mirrored: ν − ψ turns the other way for the same curvature
        self.sign = -1.0 if finger is Finger.ONE else 1.0
        self.short = _Line(model.window)  # (L, ν − ψ): the curvature window
        self.long = _Line(model.long_window)  # the same over about a half stroke
        self.kind: ContactKind | None = None
        self.radius: float | None = None
        self.kinematic_radius = MAX_RADIUS_MM
        self.features: list[float] | None = None  # see contact_features
        self.p: np.ndarray | None = None  # the kind model's smoothed probabilities
        # the footprint's features over the last TREND_FAR + 1 iterations
        self._recent: deque[list[float]] = deque(maxlen=TREND_FAR + 1)
        # the run's mean of log(rubber compression / F^⅔): Hertz's compression grows as F^⅔
        # against a rigid body; a soft object takes its part of the squeeze, the pad less
        self._soft_sum, self._soft_n = 0.0, 0

    @property
    def softness(self) -> float:
        """The run's mean log(compression / F^⅔) at this pad (0 before a firm contact)."""
        return self._soft_sum / self._soft_n if self._soft_n else 0.0

    def lost(self) -> None:
        self.short.clear()
        self.long.clear()
        self._recent.clear()
        self.kind, self.radius, self.features, self.p = None, None, None, None

    def update(self, c: ContactEstimate, nu: float, psi: float, counts: np.ndarray) -> None:
        assert c.L_mm is not None
        self.short.add(c.L_mm, nu - psi)
        self.long.add(c.L_mm, nu - psi)
        if len(self.short.x) < 3:
            return
        kappa, travel, turn, resid = self.short.fit()
        kappa *= self.sign
        self.kinematic_radius = _radius_of(kappa)
        # the same over the long window (a half stroke): a small radius (a stick's end, an
        # ellipse's tip) turns the pad by a fraction of a degree per 0.1 mm of travel, too
        # little to tell from a pivot in the short window
        long_kappa, long_travel, long_turn, long_resid = self.long.fit()
        long_radius = _radius_of(self.sign * long_kappa)
        main = max(c.blobs, key=lambda b: b.pressure_sum_n_per_mm2)
        d = c.depth
        if c.force > 0.05:
            self._soft_sum += math.log(d.compression_mm + 0.01) - math.log(c.force) * 2 / 3
            self._soft_n += 1
        self.features = [
            math.log(max(self.kinematic_radius, 0.5)),
            math.log(travel + 0.05),
            math.log(turn + 0.05),
            d.footprint_sd_mm or 0.0,
            float(main.last_row - main.first_row + 1),
            float(c.n_cells),
            math.log(d.compression_mm + 0.01),
            d.band_mm,
            c.force,
            c.L_mm,
            math.log(resid + 0.05),
            self.softness,
            math.log(max(long_radius, 0.5)),  # LONG_RADIUS
            math.log(long_travel + 0.05),
            math.log(long_turn + 0.05),
            math.log(long_resid + 0.05),
            *pressure_profile(counts, main.first_row, main.last_row),
        ]
        # what changed lately: the window's best break into two lines (CHANGE) and how the
        # footprint moved over the last few iterations (TREND), so a contact that just went
        # from a face onto a corner, or back, need not wait for the whole window to show it
        gain, since, recent_kappa, recent_travel, recent_turn = self.short.split()
        self.features += [
            gain, since, math.log(max(_radius_of(self.sign * recent_kappa), 0.5)),
            math.log(recent_travel + 0.05), math.log(recent_turn + 0.05),
        ]  # fmt: skip
        now = [self.features[i] for i in _FOOTPRINT]
        self._recent.append(now)
        near, far = self._recent[max(0, len(self._recent) - 1 - TREND_NEAR)], self._recent[0]
        self.features += [a - b for a, b in zip(now, near, strict=True)]
        self.features += [a - b for a, b in zip(now, far, strict=True)]
        self.kind, self.radius = self._rules(travel, turn, kappa)

    def _rules(
        self, travel: float, turn: float, kappa: float
    ) -> tuple[ContactKind | None, float | None]:
        """The kind without a learned model: a pivot is an edge, no relative turn is flat."""
        m = self.model
        if travel < m.min_travel_mm:
            return (
                (ContactKind.EDGE, None) if turn > 2 * m.min_turn_deg else (self.kind, self.radius)
            )
        if turn < m.min_turn_deg or kappa <= 1.0 / m.flat_radius_mm:
            return ContactKind.FLAT, None
        if kappa >= 1.0 / m.edge_radius_mm:
            return ContactKind.EDGE, None
        return ContactKind.CURVED, 1.0 / kappa


def _radius_of(kappa: float) -> float:
    """The radius (mm) of a signed curvature: MAX_RADIUS_MM for a flat or concave one."""
    return min(1.0 / kappa, MAX_RADIUS_MM) if kappa > 0 else MAX_RADIUS_MM


class _Extremes:
    """The largest and the smallest of the last ``n`` values added, in constant time per value
    (amortised): monotonic queues of (index, value). Of equal values the queues keep the
    oldest at the front, the one ``max`` and ``min`` of the window return."""

    __slots__ = ("_hi", "_lo", "_n", "_t")

    def __init__(self, n: int) -> None:
        self._n = n
        self._hi: deque[tuple[int, float]] = deque()
        self._lo: deque[tuple[int, float]] = deque()
        self._t = 0

    def clear(self) -> None:
        self._hi.clear()
        self._lo.clear()
        self._t = 0

    def add(self, v: float) -> None:
        hi, lo, t = self._hi, self._lo, self._t
        while hi and hi[-1][1] < v:
            hi.pop()
        hi.append((t, v))
        while lo and lo[-1][1] > v:
            lo.pop()
        lo.append((t, v))
        if hi[0][0] <= t - self._n:  # the value leaving the window
            hi.popleft()
        if lo[0][0] <= t - self._n:
            lo.popleft()
        self._t = t + 1

    def span(self) -> float:
        """max − min of the window (as ``max(window) - min(window)``)."""
        return self._hi[0][1] - self._lo[0][1]


class _Line:
    """The last ``n`` (L, ν − ψ) and their least-squares line, in constant time per iteration:
    running sums (made anew every ``n`` additions, so rounding never builds up), the window's
    extremes from monotonic queues (:class:`_Extremes`)."""

    def __init__(self, n: int) -> None:
        self.x: deque[float] = deque(maxlen=n)
        self.y: deque[float] = deque(maxlen=n)
        self._x_range, self._y_range = _Extremes(n), _Extremes(n)
        self.clear()

    def clear(self) -> None:
        self.x.clear()
        self.y.clear()
        self._x_range.clear()
        self._y_range.clear()
        self._sums = [0.0] * 5  # Σx, Σy, Σxx, Σxy, Σyy
        # the same sums over the values added since the sums were last made anew: when they
        # are made anew, those values are the window, in order (the first time a window of
        # one, then every n additions), so these are the window's sums as summed afresh —
        # added up one value at a time, not all at once every n (a long window's spike)
        self._fresh = [0.0] * 5
        self._since = 0

    def add(self, x: float, y: float) -> None:
        sums, fresh, xs, ys = self._sums, self._fresh, self.x, self.y
        if len(xs) == xs.maxlen:
            ox, oy = xs[0], ys[0]
            sums[0] -= ox
            sums[1] -= oy
            sums[2] -= ox * ox
            sums[3] -= ox * oy
            sums[4] -= oy * oy
        xs.append(x)
        ys.append(y)
        self._x_range.add(x)
        self._y_range.add(y)
        xx, xy, yy = x * x, x * y, y * y
        fresh[0] += x
        fresh[1] += y
        fresh[2] += xx
        fresh[3] += xy
        fresh[4] += yy
        self._since += 1
        if self._since >= len(xs):
            self._since = 0
            sums[:] = fresh
            fresh[:] = _ZEROS5
        else:
            sums[0] += x
            sums[1] += y
            sums[2] += xx
            sums[3] += xy
            sums[4] += yy

    def split(self) -> tuple[float, float, float, float, float]:
        """The window broken where two lines fit it best (each of at least MIN_PIECE points):
        log(one line's squared residual / the two lines'), the later line's length
        (iterations), slope (as :meth:`fit`'s), travel (mm) and relative turn (°). A window on
        one feature gains little from a break; one across a change gains much, and the later
        line is the new feature's alone."""
        xs, ys = self.x, self.y
        n = len(xs)
        if n < 2 * MIN_PIECE + 2:
            return 0.0, 0.0, 0.0, 0.0, 0.0
        # prefix sums of x, y, xx, xy, yy (the loop below written out: it runs per pad and
        # iteration)
        px = list(itertools.accumulate(xs, initial=0.0))
        py = list(itertools.accumulate(ys, initial=0.0))
        pxx = list(itertools.accumulate(map(operator.mul, xs, xs), initial=0.0))
        pxy = list(itertools.accumulate(map(operator.mul, xs, ys), initial=0.0))
        pyy = list(itertools.accumulate(map(operator.mul, ys, ys), initial=0.0))
        X, Y, XX, XY, YY = px[n], py[n], pxx[n], pxy[n], pyy[n]
        best, cut = math.inf, MIN_PIECE
        # _line_residual written out for both pieces (a call per piece costs a third more)
        for k in range(MIN_PIECE, n - MIN_PIECE + 1):
            sx, sy, m = px[k], py[k], n - k
            vxx, vxy = pxx[k] - sx * sx / k, pxy[k] - sx * sy / k
            e = pyy[k] - sy * sy / k - (vxy * vxy / vxx if vxx > 1e-9 else 0.0)
            sx, sy = X - sx, Y - sy
            vxx, vxy = XX - pxx[k] - sx * sx / m, XY - pxy[k] - sx * sy / m
            e2 = YY - pyy[k] - sy * sy / m - (vxy * vxy / vxx if vxx > 1e-9 else 0.0)
            # each piece's residual, less rounding below nil
            e = (e if e > 0.0 else 0.0) + (e2 if e2 > 0.0 else 0.0)
            if e < best:
                best, cut = e, k
        whole = _line_residual(n, X, Y, XX, XY, YY)
        m = n - cut
        sx, sy = X - px[cut], Y - py[cut]
        vxx, vxy = XX - pxx[cut] - sx * sx / m, XY - pxy[cut] - sx * sy / m
        later_x = list(itertools.islice(xs, cut, n))
        later_y = list(itertools.islice(ys, cut, n))
        return (
            math.log((whole + 1e-7) / (best + 1e-7)),
            float(n - cut),
            vxy / vxx if vxx > 1e-9 else 0.0,
            max(later_x) - min(later_x),
            math.degrees(max(later_y) - min(later_y)),
        )

    def fit(self) -> tuple[float, float, float, float]:
        """The slope of ν − ψ (rad) against L (mm): the curvature (unsigned, 1/mm; 0 without
        travel); the contact's travel (mm) and relative turn (°) over the window; the rms of
        what the line leaves (°: small on one feature, large across a transition)."""
        n = len(self.x)
        sx, sy, sxx, sxy, syy = self._sums
        sxx, sxy, syy = sxx - sx * sx / n, sxy - sx * sy / n, syy - sy * sy / n
        travel = self._x_range.span()
        turn = math.degrees(self._y_range.span())
        if sxx <= 1e-9:
            return 0.0, travel, turn, 0.0
        resid = math.degrees(math.sqrt(max(syy - sxy * sxy / sxx, 0.0) / n))
        return sxy / sxx, travel, turn, resid


_ZEROS5 = (0.0, 0.0, 0.0, 0.0, 0.0)


def _line_residual(m: int, sx: float, sy: float, sxx: float, sxy: float, syy: float) -> float:
    """m points' squared residual from their least-squares line, from their sums."""
    vxx, vxy = sxx - sx * sx / m, sxy - sx * sy / m
    return max(syy - sy * sy / m - (vxy * vxy / vxx if vxx > 1e-9 else 0.0), 0.0)


MIN_PIECE = 3  # iterations in either line of _Line.split
LONG_RADIUS = 12  # in a track's features: log of the long window's kinematic radius
# a contact of one row: no shape along the pad (flat-topped, no skew, nor spread, nor ramp)
_ONE_ROW = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
PROFILE = len(_ONE_ROW)  # pressure_profile's values in a track's features, from PROFILE_AT
PROFILE_AT = 16
CHANGE_AT = PROFILE_AT + PROFILE  # _Line.split's five values
TREND_AT = CHANGE_AT + 5  # the footprint's changes over TREND_NEAR and TREND_FAR iterations
TREND_NEAR, TREND_FAR = 3, 8
# the footprint's features whose changes are the trend: its spread, rows, cells, rubber
# compression, band, force and profile
_FOOTPRINT = (3, 4, 5, 6, 7, 8, *range(PROFILE_AT, CHANGE_AT))
# contact_features' first RADIUS_FEATURES are the radius model's input
RADIUS_FEATURES = CHANGE_AT + 1 + 4 + 1 + PROFILE + 1


def pressure_profile(counts: np.ndarray, first: int, last: int) -> tuple[float, ...]:
    """The shape of the pressure along the pad over a contact's rows ``first``…``last``,
    whatever its scale: peak / mean (1 flat-topped), |skewness| (a ramp is lopsided), kurtosis,
    the end rows' mean against the peak, log(spread / rows), and the rms of what a straight
    line leaves, against the peak. A rigid flat face pressed evenly loads the rows under it
    alike, tilted in a ramp; a curved surface loads them in a hump (Hertz), an edge in one or
    two rows; a soft object's flat face, which wraps the pad as it rolls and turns against it
    like a curved one, keeps its even load."""
    # each row's sum of whole counts, in plain Python: a handful of rows, exact in any order
    p = list(map(sum, counts[first : last + 1].tolist()))
    n, peak = len(p), max(p)
    if n < 2 or peak <= 0.0:
        return _ONE_ROW
    # the profile's raw moments about its first row, in one pass
    m0 = m1 = m2 = m3 = m4 = q = 0.0
    for i, v in enumerate(p):
        m0 += v
        m1 += i * v
        m2 += i * i * v
        m3 += i * i * i * v
        m4 += i * i * i * i * v
        q += v * v
    mu = m1 / m0
    var = m2 / m0 - mu * mu + 1e-9
    skew = (m3 / m0 - 3 * mu * m2 / m0 + 2 * mu**3) / var**1.5
    kurt = (m4 / m0 - 4 * mu * m3 / m0 + 6 * mu * mu * m2 / m0 - 3 * mu**4) / var**2
    # the straight line's rms residual: Σ(v − v̄)² less what the slope explains
    mean, mid = m0 / n, (n - 1) / 2
    sii = n * (n * n - 1) / 12  # Σ(i − mid)²
    siv = m1 - mid * m0  # Σ(i − mid)·v
    ramp = math.sqrt(max(q - m0 * mean - siv * siv / sii, 0.0) / n)
    return (
        peak / mean, abs(skew), kurt, (p[0] + p[-1]) / 2 / peak,
        math.log(math.sqrt(var) / n), ramp / peak,
    )  # fmt: skip


def contact_features(me: list[float], other: list[float], lam: float) -> np.ndarray:
    """The kind model's input for one contact: its own track's features up to the change, the
    radius against Λ/2, the other contact's first four (radius, travel, turn, footprint),
    long-window radius and pressure profile, log Λ (these first RADIUS_FEATURES are the radius
    model's too); then both contacts' change and its own footprint's trend."""
    return np.array(_contact_row(me, other, lam))


def _contact_row(me: list[float], other: list[float], lam: float) -> list[float]:
    """:func:`contact_features` as a list."""
    return [
        *me[:CHANGE_AT], me[0] - math.log(lam / 2), *other[:4], other[LONG_RADIUS],
        *other[PROFILE_AT:CHANGE_AT], math.log(lam),
        *me[CHANGE_AT:TREND_AT], *other[CHANGE_AT:TREND_AT], *me[TREND_AT:],
    ]  # fmt: skip


class _LogHistogram:
    """Counts of log values in fixed bins: quantiles in constant time however long the run."""

    LO, HI, BINS = -4.0, 2.0, 120  # log(radius / (Λ/2)): 0.018 … 7.4, bins of 5 %

    def __init__(self) -> None:
        self.counts = [0] * self.BINS
        self.n = 0

    def add(self, value: float) -> None:
        x = (math.log(max(value, 1e-9)) - self.LO) / (self.HI - self.LO) * self.BINS
        self.counts[min(self.BINS - 1, max(0, int(x)))] += 1
        self.n += 1

    def quantiles(self, qs: tuple[float, ...]) -> list[float]:
        """The log values at the quantiles ``qs`` (0…1; bin centres; 0 while empty)."""
        if self.n == 0:
            return [0.0] * len(qs)
        cum = list(itertools.accumulate(self.counts))
        width = (self.HI - self.LO) / self.BINS
        return [self.LO + (bisect.bisect_left(cum, q * self.n) + 0.5) * width for q in qs]


class _LogMedian:
    """The running median of positive values to 1 %: counts of their logs in bins of 0.01 over
    [``lo``, ``hi``) (values outside count in the end bins), and the median's bin kept as each
    value comes (it moves a bin or so at a time): constant memory and O(1) per value however
    long the run."""

    def __init__(self, lo: float, hi: float) -> None:
        self.lo = lo
        self.counts = [0] * round((hi - lo) / 0.01)
        self.n = 0
        self._m = 0  # the median's bin: the first whose cumulative count reaches n / 2
        self._cum = 0  # the count of values in bins 0 … _m

    def add(self, value: float) -> None:
        counts = self.counts
        i = min(len(counts) - 1, max(0, int((math.log(max(value, 1e-12)) - self.lo) / 0.01)))
        counts[i] += 1
        self.n += 1
        m, cum, half = self._m, self._cum + (i <= self._m), self.n / 2
        while m > 0 and cum - counts[m] >= half:
            cum -= counts[m]
            m -= 1
        while cum < half:
            m += 1
            cum += counts[m]
        self._m, self._cum = m, cum

    def median(self) -> float | None:
        """The median (its bin's centre), or None while empty."""
        return math.exp(self.lo + (self._m + 0.5) * 0.01) if self.n else None


MIN_SWEEP = 5  # iterations of an edge run before its sweep counts
MAX_SWEEPS = 24  # the widest sweeps kept (a run's pivots are few; this bounds the cost)
_BETAS = np.arange(90.0)  # a box's orientations tried, deg (its directions β + k·90°)
_OFF_GRID = np.abs((np.arange(180.0)[None, :] + 0.5 - _BETAS[:, None] + 45.0) % 90.0 - 45.0)


@dataclass
class _Evidence:
    """What the run has shown so far, for the class."""

    n: int = 0  # iterations with both contacts labelled
    flat: int = 0  # contact-iterations by kind (both fingers)
    edge: int = 0
    curved: int = 0
    both_flat: int = 0
    both_edge: int = 0
    parallel: int = 0  # of both_flat: the pad normals antiparallel
    radii: _LogHistogram = field(default_factory=_LogHistogram)  # curved: radius / (Λ/2)
    lam_min: float = math.inf
    lam_max: float = 0.0
    lam_sum: float = 0.0
    lam_n: int = 0
    psi_min: float = 0.0  # rad
    psi_max: float = 0.0
    # dσ against dψ over the run (Σ dψ·dσ, Σ dψ²): a circle rolls with σ still (slope 0), a
    # stick's contacts stay at its ends, so AB turns with it (slope 1)
    s_ps: float = 0.0
    s_pp: float = 0.0
    # the caliper width D = Λ / cos(w/2) — Λ with the pads' wedge w taken out: a circle's
    # diameter whatever the wedge, where Λ, its chord, shrinks as the wedge opens — against ψ
    # (Σψ, Σψ², ΣψD, ΣD; the count is lam_n) and its least and most: its slope as the object
    # turns is nil for a circle, a cos 2θ for an ellipse, a box's other side at a corner
    p_sum: float = 0.0
    pp_sum: float = 0.0
    pd_sum: float = 0.0
    d_sum: float = 0.0
    d_min: float = math.inf
    d_max: float = 0.0
    # a·b from each curved contact: an ellipse's radius of curvature where its tangent lies p
    # from its centre is ρ = (ab)² / p³, and p is half the caliper width, so ab = √ρ · (D/2)^1.5
    # wherever it touches: the axis the rolling never turned to the pads follows from the other
    # (mm², from 1 to 22 000)
    ab: _LogMedian = field(default_factory=lambda: _LogMedian(0.0, 10.0))
    # the touched outline in the object frame (ν − ψ, deg): Σ over the flat contacts of their
    # direction's distance from β + k·90° for every β in _BETAS, and how many; and the pivots'
    # sweeps (each edge run's lowest and highest direction)
    faces: np.ndarray = field(default_factory=lambda: np.zeros(len(_BETAS)))
    faces_n: int = 0
    sweeps: list[tuple[float, float]] = field(default_factory=list)
    # the sweeps' farthest crossing of β + k·90° for every β (:func:`_crossing`), kept until
    # the next sweep ends: the edge runs end a few times a stroke, the class is asked for
    # every iteration
    _crossed: np.ndarray | None = field(default=None, repr=False)

    def add_width(self, lam: float, psi: float, wedge: float = 0.0) -> float:
        """One iteration's Λ (mm) at the object's rotation ψ, between pads whose surfaces
        meet at ``wedge`` (rad; 0: parallel); returns the caliper width D."""
        self.lam_min, self.lam_max = min(self.lam_min, lam), max(self.lam_max, lam)
        self.lam_sum += lam
        self.lam_n += 1
        d = lam / math.cos(wedge / 2)
        self.d_min, self.d_max = min(self.d_min, d), max(self.d_max, d)
        self.d_sum += d
        self.p_sum += psi
        self.pp_sum += psi * psi
        self.pd_sum += psi * d
        return d

    @property
    def d_mean(self) -> float:
        """The caliper width's mean (mm; 0 before any width)."""
        return self.d_sum / self.lam_n if self.lam_n else 0.0

    def add_face(self, direction: float) -> None:
        """A flat contact's direction on the object (ν − ψ, deg)."""
        self.faces += _OFF_GRID[:, int(direction % 180.0)]
        self.faces_n += 1

    def add_sweep(self, span: tuple[float, float]) -> None:
        """A finished edge run's sweep (deg); only the MAX_SWEEPS widest are kept."""
        self.sweeps.append(span)
        if len(self.sweeps) > MAX_SWEEPS:
            self.sweeps.remove(min(self.sweeps, key=lambda s: s[1] - s[0]))
        self._crossed = None

    def crossed(self) -> np.ndarray:
        """:func:`_crossing` of the finished sweeps (some)."""
        if self._crossed is None:
            self._crossed = _crossing(self.sweeps)
        return self._crossed


class _Sweep:
    """One pad's current edge run: how far the pad's direction on the object swept (deg)."""

    __slots__ = ("d0", "hi", "lo", "n")

    def __init__(self, d: float) -> None:
        self.d0, self.lo, self.hi, self.n = d, 0.0, 0.0, 1

    def add(self, d: float) -> None:
        rel = (d - self.d0 + 90.0) % 180.0 - 90.0  # unwrapped about the run's start
        self.lo, self.hi, self.n = min(self.lo, rel), max(self.hi, rel), self.n + 1

    @property
    def span(self) -> tuple[float, float]:
        return self.d0 + self.lo, self.d0 + self.hi


def box_misfit(ev: _Evidence, open_sweeps: list[tuple[float, float]]) -> tuple[float, float]:
    """How far the touched outline is from a box's (deg): a box shows faces in two directions
    at right angles, and its corners turn the pad from one face's direction towards the next,
    never across one. Over every orientation β, the faces' mean distance from the nearest of
    β + k·90° — the least: the first figure — and that plus the farthest any sweep crossed a
    direction β + k·90° (by the lesser of its two sides) — the least: the second. A polygon at
    other angles, or a corner opposite a face turning the pad both ways of parallel (a regular
    odd polygon), reads above a box's few tenths of a degree."""
    face = ev.faces / ev.faces_n if ev.faces_n else np.zeros(len(_BETAS))
    if not ev.sweeps and not open_sweeps:
        least = float(face.min())
        return least, least
    if not open_sweeps:
        crossed = ev.crossed()
    elif not ev.sweeps:
        crossed = _crossing(open_sweeps)
    else:  # the farthest of all sweeps, the finished ones' kept
        crossed = np.maximum(ev.crossed(), _crossing(open_sweeps))
    return float(face.min()), float((face + crossed).min())


def _crossing(sweeps: list[tuple[float, float]]) -> np.ndarray:
    """For every β, the farthest any of ``sweeps`` (some) crossed a direction β + k·90°, by
    the lesser of its two sides (deg; 0 where none crossed one)."""
    lo, hi = np.array(sweeps).T
    g = _BETAS[None, :] + 90.0 * np.ceil((lo[:, None] - _BETAS[None, :]) / 90.0)
    cross = np.where(g < hi[:, None], np.minimum(g - lo[:, None], hi[:, None] - g), 0.0)
    crossed: np.ndarray = cross.max(axis=0)
    return crossed


def caliper_slope(ev: _Evidence) -> float:
    """dD/dψ over the run relative to D's mean, D the caliper width (:class:`_Evidence`; least
    squares; 0 before the object turned)."""
    n = ev.lam_n
    if n < 3:
        return 0.0
    vpp = ev.pp_sum - ev.p_sum * ev.p_sum / n
    if vpp < 1e-8:
        return 0.0
    slope = (ev.pd_sum - ev.p_sum * ev.d_mean) / vpp
    return slope / ev.d_mean


def class_features(
    ev: _Evidence, softness: float = 0.0, open_sweeps: list[tuple[float, float]] | None = None
) -> np.ndarray:
    """The class model's input: the shares of each contact kind and of both-flat (parallel or
    not) and both-edge iterations, the curved radii against Λ/2 (median, how far from 1,
    spread), the caliper width's spread and Λ's size, how far the object turned, how σ
    turned with it, how the caliper width changed with it (:func:`caliper_slope`), how soft
    the object reads
    (:attr:`_ContactTrack.softness`), and how far the touched outline is from a box's
    (:func:`box_misfit`, with the edge runs still open)."""
    face_misfit, box = box_misfit(ev, open_sweeps or [])
    total = max(1, ev.flat + ev.edge + ev.curved)
    n = max(1, ev.n)
    q25, q50, q75 = ev.radii.quantiles((0.25, 0.5, 0.75))
    lam_mean = ev.lam_sum / max(1, ev.lam_n)
    return np.array(
        [
            ev.flat / total,
            ev.edge / total,
            ev.curved / total,
            ev.both_flat / n,
            ev.parallel / n,
            ev.both_edge / n,
            q50,
            abs(q50),
            q75 - q25,
            math.log((ev.d_max - ev.d_min) / ev.d_mean + 0.01),
            math.log(lam_mean),
            math.log(math.degrees(ev.psi_max - ev.psi_min) + 0.5),
            max(-2.0, min(2.0, ev.s_ps / ev.s_pp)) if ev.s_pp > 0 else 0.0,
            math.log(abs(caliper_slope(ev)) + 0.01),
            softness,
            math.log(face_misfit + 0.5),
            math.log(box + 0.5),
        ]
    )


class Recognizer:
    """One run's recognition: feed it every rolling iteration, in order."""

    def __init__(self, ctx: ModelContext, model: RecognitionModel | None = None) -> None:
        self.ctx = ctx
        self.model = model or packaged_model()
        self.last = Recognition()
        self._prev: Observation | None = None
        self._psi = 0.0
        self._axis: float | None = None
        self._lam0 = 0.0  # Λ at the grasp
        m = self.model
        self._tracks = (_ContactTrack(Finger.ONE, m), _ContactTrack(Finger.TWO, m))
        self._ev = _Evidence()
        self._sweeps: list[_Sweep | None] = [None, None]  # each pad's open edge run

    def update(self, obs: Observation, counts1: np.ndarray, counts2: np.ndarray) -> Recognition:
        """This iteration's estimate (the state carried from the iterations before)."""
        if obs.points is None or obs.Lambda is None or obs.sigma is None:
            self._prev = None
            for t in self._tracks:
                t.lost()
            self._end_sweep(0)
            self._end_sweep(1)
            self.last = replace(self.last, kind1=None, kind2=None, radius1=None, radius2=None)
            return self.last
        if self._axis is None:
            self._axis, self._lam0 = obs.sigma, obs.Lambda
        if self._prev is not None:
            d = rolling_turn(self._prev, obs.pose, self.ctx)
            if d is not None and self._prev.sigma is not None:
                self._psi += d
                ds = (obs.sigma - self._prev.sigma + math.pi) % (2 * math.pi) - math.pi
                self._ev.s_ps += d * ds
                self._ev.s_pp += d * d
        self._prev = obs
        ev = self._ev
        ev.psi_min, ev.psi_max = min(ev.psi_min, self._psi), max(ev.psi_max, self._psi)
        nus = []  # each pad's surface direction at its contact
        for track, c, counts in zip(
            self._tracks, (obs.contact1, obs.contact2), (counts1, counts2), strict=True
        ):
            assert c.x3_mm is not None
            nus.append(pad_normal_angle(track.finger, obs.pose, c.x3_mm, self.ctx))
            track.update(c, nus[-1], self._psi, counts)
        (k1, r1), (k2, r2) = self._kinds(obs.Lambda)
        self._gather(obs.Lambda, nus, k1, k2, r1, r2)
        cls, conf, a, b = self._classify()
        if ev.psi_max - ev.psi_min < MIN_TURN_TO_CLASSIFY:  # a grasp alone is no evidence yet
            cls, conf, a, b = None, 0.0, None, None
        self.last = Recognition(
            kind1=k1,
            kind2=k2,
            radius1=r1,
            radius2=r2,
            object_class=cls,
            confidence=conf,
            size_a=a,
            size_b=b,
            rotation=math.degrees(self._psi),
            axis=math.degrees(self._axis) + self._across(cls, a, b),
            side=centre_side(obs.points.A, obs.points.B, nus[0], nus[1]),
        )
        return self.last

    def _across(self, cls: ObjectClass | None, a: float | None, b: float | None) -> float:
        """90° for an ellipse grasped across its minor axis (Λ₀ nearer 2b than 2a), else 0; an
        ellipse of nearly equal axes has no side to tell (the outline would turn 90° with
        every reading)."""
        if cls is not ObjectClass.ELLIPSE or a is None or b is None or a - b < ROUND * a:
            return 0.0
        return 90.0 if abs(self._lam0 - 2 * b) < abs(self._lam0 - 2 * a) else 0.0

    def _kinds(self, lam: float) -> list[tuple[ContactKind | None, float | None]]:
        t1, t2 = self._tracks
        model = self.model.kind
        if model is None or t1.features is None or t2.features is None:
            return [(t1.kind, t1.radius), (t2.kind, t2.radius)]
        # both contacts in one go, their pairwise products expanded once
        x = np.array([_contact_row(t1.features, t2.features, lam),
                      _contact_row(t2.features, t1.features, lam)])  # fmt: skip
        xx = expand(x) if model.quadratic else None
        ps = model.probabilities(x, xx)
        out: list[tuple[ContactKind | None, float | None]] = []
        a = self.model.smoothing
        for row, me in enumerate((t1, t2)):
            p = ps[row]
            me.p = p if me.p is None or a <= 0.0 else a * me.p + (1.0 - a) * p
            kind = KINDS[int(np.argmax(me.p))]
            radius = None
            if kind is ContactKind.CURVED:
                # the radius model's products are among the kind model's: picked, not made anew
                sub = None if xx is None else xx[row].take(_sub_expansion(x.shape[1]))
                radius = self._radius(me, x[row, :RADIUS_FEATURES], sub)
            out.append((kind, radius))
        return out

    def _radius(
        self, track: _ContactTrack, x: np.ndarray, expanded: np.ndarray | None = None
    ) -> float:
        """A curved contact's radius: the kinematic one, corrected by the radius model (``x``:
        the contact's first RADIUS_FEATURES features; ``expanded``: ``expand(x)``, if known)."""
        fit = self.model.radius
        if fit is None:
            return track.kinematic_radius
        log_ratio = max(-MAX_LOG_CORRECTION, min(fit.predict(x, expanded), MAX_LOG_CORRECTION))
        return min(track.kinematic_radius * math.exp(log_ratio), MAX_RADIUS_MM)

    def _gather(
        self,
        lam: float,
        nus: list[float],
        k1: ContactKind | None,
        k2: ContactKind | None,
        r1: float | None,
        r2: float | None,
    ) -> None:
        ev = self._ev
        # the pads' wedge: how far their surfaces at the contacts are from parallel
        wedge = abs((nus[0] - nus[1] + math.pi / 2) % math.pi - math.pi / 2)
        d = ev.add_width(lam, self._psi, wedge)
        self._trace(nus, (k1, k2))
        if k1 is None or k2 is None:
            return
        ev.n += 1
        for k, r in ((k1, r1), (k2, r2)):
            if k is ContactKind.FLAT:
                ev.flat += 1
            elif k is ContactKind.EDGE:
                ev.edge += 1
            else:
                ev.curved += 1
                assert r is not None
                ev.radii.add(r / (lam / 2))
                ev.ab.add(ellipse_ab(r, d / 2))
        ev.both_edge += k1 is ContactKind.EDGE and k2 is ContactKind.EDGE
        if k1 is ContactKind.FLAT and k2 is ContactKind.FLAT:
            ev.both_flat += 1
            if math.degrees(wedge) < self.model.parallel_deg:
                ev.parallel += 1

    def _trace(self, nus: list[float], kinds: tuple[ContactKind | None, ...]) -> None:
        """The touched outline in the object frame: a flat contact's direction ν − ψ, an edge
        contact's sweep."""
        ev = self._ev
        for i, (nu, kind) in enumerate(zip(nus, kinds, strict=True)):
            d = math.degrees(nu - self._psi)
            if kind is ContactKind.FLAT:
                ev.add_face(d)
            if kind is ContactKind.EDGE:
                sweep = self._sweeps[i]
                if sweep is None:
                    self._sweeps[i] = _Sweep(d)
                else:
                    sweep.add(d)
            else:
                self._end_sweep(i)

    def _end_sweep(self, i: int) -> None:
        sweep, self._sweeps[i] = self._sweeps[i], None
        if sweep is not None and sweep.n >= MIN_SWEEP:
            self._ev.add_sweep(sweep.span)

    def open_sweeps(self) -> list[tuple[float, float]]:
        """The edge runs still going that count already (their sweeps so far)."""
        return [s.span for s in self._sweeps if s is not None and s.n >= MIN_SWEEP]

    def _classify(self) -> tuple[ObjectClass | None, float, float | None, float | None]:
        ev, model = self._ev, self.model.object_class
        if model is None or ev.n == 0:
            return classify(ev, self.model)
        p = model.probabilities(class_features(ev, self.softness(), self.open_sweeps()))
        i = int(np.argmax(p))
        a, b = sizes(CLASSES[i], ev)
        return CLASSES[i], float(p[i]), a, b

    def softness(self) -> float:
        """Both pads' :attr:`_ContactTrack.softness`, averaged."""
        return sum(t.softness for t in self._tracks) / 2

    def summary(self) -> dict[str, Any] | None:
        """The run's estimate for its summary: class, confidence, sizes, rotation (JSON; None
        before a contact was labelled, a class's fields null while none is decided)."""
        r = self.last
        ev = self._ev
        total = ev.flat + ev.edge + ev.curved
        if total == 0:
            return None
        cls = r.object_class
        out: dict[str, Any] = clean_json({  # strict JSON wherever a summary goes
            "object_class": None if cls is None else cls.value,
            "confidence": None if cls is None else r.confidence,
            "size_a_mm": r.size_a,
            "size_b_mm": r.size_b,
            "rotation_deg": r.rotation,
            "rotation_range_deg": math.degrees(ev.psi_max - ev.psi_min),
            "contacts": {
                "flat": ev.flat / total,
                "edge": ev.edge / total,
                "curved": ev.curved / total,
            },
        })  # fmt: skip
        return out


def sizes(cls: ObjectClass, ev: _Evidence) -> tuple[float | None, float | None]:
    """size_a, size_b of a class from the run's Λ, caliper width and curved radii (see
    :class:`Recognition`; a box's second side and a polygon's side length are not measured:
    None)."""
    if ev.lam_n == 0:
        return None, None
    lam_mean = ev.lam_sum / ev.lam_n
    r_med = math.exp(ev.radii.quantiles((0.5,))[0]) * lam_mean / 2 if ev.radii.n else None
    if cls is ObjectClass.CIRCLE:  # the caliper width, not the chord Λ (see _Evidence)
        return ev.d_mean / 2, None
    if cls is ObjectClass.ELLIPSE:
        return ellipse_axes(ev.d_max / 2, ev.d_min / 2, ev.ab.median())
    if cls is ObjectClass.STICK:
        return ev.lam_max, max(2 * r_med, 1.0) if r_med is not None else None
    if cls is ObjectClass.BOX:
        return lam_mean, None
    return ev.lam_max / 2, None


def ellipse_ab(radius: float, p: float) -> float:
    """a·b of an ellipse whose radius of curvature is ``radius`` where its tangent lies ``p``
    from its centre (half its caliper width there): ρ = (ab)² / p³."""
    return float(math.sqrt(radius) * p**1.5)


def ellipse_axes(widest: float, narrowest: float, ab: float | None) -> tuple[float, float]:
    """An ellipse's semi-axes a ≥ b from the half caliper widths seen (``widest``,
    ``narrowest``) and the product a·b its curvature gave (None: not known). The widths bound
    them, a ≥ widest and b ≤ narrowest; with a·b, one of the two is the bound and the other
    follows (exactly one choice keeps both bounds): a rolling that never turned the object
    across its short axis showed a but not b, and one that never turned it to its long axis b."""
    if ab is None:
        return widest, narrowest
    if ab <= widest * narrowest:
        return widest, ab / widest
    return ab / narrowest, narrowest


def classify(
    ev: _Evidence, m: RecognitionModel
) -> tuple[ObjectClass | None, float, float | None, float | None]:
    """Class, confidence and sizes by rules, without a learned model (None before a label)."""
    total = ev.flat + ev.edge + ev.curved
    if total == 0 or ev.lam_n == 0:
        return None, 0.0, None, None
    f_flat, f_edge, f_curved = ev.flat / total, ev.edge / total, ev.curved / total
    r_med = math.exp(ev.radii.quantiles((0.5,))[0]) if ev.radii.n else 1.0  # radius / (Λ/2)
    if f_curved >= max(f_flat, f_edge):
        if r_med < m.stick_ratio * 2:
            cls, conf = ObjectClass.STICK, f_curved
        elif abs(r_med - 1.0) < m.circle_tol and (ev.d_max - ev.d_min) / ev.d_mean < 0.05:
            cls, conf = ObjectClass.CIRCLE, f_curved
        else:
            cls, conf = ObjectClass.ELLIPSE, f_curved
    elif f_edge > 0.8:
        cls, conf = ObjectClass.STICK, f_edge
    elif ev.both_flat and ev.parallel / ev.both_flat > 0.5:
        cls, conf = ObjectClass.BOX, ev.parallel / ev.both_flat
    else:
        cls, conf = ObjectClass.POLYGON, 1.0 - f_curved
    return (cls, conf, *sizes(cls, ev))


MIN_TURN_TO_CLASSIFY = math.radians(2.0)  # no class before the object has turned this far
ROUND = 0.05  # an ellipse whose axes differ by less than this fraction has no long axis to show
SIDE_TILT = 0.05  # the pads' normals' summed tilt off AB below which they do not tell the side


def centre_side(A: Point, B: Point, nu1: float, nu2: float) -> int:
    """The side of A→B the object's centre lies on: +1 to the left (AB turned +90°), −1 to the
    right, 0 when the pads do not tell. A convex object's surface normals at the ends of a
    chord tilt away from its centre, so the pads' normals (into the object; ``nu1``, ``nu2``
    are the pads' surface directions) tilt towards it; flat faces held parallel do not tilt."""
    uy, uz = B.y - A.y, B.z - A.z
    n = math.hypot(uy, uz)
    if n < 1e-9:
        return 0
    uy, uz = uy / n, uz / n
    tilt = 0.0
    for nu, towards in ((nu1, 1.0), (nu2, -1.0)):
        ny, nz = -math.sin(nu), math.cos(nu)  # a normal of the pad's surface…
        if (ny * uy + nz * uz) * towards < 0:  # …the one into the object (towards the other pad)
            ny, nz = -ny, -nz
        tilt += -ny * uz + nz * uy  # its part along AB turned +90°
    return 0 if abs(tilt) < SIDE_TILT else (1 if tilt > 0 else -1)


def _template(rec: Recognition) -> np.ndarray | None:
    """The class's outline around its centre, x along the object's axis (m × 2, mm)."""
    a, b = rec.size_a, rec.size_b
    if rec.object_class is None or a is None:
        return None
    t = np.linspace(0.0, 2 * math.pi, 96, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)
    if rec.object_class is ObjectClass.CIRCLE:
        return a * circle
    if rec.object_class is ObjectClass.ELLIPSE:
        return np.stack([a * np.cos(t), (b or a) * np.sin(t)], axis=1)
    if rec.object_class is ObjectClass.STICK:
        r = max((b or 2.0) / 2, 0.5)
        half = max(a / 2 - r, 0.0)
        ends = [
            (half + r * np.cos(u), r * np.sin(u))
            for u in np.linspace(-math.pi / 2, math.pi / 2, 24)
        ]
        ends += [
            (-half - r * np.cos(u), -r * np.sin(u))
            for u in np.linspace(-math.pi / 2, math.pi / 2, 24)
        ]
        return np.asarray(ends)
    if rec.object_class is ObjectClass.BOX:
        w, h = a / 2, (b or a) / 2
        return np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
    k = 6  # a polygon of unknown corners: a hexagon of the circumradius
    u = np.linspace(0.0, 2 * math.pi, k, endpoint=False)
    return a * np.stack([np.cos(u), np.sin(u)], axis=1)


def _chords(poly: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The x-range where each line y = offset crosses the convex polygon ``poly`` (NaN where
    it crosses fewer than two edges), all offsets at once."""
    p, q = poly, np.roll(poly, -1, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (offsets[:, None] - p[:, 1]) / (q[:, 1] - p[:, 1])
        xs = p[:, 0] + s * (q[:, 0] - p[:, 0])
    hit = (s >= 0.0) & (s <= 1.0) & np.isfinite(s)
    enough = hit.sum(axis=1) >= 2
    lo = np.where(hit, xs, np.inf).min(axis=1)
    hi = np.where(hit, xs, -np.inf).max(axis=1)
    return np.where(enough, lo, np.nan), np.where(enough, hi, np.nan)


def outline(
    rec: Recognition, a: tuple[float, float], b: tuple[float, float], n: int = 64
) -> np.ndarray:
    """The reconstructed outline in the hand's y0z0 plane (``n`` × 2, mm), placed so that it
    touches the contacts ``a`` (on Finger 1) and ``b`` (on Finger 2) and turned by
    ``rec.rotation``; empty (0 × 2) while no class is known.

    The class's outline, turned to ``axis + rotation``, is placed on the chord parallel to AB
    of AB's length nearest its centre (scaled a little if no chord is that long), so that the
    chord's ends are A and B."""
    shape = _template(rec)
    if shape is None:
        return np.zeros((0, 2))
    ab = np.subtract(b, a)
    lam = float(np.hypot(*ab))
    if lam < 1e-6:
        return np.zeros((0, 2))
    along = math.atan2(ab[1], ab[0])
    turn = math.radians((rec.axis or 0.0) + rec.rotation)
    # a curved surface's normals tell the side of its centre (flat faces' do not): where they
    # do not, the outline is drawn on the chord through its centre, scaled to Λ, if it can be
    side = rec.side if rec.object_class in _CURVED else 0
    placed = None if side else _place(shape, turn - along, lam, None)
    if placed is None:
        placed = _place(shape, turn - along, lam, side)
    if placed is None:  # the turn and the sizes disagree with AB: the shape along AB instead
        placed = _place(shape, 0.0, lam, side)
    if placed is None:
        return np.zeros((0, 2))
    ux, uy = ab / lam
    world = np.stack(
        [placed[:, 0] * ux - placed[:, 1] * uy, placed[:, 0] * uy + placed[:, 1] * ux], 1
    )
    return _resample(world + np.asarray(a, dtype=float), n)


def _place(shape: np.ndarray, rel: float, lam: float, side: int | None = 0) -> np.ndarray | None:
    """``shape`` turned by ``rel`` against AB (along x) with the chord of length Λ parallel to
    x nearest its centre starting at the origin — on the ``side`` of AB its centre lies on
    (+1: +y; 0: either; None: the chord through the centre, scaled to Λ) —; None if that needs
    a scale outside :data:`_SCALE`."""
    c, s = math.cos(rel), math.sin(rel)
    local = shape @ np.array([[c, s], [-s, c]])
    lo, hi = float(local[:, 1].min()), float(local[:, 1].max())
    offsets = np.linspace(lo, hi, 201)[1:-1]
    x0s, x1s = _chords(local, offsets)
    lengths = x1s - x0s
    if side is None:
        bad = np.abs(offsets)
    else:
        bad = np.abs(lengths - lam) + 1e-3 * np.abs(offsets)
        wrong = side * offsets > 0  # the chord at offset y leaves the centre at −y
        if side and not np.isnan(bad[~wrong]).all():
            bad = np.where(wrong, np.nan, bad)
    if np.isnan(bad).all():
        return None
    k = int(np.nanargmin(bad))  # the first of equals, as a scan would keep it
    off, x0, length = float(offsets[k]), float(x0s[k]), float(lengths[k])
    if not _SCALE[0] <= lam / length <= _SCALE[1]:
        return None
    placed: np.ndarray = (local - np.array([x0, off])) * (lam / length)
    return placed


_CURVED = frozenset({ObjectClass.CIRCLE, ObjectClass.ELLIPSE, ObjectClass.STICK})
_SCALE = (0.8, 1.25)  # how far outline() may stretch the estimated sizes to touch A and B


def _resample(poly: np.ndarray, n: int) -> np.ndarray:
    """``n`` points evenly along the closed polygon's perimeter (its corners kept near)."""
    closed = np.vstack([poly, poly[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    u = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.stack([np.interp(u, s, closed[:, 0]), np.interp(u, s, closed[:, 1])], axis=1)


__all__ = ["ContactKind", "ObjectClass", "Recognition", "Recognizer", "outline"]
