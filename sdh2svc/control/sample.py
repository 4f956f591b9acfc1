"""One record per rolling iteration: everything the thesis plots (architecture.md, "A Sample").

Angles in degrees, lengths in mm, forces in library units (as the thesis reports them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any, TypeVar

from sdh2svc.control.recognition import ContactKind, ObjectClass, Recognition
from sdh2svc.control.rolling import StepResult
from sdh2svc.model.kinematics import HandPose, Point


def _deg(a: float | None) -> float | None:
    return None if a is None else math.degrees(a)


def _yz(p: Point | None) -> tuple[float | None, float | None]:
    return (None, None) if p is None else (p.y, p.z)


_E = TypeVar("_E", bound=StrEnum)


def _doc(text: str, unit: str | None = None, *, optional: bool = False) -> Any:
    """A field's description and its unit (None: a count, a sign or a name), for the MCAP
    export's schema, the CSV export's header and the API's docs; ``optional``: None unless
    given (the recognition's fields)."""
    meta = {"doc": f"{text}, {unit}" if unit else text, "unit": unit}
    return field(default=None, metadata=meta) if optional else field(metadata=meta)


def _est(text: str, unit: str | None = None) -> Any:
    return _doc(text, unit, optional=True)


@dataclass(frozen=True, slots=True)
class Sample:
    """The flat record of one iteration (None where a quantity does not exist this time)."""

    iteration: int = _doc("iteration number of the rolling loop (count)")
    t: float = _doc("time since the run started", "s")
    phi2: float = _doc("Finger 1 proximal joint angle φ2, actual", "deg")
    phi3: float = _doc("Finger 1 distal joint angle φ3, actual", "deg")
    phi4: float = _doc("Finger 2 proximal joint angle φ4, actual", "deg")
    phi5: float = _doc("Finger 2 distal joint angle φ5, actual", "deg")
    phi2_d: float | None = _doc("φ2 target commanded this iteration", "deg")
    phi3_d: float | None = _doc("φ3 target commanded this iteration", "deg")
    phi4_d: float | None = _doc("φ4 target commanded this iteration", "deg")
    phi5_d: float | None = _doc("φ5 target commanded this iteration", "deg")
    S1: float | None = _doc("contact height on Finger 1's distal pad (tactile centroid)", "mm")
    S2: float | None = _doc("contact height on Finger 2's distal pad (tactile centroid)", "mm")
    F1: float = _doc("contact force on Finger 1's distal pad", "library force units")
    F2: float = _doc("contact force on Finger 2's distal pad", "library force units")
    F: float = _doc("mean contact force (F1 + F2)/2", "library force units")
    dF: float = _doc("change of F since the previous iteration", "library force units")
    Lambda: float | None = _doc("distance Λ = |AB| between the contact points", "mm")
    Lambda_ad: float | None = _doc("held distance Λad planned for the next step", "mm")
    sigma: float | None = _doc("inclination σ of AB in the y0z0 plane", "deg")
    sigma_d: float | None = _doc("desired inclination σd of the next step", "deg")
    omega_A: float | None = _doc(
        "angle ωA between AB and Finger 1's pad tangent at A (planned when a plan exists)", "deg"
    )
    omega_B: float | None = _doc(
        "angle ωB between BA and Finger 2's pad tangent at B (planned when a plan exists)", "deg"
    )
    Ay: float | None = _doc("contact point A on Finger 1, y0", "mm")
    Az: float | None = _doc("contact point A on Finger 1, z0", "mm")
    By: float | None = _doc("contact point B on Finger 2, y0", "mm")
    Bz: float | None = _doc("contact point B on Finger 2, z0", "mm")
    Cy: float | None = _doc("Finger 1's distal joint C, y0", "mm")
    Cz: float | None = _doc("Finger 1's distal joint C, z0", "mm")
    Dy: float | None = _doc("Finger 2's distal joint D, y0", "mm")
    Dz: float | None = _doc("Finger 2's distal joint D, z0", "mm")
    direction: int = _doc("rotation direction of Finger 2's step, sign of Δφ (+1 | -1)")
    stroke: int = _doc("back-and-forth strokes completed (count)")
    half_strokes: int = _doc("direction reversals that ended a half stroke so far (count)")
    reversal: str | None = _doc("why the direction reversed this iteration (null: it did not)")
    frame_age_ms: float = _doc("age of the tactile frame when the iteration used it", "ms")
    joint_age_ms: float = _doc(
        "age of the actual joint angles φ2…φ5 when the iteration took them", "ms"
    )
    latency_ms: float = _doc("time from the frame's arrival to the targets on the joint line", "ms")
    alpha: float | None = _doc(
        "half-angle α of the friction cones from this iteration on: the configured α, widened to "
        "what the grasp and the contacts held (null: not recorded)",
        "deg",
        optional=True,
    )
    # recognition while rolling (control.recognition), from the tactile frames and angles only
    contact1_kind: str | None = _est(
        "what touches Finger 1's distal pad: flat | edge | curved (null: no contact or estimate)"
    )
    contact2_kind: str | None = _est("what touches Finger 2's distal pad: flat | edge | curved")
    radius1: float | None = _est("local radius of curvature at Finger 1's curved contact", "mm")
    radius2: float | None = _est("local radius of curvature at Finger 2's curved contact", "mm")
    object_class: str | None = _est(
        "the object's estimated class: box | polygon | ellipse | circle | stick (null: undecided)"
    )
    class_confidence: float | None = _est("confidence in object_class, 0…1")
    size_a: float | None = _est(
        "estimated size a: circle radius, ellipse semi-axis a, the box's side held between the "
        "pads, stick length, polygon circumradius",
        "mm",
    )
    size_b: float | None = _est(
        "estimated size b: ellipse semi-axis b (from the narrowest width seen and the product "
        "a·b the curved contacts' radii give), stick diameter; null for a box "
        "and a polygon (their other sides are not measured)",
        "mm",
    )
    rotation_est: float | None = _est(
        "the object's estimated rotation since the grasp (rolling kinematics)", "deg"
    )
    axis_est: float | None = _est(
        "direction of the reconstructed outline's first axis (size_a's) at the grasp: σ of AB "
        "then, or σ + 90° for an ellipse held across its short axis; the outline turns to "
        "axis_est + rotation_est",
        "deg",
    )
    outline_side: int | None = _est(
        "the side of A→B the object's centre lies on, from the pads' normals: +1 left (AB "
        "turned +90°), -1 right, 0 not told (faces held parallel)"
    )

    @classmethod
    def columns(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def descriptions(cls) -> dict[str, str]:
        """Every field's description, with its unit."""
        return {f.name: str(f.metadata["doc"]) for f in fields(cls)}

    @classmethod
    def units(cls) -> dict[str, str | None]:
        """Every field's unit (None where it has none: a count, a sign, a reason)."""
        return {f.name: f.metadata["unit"] for f in fields(cls)}

    @classmethod
    def csv_header(cls) -> tuple[str, ...]:
        """The CSV export's header: each column as ``name [unit]`` (a bare name without one)."""
        return tuple(n if u is None else f"{n} [{u}]" for n, u in cls.units().items())

    def row(self) -> tuple[object, ...]:
        return tuple(getattr(self, name) for name in self.columns())

    @classmethod
    def from_step(
        cls,
        r: StepResult,
        pose: HandPose,
        t: float,
        frame_age_ms: float,
        joint_age_ms: float,
        latency_ms: float,
        rec: Recognition | None = None,
        commanded: HandPose | None = None,
    ) -> Sample:
        """The sample of one iteration; ``pose`` are the actual angles it started from, ``rec``
        what the recognition made of it (None: no estimate, its fields null), ``commanded`` the
        targets as sent (the step's, clamped by the supervisor; default: the step's)."""
        obs, plan = r.obs, r.plan
        tg = commanded if commanded is not None else r.targets
        pts = obs.points
        ay, az = _yz(pts.A if pts else None)
        by, bz = _yz(pts.B if pts else None)
        cy, cz = _yz(pts.C if pts else None)
        dy, dz = _yz(pts.D if pts else None)
        phi = pose.degrees()
        phi_d = tg.degrees() if tg else (None, None, None, None)
        return cls(
            iteration=r.state.iteration, t=t,
            phi2=phi[0], phi3=phi[1], phi4=phi[2], phi5=phi[3],
            phi2_d=phi_d[0], phi3_d=phi_d[1], phi4_d=phi_d[2], phi5_d=phi_d[3],
            S1=obs.contact1.S_mm, S2=obs.contact2.S_mm,
            F1=obs.contact1.force, F2=obs.contact2.force, F=r.F, dF=r.dF,
            Lambda=obs.Lambda, Lambda_ad=plan.Lambda_ad if plan else None,
            sigma=_deg(obs.sigma), sigma_d=_deg(plan.sigma_d) if plan else None,
            omega_A=_deg(plan.omega_A_d) if plan else _deg(obs.omega_A),
            omega_B=_deg(plan.omega_B_d) if plan else _deg(obs.omega_B),
            Ay=ay, Az=az, By=by, Bz=bz, Cy=cy, Cz=cz, Dy=dy, Dz=dz,
            direction=r.state.direction, stroke=r.state.strokes,
            half_strokes=r.state.half_strokes,
            reversal=r.reversal.value if r.reversal else None,
            frame_age_ms=frame_age_ms, joint_age_ms=joint_age_ms, latency_ms=latency_ms,
            alpha=math.degrees(r.alpha), **_recognized(rec),
        )  # fmt: skip

    def recognition(self) -> Recognition | None:
        """The recognition this sample recorded (None: none); the inverse of ``from_step``'s
        ``rec``, for whoever draws it (the reconstructed outline)."""
        if self.rotation_est is None:
            return None
        return Recognition(
            kind1=_enum(ContactKind, self.contact1_kind),
            kind2=_enum(ContactKind, self.contact2_kind),
            radius1=self.radius1, radius2=self.radius2,
            object_class=_enum(ObjectClass, self.object_class),
            confidence=self.class_confidence or 0.0,
            size_a=self.size_a, size_b=self.size_b, rotation=self.rotation_est,
            axis=self.axis_est, side=self.outline_side or 0,
        )  # fmt: skip


def _enum(kind: type[_E], value: str | None) -> _E | None:
    try:
        return None if value is None else kind(value)
    except ValueError:  # a value this version does not know: as if undecided
        return None


def _recognized(rec: Recognition | None) -> dict[str, Any]:
    """The Sample's recognition fields of ``rec`` (all null without one)."""
    if rec is None:
        return {}
    return {
        "contact1_kind": None if rec.kind1 is None else rec.kind1.value,
        "contact2_kind": None if rec.kind2 is None else rec.kind2.value,
        "radius1": rec.radius1, "radius2": rec.radius2,
        "object_class": None if rec.object_class is None else rec.object_class.value,
        "class_confidence": None if rec.object_class is None else rec.confidence,
        "size_a": rec.size_a, "size_b": rec.size_b,
        "rotation_est": rec.rotation, "axis_est": rec.axis, "outline_side": rec.side,
    }  # fmt: skip
