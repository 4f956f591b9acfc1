"""One record per rolling iteration: everything the thesis plots (architecture.md, "A Sample").

Angles in degrees, lengths in mm, forces in library units (as the thesis reports them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from sdh2svc.control.rolling import StepResult
from sdh2svc.model.kinematics import HandPose, Point


def _deg(a: float | None) -> float | None:
    return None if a is None else math.degrees(a)


def _yz(p: Point | None) -> tuple[float | None, float | None]:
    return (None, None) if p is None else (p.y, p.z)


@dataclass(frozen=True, slots=True)
class Sample:
    """The flat record of one iteration (None where a quantity does not exist this time)."""

    iteration: int
    t: float  # s since the run started
    phi2: float
    phi3: float
    phi4: float
    phi5: float
    phi2_d: float | None
    phi3_d: float | None
    phi4_d: float | None
    phi5_d: float | None
    S1: float | None
    S2: float | None
    F1: float
    F2: float
    F: float
    dF: float
    Lambda: float | None
    Lambda_ad: float | None
    sigma: float | None
    sigma_d: float | None
    omega_A: float | None
    omega_B: float | None
    Ay: float | None
    Az: float | None
    By: float | None
    Bz: float | None
    Cy: float | None
    Cz: float | None
    Dy: float | None
    Dz: float | None
    direction: int
    stroke: int
    half_strokes: int
    reversal: str | None
    frame_age_ms: float
    joint_age_ms: float  # of the actual angles φ2…φ5 when the iteration took them
    latency_ms: float

    @classmethod
    def columns(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

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
    ) -> Sample:
        """The sample of one iteration; ``pose`` are the actual angles it started from."""
        obs, plan, tg = r.obs, r.plan, r.targets
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
        )  # fmt: skip
