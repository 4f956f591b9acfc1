"""The grasp as a pure step: how far each coupled finger closes on one fresh frame (hand-model §8,
step 1), from the two distal contacts and the actual joint angles; and :class:`GraspWatch`, when
the grasp holds or has failed. No I/O, no clock.

The thesis (and SCHUNK's demo) close both fingers in a mirror pose at a speed proportional to
Fd − F. Our additions:

* **An approach speed of its own.** A finger whose pad reads nothing closes at
  ``approach_velocity_deg_s``, not at the force law's limit: it sets how far the first pad to
  touch presses on before its frame shows the touch (config/default.toml says what it cost).
* **A floor on the closing speed** while F < Fd: the proportional law approaches Fd
  asymptotically, and on a soft object or a small contact (little force per degree) it does not
  reach Fd before the grasp's timeout.
* **The pads' wedge.** Closing with the distal links held parallel presses a contact wherever
  the pad happens to meet the object; on the pads' arcs (a large object held high, a corner)
  the two pad normals are tilted apart, (ωA + ωB)/2 − 90° (the wedge) is as large as the
  friction cone, and the rolling cannot start: both directions leave a cone. Once the grip
  holds (F ≥ Fd), both pads turn so that the wedge shrinks by a fraction ``align_gain`` per
  frame, each pad by the same change of its ω, so that the object's tilt against the pads,
  ωA − ωB, is left as it is. Each pad turns about its contact, not its joint: the proximal
  joint follows so that the contact keeps its distance to the other one (to first order).
  Turned about the joint, a pad pressed on a rigid object squeezes it: F rose to ≈ 2·Fd
  during the turn, and the rubber and the fingers' yield under that force put Λ at grasp
  2–4 mm short on wide objects.
* **No finger opens while the grip is short of Fd.** Each finger closes by its own pad's force,
  but once both pads touch, the two forces on the object are equal whatever the pads read: a
  pad reading higher than the other (gains apart, a needle's end between texels) had its finger
  open while the other closed, and the grip's F crept towards Fd without reaching it.
* **The first pad to touch waits for the other** (closes at the speed floor until the other pad
  touches too): closing on at full speed, it pushes the object before the other pad holds it —
  a soft object is pressed a millimetre deep by the time the other finger arrives, and the
  person (or fixture) placing it takes it back; a light object is pushed off its place.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

from sdh2svc.control import safety
from sdh2svc.control.plan import grip_force
from sdh2svc.control.safety import RunConfig, Violation
from sdh2svc.model.contact import ContactEstimate
from sdh2svc.model.friction import omega, wedge
from sdh2svc.model.hand import AxisMap
from sdh2svc.model.kinematics import Finger, HandGeometry, HandPose, Point, contact_point, pad_gap
from sdh2svc.model.observe import ModelContext

_EPS = math.radians(0.1)  # the finite difference of ω with respect to a distal joint


@dataclass(frozen=True, slots=True)
class GraspLaw:
    """The grasp's closing law (config [run]; angles in degrees, speeds in degrees/s)."""

    grasp_force: float  # Fd
    gain_deg_s: float  # closing speed per force unit below Fd
    max_velocity_deg_s: float
    min_velocity_deg_s: float  # while F < Fd
    approach_velocity_deg_s: float  # a finger whose pad reads nothing
    align_gain: float  # fraction of the pads' wedge taken out per frame; 0: the mirror grasp
    period_s: float  # one frame
    max_step_deg: float  # per joint per frame


@dataclass(frozen=True, slots=True)
class GraspStep:
    """Joint increments (degrees) for φ2, φ3, φ4, φ5, and the pads' wedge the step saw."""

    d_phi: tuple[float, float, float, float]
    wedge_deg: float | None  # (ωA + ωB)/2 − 90°; None without both contacts


