"""Run and safety settings, and the supervisor's checks — independent of the rolling step.

The supervisor never trusts the step: whatever it proposes is clamped to the joint limits and to
a maximum change per iteration, and the run is stopped on a force above the ceiling, on a silent
or stale sensor stream, on a dropped object or when the rotation keeps reversing on the spot.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator

from sdh2svc.control.params import RollingParams
from sdh2svc.control.rolling import Reversal, StepResult
from sdh2svc.model.base import Finite
from sdh2svc.model.hand import AngleDeg, AxisMap, JointLimits

Deg7 = tuple[AngleDeg, ...]
SLOW_CLOSING = 0.5  # an untouched grasp closing below this share of its speed times out (a healthy
# one closes at ≈ 0.96–1.0 of it, on lines as slow as 9600 baud: tests/control/test_runner.py)
# An untouched grasp's pads this close: nothing between them. The margin covers the newest
# angles' age (≤ safety.stale_joint_ms: ≈ 1 mm of each pad at 2 °/s) and the pads' model
MIN_PAD_GAP_MM = 5.0
STALL_S = 2.0  # an untouched grasp is judged on how far it closed over this long: …
SLOWDOWN = 0.5  # …under this share of its own mean speed so far, something stopped it (the
# encoders go on slowly as the fingers' structure yields: 0.6 °/s against 2 °/s in the air)


class RunConfig(Finite):
    """How a run pre-shapes and grasps (config [run])."""

    preshape_deg: Deg7
    preshape_velocity_deg_s: Annotated[float, Field(gt=0.0, le=200.0)]
    grasp_gain_deg_s: Annotated[float, Field(gt=0.0, le=100.0)]
    grasp_max_velocity_deg_s: Annotated[float, Field(gt=0.0, le=100.0)]
    grasp_approach_velocity_deg_s: Annotated[float, Field(gt=0.0, le=100.0)]
    grasp_min_velocity_deg_s: Annotated[float, Field(ge=0.0, le=100.0)]
    grasp_align_gain: Annotated[float, Field(ge=0.0, le=1.0)]
    grasp_settle_s: Annotated[float, Field(ge=0.0, le=60.0)]
    grasp_timeout_s: Annotated[float, Field(gt=0.0, le=600.0)]
    grasp_max_close_deg: Annotated[float, Field(ge=-90.0, le=90.0)]
    # the DSACON32m streams at 30 frames a second at most (protocols.md §1.6): a faster loop
    # would wait for frames that never come (and its grasp close that much slower)
    tactile_rate_hz: Annotated[float, Field(gt=0.0, le=30.0)]

    @field_validator("preshape_deg")
    @classmethod
    def _seven(cls, v: Deg7) -> Deg7:
        if len(v) != 7:
            raise ValueError(f"needs 7 angles, one per wire axis 0…6 (got {len(v)})")
        return v

    @model_validator(mode="after")
    def _grasp_speeds(self) -> RunConfig:
        top = self.grasp_max_velocity_deg_s  # the joints' velocity limit during the grasp
        for key in ("grasp_min_velocity_deg_s", "grasp_approach_velocity_deg_s"):
            if getattr(self, key) > top:
                raise ValueError(f"{key} ({getattr(self, key):g}) must not exceed "
                                 f"grasp_max_velocity_deg_s ({top:g})")  # fmt: skip
        return self

    def speeds_outside(self, vlim: Sequence[float]) -> list[str]:
        """One line per run speed the hand cannot reach (``vlim``: its axes' velocity limits,
        read from it at connect; a run commands each speed on every axis)."""
        if not vlim:
            return []
        top = min(vlim)
        axis = list(vlim).index(top)
        return [
            f"run.{key} = {v:g}: above the hand's velocity limit, {top:g} °/s on axis {axis} "
            f"(its vlim; allowed: {key} ≤ {top:g})"
            for key in ("preshape_velocity_deg_s", "grasp_max_velocity_deg_s")
            if (v := getattr(self, key)) > top
        ]

    def preshape_outside(self, limits: JointLimits) -> list[str]:
        """One line per pre-shape angle outside its axis's joint limits (none: all inside)."""
        bounds = zip(self.preshape_deg, limits.min_deg, limits.max_deg, strict=True)
        return [
            f"run.preshape_deg.{i} = {a:g}: outside axis {i}'s joint limits "
            f"(allowed: {lo:g} ≤ preshape_deg.{i} ≤ {hi:g}, limits.min_deg/max_deg)"
            for i, (a, lo, hi) in enumerate(bounds)
            if not lo <= a <= hi
        ]


class SafetyConfig(Finite):
    """The supervisor's limits (config [safety]). A stale line is lost within a second at most:
    the pre-shape and the release move on joint round trips alone and see the ceiling only
    through fresh tactile frames."""

    max_step_deg: Annotated[float, Field(gt=0.0, le=1.0)]
    force_ceiling_factor: Annotated[float, Field(gt=1.0, le=20.0)]
    # the ceiling's highest, whatever Fd (a run parameter, which the API may change)
    force_ceiling_max: Annotated[float, Field(gt=0.0, le=1000.0)]
    stale_frame_ms: Annotated[float, Field(gt=0.0, le=1000.0)]
    stale_joint_ms: Annotated[float, Field(gt=0.0, le=1000.0)]
    max_consecutive_reversals: Annotated[int, Field(ge=2, le=1000)]

    def ceiling(self, grasp_force: float) -> float:
        """The force ceiling for Fd = ``grasp_force``: factor × Fd, never above the maximum."""
        return min(self.force_ceiling_factor * grasp_force, self.force_ceiling_max)


def params_outside(p: RollingParams, safety: SafetyConfig, section: str = "rolling.") -> list[str]:
    """One line per rolling parameter the supervisor's limits would void (none: all within):
    an Fd whose ceiling the maximum would cut (no headroom left between the grip and the stop),
    and a Finger 1 step the step limit would clip (Finger 1 would lag its plan, which squeezes
    or drops the object, instead of the iteration slowing down as the step means it to).
    Finger 2's k·Δφ beyond the step limit is clipped, not refused: the thesis's sticks roll at
    k = 5 (1.25° a step, Finger 2 following its route at 1°). Each line names its field after
    ``section`` (the configuration's ``rolling.``; the API's fields have none)."""
    out = []
    top = params_maxima(safety)["grasp_force"]
    if p.grasp_force > top:
        out.append(
            f"{section}grasp_force = {p.grasp_force:g}: its ceiling, safety.force_ceiling_factor "
            f"× Fd = {safety.force_ceiling_factor * p.grasp_force:g}, is above "
            f"safety.force_ceiling_max = {safety.force_ceiling_max:g} (allowed: grasp_force ≤ "
            f"{top:g}: a firmer grip needs a higher safety.force_ceiling_max in the configuration)"
        )
    step = safety.max_step_deg
    if p.finger1_max_step_deg > step:
        out.append(
            f"{section}finger1_max_step_deg = {p.finger1_max_step_deg:g}: above "
            f"safety.max_step_deg = {step:g}, the supervisor's step limit (allowed: ≤ {step:g})"
        )
    return out


def params_maxima(safety: SafetyConfig) -> dict[str, float]:
    """The largest value :func:`params_outside` lets through, per parameter it limits: Fd whose
    ceiling the maximum does not cut, and Finger 1's step within the supervisor's."""
    return {
        "grasp_force": safety.force_ceiling_max / safety.force_ceiling_factor,
        "finger1_max_step_deg": safety.max_step_deg,
    }


def params_schema(safety: SafetyConfig, configured: RollingParams) -> dict[str, Any]:
    """The rolling parameters' JSON schema with the ranges this configuration allows: a form
    built from it offers no value the supervisor's limits would refuse (:func:`params_maxima`
    lowers the fields' own maxima where they are tighter). Each field's ``default`` is the
    configuration's value, what a field left out of a run's parameters falls back to before
    any patch (the model's own defaults are for parameters recorded before a field existed)."""
    schema = RollingParams.model_json_schema()
    for key, value in configured.model_dump(mode="json").items():
        schema["properties"][key]["default"] = value
    for key, top in params_maxima(safety).items():
        field = schema["properties"][key]
        if top < field.get("maximum", math.inf):
            field["maximum"] = top
    return schema