def _closing_speed(f: float, law: GraspLaw) -> float:
    """Degrees per second one finger closes for its own contact force ``f`` (negative: it
    opens — above Fd, while the pads turn against their wedge)."""
    speed = (law.grasp_force - f) * law.gain_deg_s
    if f < law.grasp_force:
        speed = max(law.min_velocity_deg_s, speed)
    return max(-law.max_velocity_deg_s, min(law.max_velocity_deg_s, speed))


def _closing_step(c: ContactEstimate, law: GraspLaw, since_s: float) -> float:
    """Degrees one finger closes this frame for its own contact ``c``: by the force law, one
    frame period's worth (a frame held up is a force read late: no further on it); while its
    pad reads nothing, at the approach speed over ``since_s``, the time since the last frame
    (nothing to wait for: a loop held up closes as fast)."""
    if c.present:
        step = _closing_speed(c.force, law) * law.period_s
    else:
        step = law.approach_velocity_deg_s * since_s
    return max(-law.max_step_deg, min(step, law.max_step_deg))


def _omega(finger: Finger, pose: HandPose, mine: ContactEstimate, other_point: Point,
           ctx: ModelContext) -> float:  # fmt: skip
    """ω at ``finger``'s contact for ``pose``, the other contact held at ``other_point``."""
    assert mine.r_mm is not None and mine.theta_rad is not None and mine.x3_mm is not None
    prox, dist = pose.finger(finger)
    here = contact_point(finger, prox, dist, mine.r_mm, mine.theta_rad, ctx.geom)
    return omega(finger, prox + dist, mine.x3_mm, here, other_point, ctx.geom.pad)


def _other_point(finger: Finger, pose: HandPose, other: ContactEstimate,
                 ctx: ModelContext) -> Point:  # fmt: skip
    """The other finger's contact point."""
    assert other.r_mm is not None and other.theta_rad is not None
    o = Finger.TWO if finger is Finger.ONE else Finger.ONE
    oprox, odist = pose.finger(o)
    return contact_point(o, oprox, odist, other.r_mm, other.theta_rad, ctx.geom)


def _slope(finger: Finger, pose: HandPose, mine: ContactEstimate, other_point: Point,
           ctx: ModelContext) -> tuple[float, float]:  # fmt: skip
    """ω at ``finger``'s contact (rad) and its change per radian of the finger's distal joint."""
    w = _omega(finger, pose, mine, other_point, ctx)
    prox, dist = pose.finger(finger)
    turned = pose.with_finger(finger, prox, dist + _EPS)
    return w, (_omega(finger, turned, mine, other_point, ctx) - w) / _EPS  # ≈ ±1


def _pivot(finger: Finger, pose: HandPose, mine: ContactEstimate, other_point: Point,
           ctx: ModelContext) -> float:  # fmt: skip
    """The proximal turn per radian of distal turn that keeps the contact's distance to the
    other contact (to first order): the pad then turns about its contact instead of its joint,
    and aligning it does not squeeze the object. 0 where the proximal joint cannot help
    (it would move the contact across AB rather than along it)."""
    assert mine.r_mm is not None and mine.theta_rad is not None
    prox, dist = pose.finger(finger)
    r, th, g = mine.r_mm, mine.theta_rad, ctx.geom
    p = contact_point(finger, prox, dist, r, th, g)
    pd = contact_point(finger, prox, dist + _EPS, r, th, g)
    pp = contact_point(finger, prox + _EPS, dist, r, th, g)
    n = math.hypot(other_point.y - p.y, other_point.z - p.z)
    uy, uz = (other_point.y - p.y) / n, (other_point.z - p.z) / n
    gd = uy * (pd.y - p.y) + uz * (pd.z - p.z)
    gp = uy * (pp.y - p.y) + uz * (pp.z - p.z)
    if abs(gp) < 0.2 * math.hypot(pp.y - p.y, pp.z - p.z):
        return 0.0
    return -gd / gp