class Fault(StrEnum):
    """Why a run stopped on its own."""

    NO_CONTACT = "no_contact"  # the grasp found nothing
    FORCE_CEILING = "force_ceiling"
    STALE_SENSOR = "stale_sensor"
    DROPPED = "dropped"  # both contacts lost while rolling
    STUCK = "stuck"  # reversing again and again without a half stroke
    JOINT_ERROR = "joint_error"
    SENSOR_ERROR = "sensor_error"
    INTERNAL = "internal_error"  # an unexpected error in the run's own code (a bug)


class OutsideLimits(ValueError):
    """An axis beyond its joint limits by more than one step: no target keeps it within them
    and moves it at most one step."""


def clamp_targets(
    targets: Sequence[float],
    current: Sequence[float],
    lo: Sequence[float],
    hi: Sequence[float],
    max_step: float,
) -> tuple[float, ...]:
    """Targets moved at most ``max_step`` from ``current`` and kept within [lo, hi] (degrees).
    A target that is no finite number holds its axis where it is (a NaN would otherwise clamp
    to a step towards the lower limit). :class:`OutsideLimits` if an axis stands beyond its
    limits by more than ``max_step`` (it sagged or was moved there unpowered, or the limits
    were narrowed since): clipped to the limit, its target would be a larger step."""
    out = []
    for axis, (t, c, a, b) in enumerate(zip(targets, current, lo, hi, strict=True)):
        if c < a - max_step or c > b + max_step:
            raise OutsideLimits(f"axis {axis} is at {c:.1f}°, outside its joint limits "
                                f"[{a:g}, {b:g}]° by more than one step ({max_step:g}°): "
                                "move it within them with the hand off, or widen the "
                                "limits")  # fmt: skip
        if not math.isfinite(t):
            t = c
        t = min(c + max_step, max(c - max_step, t))
        out.append(min(b, max(a, t)))
    return tuple(out)


# --- the supervisor's decisions: pure, one per fault, None while all is well --------------------


@dataclass(frozen=True, slots=True)
class Violation:
    """A reason to stop the run: which fault, and in words."""

    fault: Fault
    message: str


def stale_s(safety: SafetyConfig) -> float:
    """The oldest a tactile frame may be (and the longest to wait for one), seconds."""
    return safety.stale_frame_ms / 1000


def frame_age(age_s: float | None, safety: SafetyConfig) -> Violation | None:
    """A frame ``age_s`` old is too old; ``None``: none came within :func:`stale_s`."""
    stale = stale_s(safety)
    if age_s is None:
        return Violation(Fault.STALE_SENSOR, f"no tactile frame for {stale * 1000:.0f} ms")
    if age_s > stale:
        return Violation(Fault.STALE_SENSOR, f"tactile frame {age_s * 1000:.0f} ms old")
    return None


def joint_age(age_s: float | None, safety: SafetyConfig) -> Violation | None:
    """The newest joint reading ``age_s`` old is too old (``None``: none yet): the joint line is
    lost as surely as a silent tactile stream, and nothing may move on angles that old."""
    if age_s is None or age_s > safety.stale_joint_ms / 1000:
        shown = "no" if age_s is None else f"{age_s * 1000:.0f} ms old"
        return Violation(Fault.JOINT_ERROR, f"joint angles: {shown} reading "
                         f"(limit {safety.stale_joint_ms:.0f} ms)")  # fmt: skip
    return None


def force_ceiling(F1: float, F2: float, grasp_force: float, safety: SafetyConfig,
                  ) -> Violation | None:  # fmt: skip
    """Either pad's force above the ceiling (:meth:`SafetyConfig.ceiling`). Each pad, not the
    grip's F (their mean): one pad alone can press hard while the other barely touches (an
    object wedged against it, a person's press), and would reach twice the ceiling unseen."""
    limit = safety.ceiling(grasp_force)
    pad, F = (1, F1) if F1 >= F2 else (2, F2)
    if F > limit:
        factor = safety.force_ceiling_factor
        if limit < factor * grasp_force:
            return Violation(Fault.FORCE_CEILING, f"F{pad} = {F:.2f} above the ceiling's "
                             f"maximum {limit:g} (safety.force_ceiling_max)")  # fmt: skip
        return Violation(Fault.FORCE_CEILING, f"F{pad} = {F:.2f} above {factor:g} × Fd")
    return None


def dropped(contact1: bool, contact2: bool) -> Violation | None:
    """Both distal contacts lost while rolling: the object is no longer held (or neither pad
    reads it any more: the pads alone cannot tell the two apart)."""
    if not contact1 and not contact2:
        return Violation(Fault.DROPPED, "both contacts lost: the object is no longer held, or "
                         "both distal pads stopped reading it")  # fmt: skip
    return None


def grasp_lost(contact1: bool, contact2: bool, read1: bool = True,
               read2: bool = True) -> Violation | None:  # fmt: skip
    """A pad without its contact as the grasp ends: the pads' turn against their wedge rolled
    the contact off a pad's end, or the object was never held. The rolling would start from
    one contact or none; this is a grasp that failed, not a grasp. ``read1``/``read2``: whether
    each pad read a contact at any frame of the grasp: one that never did while the other held
    the grip is named (a dead pad, or the object touching that finger off its distal pad)."""
    if contact1 and contact2:
        return None
    if read1 != read2:
        silent, other = (1, 2) if read2 else (2, 1)
        return Violation(Fault.NO_CONTACT, f"no grasp: Finger {silent}'s distal pad read no "
                         f"contact during the whole grasp while Finger {other}'s gripped (a "
                         f"dead pad, or the object touches Finger {silent} off its distal "
                         "pad)")  # fmt: skip
    lost = "both contacts" if not (contact1 or contact2) else "a contact"
    return Violation(Fault.NO_CONTACT, f"no grasp: {lost} lost as the grasp settled")


def stuck(
    consecutive: int, last: str | None, safety: SafetyConfig, why: str = ""
) -> Violation | None:
    """More reversals in a row than allowed (``last``: the latest one's reason; ``why``: what
    the contacts say of it, added to the message)."""
    if consecutive > safety.max_consecutive_reversals:
        said = f"{consecutive} reversals in a row without a half stroke (last: {last})"
        return Violation(Fault.STUCK, f"{said}: {why}" if why else said)
    return None


def one_contact_lost(F1: float, F2: float, present1: bool, present2: bool) -> str:
    """Which pad lost its contact while the other holds one, in words ("" unless exactly one
    did): the object slid off that pad, or the pad stopped reading — the frames alone cannot
    tell the two apart, so both are said."""
    if present1 == present2:
        return ""
    gone, held, F = (1, 2, F2) if present2 else (2, 1, F1)
    return (f"Finger {gone}'s distal pad reads no contact while Finger {held}'s reads "
            f"F{held} = {F:.2f} (the object slid off that pad, or the pad stopped "
            "reading)")  # fmt: skip


def rolling_step(r: StepResult, grasp_force: float, safety: SafetyConfig) -> Violation | None:
    """A rolling iteration's verdict, the checks in order: force ceiling, dropped, stuck."""
    c1, c2, n = r.obs.contact1, r.obs.contact2, r.state.consecutive_reversals
    why = ""
    if r.reversal == Reversal.CONTACT_LOST:
        why = one_contact_lost(c1.force, c2.force, c1.present, c2.present)
    return (
        force_ceiling(c1.force, c2.force, grasp_force, safety)
        or dropped(c1.present, c2.present)
        or stuck(n, r.reversal, safety, why)
    )