def grasp_step(
    pose: HandPose,
    c1: ContactEstimate,
    c2: ContactEstimate,
    law: GraspLaw,
    ctx: ModelContext,
    since_s: float | None = None,
) -> GraspStep:
    """The increments of one grasp frame: each finger closes (proximal in, distal out by the
    same angle, so the pad keeps its orientation) and, once both contacts are present, turns
    its distal joint against the pads' wedge. Every increment is within ±``max_step_deg``.
    ``since_s``: the time since the previous frame (default: one period)."""
    lim = law.max_step_deg

    def clip(x: float) -> float:
        return max(-lim, min(lim, x))

    since = law.period_s if since_s is None else max(0.0, since_s)
    s1, s2 = _closing_step(c1, law, since), _closing_step(c2, law, since)
    if c1.present and c2.present and grip_force(c1, c2) < law.grasp_force:
        # the grip (their mean) short of Fd: no finger opens. Both pads press one free object
        # equally hard, so a difference between them is the pads' (their gains, a contact
        # smaller than the texel pitch): one finger then opened as fast as the other closed,
        # the object travelled sideways and the mean crept towards Fd without reaching it
        s1, s2 = max(s1, 0.0), max(s2, 0.0)
    floor = law.min_velocity_deg_s * law.period_s  # the first to touch waits for the other
    if c1.present and not c2.present:
        s1 = min(s1, floor)
    elif c2.present and not c1.present:
        s2 = min(s2, floor)
    a1 = a2 = p1 = p2 = 0.0
    wedge_deg: float | None = None
    if c1.r_mm is not None and c2.r_mm is not None:
        b_point = _other_point(Finger.ONE, pose, c2, ctx)
        a_point = _other_point(Finger.TWO, pose, c1, ctx)
        wa, sa = _slope(Finger.ONE, pose, c1, b_point, ctx)
        wb, sb = _slope(Finger.TWO, pose, c2, a_point, ctx)
        wedge_deg = math.degrees(wedge(wa, wb))
        if law.align_gain > 0 and min(abs(sa), abs(sb)) > 0.2:  # else AB lies along a tangent
            # each pad turns about its contact (the proximal joint follows): turning about the
            # joint would press the pad into the object. What squeezing remains (the contact
            # rolls along the pad), the room takes out: none at 2·Fd, where the fingers open.
            # Below Fd a pad turns about its joint: the squeeze it adds helps the grip form.
            f = (c1.force + c2.force) / 2 / law.grasp_force
            room = max(0.0, min(1.0, 2.0 - f))
            a1 = room * clip(-law.align_gain * wedge_deg / sa)
            a2 = room * clip(-law.align_gain * wedge_deg / sb)
            if f >= 1.0:
                p1 = a1 * _pivot(Finger.ONE, pose, c1, b_point, ctx)
                p2 = a2 * _pivot(Finger.TWO, pose, c2, a_point, ctx)

    return GraspStep((clip(s1 + p1), clip(-s1 + a1), clip(s2 + p2), clip(-s2 + a2)), wedge_deg)


class Held:
    """:meth:`GraspWatch.observe`'s answer once the grasp holds: the rolling may start."""


HELD: Final = Held()


@dataclass(slots=True)
class GraspWatch:
    """When the grasp holds, and when it has failed, one fresh frame at a time: the grasp's
    supervision (docs/safety.md), pure — the caller passes the time. The frame's force law is
    :func:`grasp_step`'s."""

    run: RunConfig
    axes: AxisMap
    geom: HandGeometry
    contact_force_min: float  # a pad's force that counts as a touch
    alpha_deg: float  # the settling ends early once the wedge is within α/2
    align: bool  # the pads turn against their wedge (GraspLaw.align_gain > 0)
    approach_deg_s: float  # what a finger whose pad reads nothing is commanded
    started: float  # when the grasp began
    # the timeout counts from the first touch once there is one: a small object is far from
    # the pre-shape, and the closing takes most of the timeout before it touches
    touched: float | None = None
    at_touch: tuple[float, ...] | None = None  # the angles then
    opened: tuple[float, ...] | None = None  # the angles at the grasp's first frame
    settle_until: float | None = None  # once held: the settling's end
    read: list[bool] = field(default_factory=lambda: [False, False])  # each pad ever touched
    progress: deque[tuple[float, float]] = field(default_factory=deque)  # (t, closed °) untouched

    def observe(
        self, now: float, c1: ContactEstimate, c2: ContactEstimate, fd: float,
        actual: tuple[float, ...], pose: HandPose, wedge_deg: float | None,
    ) -> Held | Violation | None:  # fmt: skip
        """One frame: :data:`HELD`, a violation that ends the run, or None (close on)."""
        F = grip_force(c1, c2)
        self.read = [self.read[0] or c1.present, self.read[1] or c2.present]
        if self.opened is None:
            self.opened = actual
        if F >= fd:  # held; the pads may still turn against their wedge for a while
            self.settle_until = self.settle_until or now + self.run.grasp_settle_s
        if self.settle_until is not None:
            # (once held, F may dip below Fd while the pads turn: the settling ends the grasp,
            # not the timeout; the rolling's force band takes F back to Fd)
            wedge_ok = wedge_deg is None or abs(wedge_deg) <= self.alpha_deg / 2
            if (F >= fd and (wedge_ok or not self.align)) or now >= self.settle_until:
                return safety.grasp_lost(c1.present, c2.present, *self.read) or HELD
        elif v := self._failed(now, c1, c2, F, fd, actual, pose):
            return v
        return safety.closed_empty(actual, self.axes, self.run)

    def _failed(
        self, now: float, c1: ContactEstimate, c2: ContactEstimate, F: float, fd: float,
        actual: tuple[float, ...], pose: HandPose,
    ) -> Violation | None:  # fmt: skip
        """Before the grip holds: out of time, stalled untouched, or the pads met on nothing."""
        touching = max(c1.force, c2.force) > self.contact_force_min
        if self.touched is None and touching:
            self.touched, self.at_touch = now, actual
        since = self.started if self.touched is None else self.touched
        assert self.opened is not None
        closed = self._closed(self.opened, actual)
        free = self.approach_deg_s
        untouched = None if self.touched is not None else (closed, free)
        waiting = self._waiting(actual)
        if v := safety.grasp_timeout(F, fd, now, since, self.run, untouched, waiting):
            return v
        if touching:
            self.progress.clear()  # the stall's window counts untouched frames only
            return None
        # nothing touched yet, or a touch lost (the object taken away; dead pads)
        lost = self.touched is not None
        window_deg, window_s = self._approach(now, closed)
        return safety.grasp_stalled(
            window_deg, window_s, closed, now - self.started, free, lost=lost
        ) or safety.pads_met(pad_gap(pose, self.geom), lost=lost)

    def _approach(self, now: float, closed: float) -> tuple[float, float]:
        """How far (°) an untouched grasp closed over its last ``safety.STALL_S`` at least, and
        over how long (s): ``progress`` keeps the frames since, and the one before."""
        self.progress.append((now, closed))
        while len(self.progress) > 1 and self.progress[1][0] <= now - safety.STALL_S:
            self.progress.popleft()
        t0, closed0 = self.progress[0]
        return closed - closed0, now - t0

    def _waiting(self, actual: Sequence[float]) -> tuple[int, float, float] | None:
        """The finger whose pad has read nothing since the other's touched (at ``at_touch``):
        (1 or 2, how far (°) its proximal joint closed since, the approach speed in °/s)."""
        if self.at_touch is None or self.read[0] == self.read[1]:
            return None
        finger, axis = (2, self.axes.phi4) if self.read[0] else (1, self.axes.phi2)
        return finger, abs(actual[axis] - self.at_touch[axis]), self.approach_deg_s

    def _closed(self, opened: Sequence[float], actual: Sequence[float]) -> float:
        """How far (°) the proximal joints closed, on average, from ``opened`` to ``actual``."""
        i, j = self.axes.phi2, self.axes.phi4
        return (abs(actual[i] - opened[i]) + abs(actual[j] - opened[j])) / 2