def grasp_timeout(
    F: float,
    grasp_force: float,
    now: float,
    started: float,
    run: RunConfig,
    untouched: tuple[float, float] | None = None,
    waiting: tuple[int, float, float] | None = None,
) -> Violation | None:
    """Still under Fd ``run.grasp_timeout_s`` after ``started`` (clock seconds): the grasp's
    start, or the first touch once a pad has touched. ``untouched``, while nothing has touched
    (``started`` is then the grasp's start): how far the proximal joints closed since (°), and
    how fast the grasp commands them to (°/s). An untouched grasp whose fingers still close at
    ``SLOW_CLOSING`` of that speed or more goes on: the smallest objects are touched after
    ≈ 20 s of closing, :func:`pads_met` ends an approach that meets nothing and
    :func:`grasp_stalled` one that something stops. An untouched finger's increments follow on
    from its previous target and cover the time since the last frame, so neither slow lines nor
    a loop held up slow it; fingers that do not follow their targets do (an axis moving slower
    than commanded): that grasp times out, and its message says so rather than only "no
    grasp". ``waiting``, once one pad has touched and the other has read nothing yet (the first
    waits for it): (that finger's number, how far its proximal joint closed since the touch
    (°), the speed commanded (°/s)); the timeout counts from the touch all the same, and a
    finger slower than ``SLOW_CLOSING`` of that speed is named in its message."""
    if F >= grasp_force or now <= started + run.grasp_timeout_s:
        return None
    msg = f"no grasp (F = {F:.2f} < Fd = {grasp_force}) within {run.grasp_timeout_s:g} s"
    if untouched is not None:
        closed_deg, commanded = untouched
        speed = closed_deg / (now - started)
        if speed >= SLOW_CLOSING * commanded:
            return None
        msg += (f"; untouched, the fingers closed at {speed:.2f}°/s of the "
                f"{commanded:g}°/s commanded: they lag behind their targets (an axis that "
                "moves slower than commanded)")  # fmt: skip
    elif waiting is not None:
        finger, closed_deg, commanded = waiting
        speed = closed_deg / (now - started)
        if speed < SLOW_CLOSING * commanded:
            msg += (f"; Finger {finger}'s pad has read nothing, and it closed at {speed:.2f}°/s "
                    f"of the {commanded:g}°/s commanded since the other touched: it lags "
                    "behind its targets (an axis that moves slower than commanded)")  # fmt: skip
    return Violation(Fault.NO_CONTACT, msg)


def pads_met(gap_mm: float, *, lost: bool = False) -> Violation | None:
    """A grasp with nothing touched whose distal pads came within ``MIN_PAD_GAP_MM`` of each
    other (:func:`~sdh2svc.model.kinematics.pad_gap`): nothing is between them, and pressed
    together the pads would read as a grip on nothing. (On the default pre-shape it ends an
    empty grasp at ≈ 10° of proximal closing, long before :func:`closed_empty`.) ``lost``: a
    pad had touched, and nothing touches now (the object taken away, or the pads gone dead)."""
    if gap_mm < MIN_PAD_GAP_MM:
        what = "the contact was lost and the fingers closed" if lost else "fingers closed"
        return Violation(Fault.NO_CONTACT, f"{what} without touching anything (the pads "
                         f"{max(gap_mm, 0.0):.1f} mm apart)")  # fmt: skip
    return None


def grasp_stalled(window_deg: float, window_s: float, closed_deg: float, since_s: float,
                  commanded: float, *, lost: bool = False) -> Violation | None:  # fmt: skip
    """A grasp with nothing touched whose proximal joints closed ``window_deg`` over the last
    ``window_s`` (≥ ``STALL_S``), slower than ``SLOWDOWN`` of their own mean speed since the
    grasp began (``closed_deg`` in ``since_s``): something stopped the fingers where no distal
    pad senses it (a link, the thumb, an object between pads that do not sense). Fingers slow
    from the start time out instead (:func:`grasp_timeout`). ``lost``: a pad had touched
    before (the pads may have gone dead on the object)."""
    if window_s < STALL_S or since_s <= 0.0:
        return None
    # (the mean no faster than commanded: a finger that fell behind and catches up is no stall)
    rate, mean = window_deg / window_s, min(closed_deg / since_s, commanded)
    if rate < SLOWDOWN * mean:
        what = "no pad reads the contact any more, and " if lost else ""
        return Violation(Fault.NO_CONTACT, f"{what}the fingers stopped closing with nothing "
                         f"touched ({rate:.2f}°/s over the last {window_s:.1f} s, after "
                         f"{mean:.2f}°/s; {commanded:g}°/s commanded): something stops them "
                         "where no distal pad senses it")  # fmt: skip
    return None


def closed_empty(wire_deg: Sequence[float], axes: AxisMap, run: RunConfig) -> Violation | None:
    """A proximal joint (φ2 or φ4) closed past ``run.grasp_max_close_deg``: nothing in between."""
    if max(wire_deg[axes.phi2], wire_deg[axes.phi4]) > run.grasp_max_close_deg:
        return Violation(Fault.NO_CONTACT, "fingers closed without touching anything")
    return None
