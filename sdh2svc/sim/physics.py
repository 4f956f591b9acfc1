"""Planar quasi-static contact mechanics of the two coupled fingers and one object (y0z0 plane).

The fingers are position-controlled bodies; the object is free. Each step finds the object pose
(y, z, ψ) at which the contact forces (and gravity) balance, for the current finger joints:

* Surfaces: both distal pads (the profile of hand-model §3), both proximal pads (flat, along the
  proximal links) and the palm, each sampled every ``sample_spacing_mm`` along its length.
* Normal compliance, an elastic foundation ("Winkler") model: each pad sample that lies inside the
  object by δ carries pressure k·δ (k: pad and object stiffness in series) over its strip of
  pad, pushing along the pad normal. Faces pressed flat spread over many samples; edges and curved
  objects concentrate — which is what the tactile sensor model rasterises.
* Coulomb friction, per contact: a tangential spring anchored where the object and the pad touched
  at the previous step, capped at μ·N. Inside the cap the contact sticks, so the object rolls on
  the pad without slipping; at the cap it slides and a slip is recorded.
* The object starts held by a *fixture* (a person's hand placing it between the fingertips) and
  is released once both distal pads press it; a step without a force balance, or with no contact
  force left on a distal pad, means the object is no longer held: it is dropped.

Joint torques from the contact forces are checked against the motor limits: a joint whose next
step would need more torque stalls at its last angle (the firmware's "blocked"), so a finger
pressing a stiff object stops instead of passing through it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from pydantic import Field
from scipy import optimize

from sdh2svc.model.base import Frozen
from sdh2svc.model.geometry import PadProfile, pad_point_from_L, pad_slope
from sdh2svc.model.kinematics import Finger, HandGeometry, HandPose, distal_joint, frame3_axes
from sdh2svc.sim.objects import Outline

Positive = Annotated[float, Field(gt=0.0)]


class PhysicsConfig(Frozen):
    """Contact mechanics parameters (see config/sim.toml)."""

    pad_stiffness_n_per_mm3: Positive
    pad_thickness_mm: Positive
    backing_stiffness_n_per_mm3: Positive
    finger_stiffness_n_per_mm: Positive
    tangential_stiffness_n_per_mm: Positive
    gravity_m_per_s2: tuple[float, float, float]  # (x0: out of the plane, y0, z0)
    sample_spacing_mm: Annotated[float, Field(gt=0.01, le=2.0)]
    max_joint_step_deg: Annotated[float, Field(gt=0.0, le=5.0)]
    release_force_n: Annotated[float, Field(ge=0.0)]
    fixture_max_overlap_mm: Annotated[float, Field(gt=0.0, le=50.0)]
    proximal_pad_offset_mm: Annotated[float, Field(ge=0.0, le=50.0)]
    proximal_pad_start_mm: Annotated[float, Field(ge=0.0, le=200.0)]
    proximal_pad_end_mm: Annotated[float, Field(ge=0.0, le=200.0)]
    palm_z_mm: float
    pad_width_mm: Positive
    torque_limit_proximal_n_mm: Positive
    torque_limit_distal_n_mm: Positive


# Surfaces, in a fixed order; a surface is a sampled curve in the frame of one link.
DISTAL1, PROXIMAL1, DISTAL2, PROXIMAL2, PALM = range(5)
SURFACE_NAMES = ("distal1", "proximal1", "distal2", "proximal2", "palm")
SURFACE_FINGER = (Finger.ONE, Finger.ONE, Finger.TWO, Finger.TWO, None)


@dataclass(frozen=True, slots=True)
class Surface:
    """Samples of one surface in its link frame: coordinates (a, b) along the link's (ex, ey),
    unit normals and tangents in the same frame, and the surface parameter s (mm) of each sample:
    L from the pad's base for a distal pad, the distance from O along the link for a proximal
    pad, y0 for the palm."""

    index: int
    s: np.ndarray
    local: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    ds: float


def _distal_surface(index: int, pad: PadProfile, spacing: float) -> Surface:
    s = np.arange(spacing / 2, pad.max_L_mm, spacing)
    pts = np.array([pad_point_from_L(L, pad) for L in s])
    slope = np.array([pad_slope(x3, pad) for x3 in pts[:, 0]])
    norm = np.sqrt(1 + slope**2)
    tangent = np.stack([1 / norm, slope / norm], axis=1)
    normal = np.stack([-slope / norm, 1 / norm], axis=1)
    return Surface(index, s, pts, normal, tangent, spacing)


def _straight_surface(
    index: int, start: float, end: float, offset: float, spacing: float
) -> Surface:
    s = np.arange(start + spacing / 2, end, spacing)
    local = np.stack([s, np.full_like(s, offset)], axis=1)
    normal = np.tile([0.0, 1.0], (len(s), 1))
    tangent = np.tile([1.0, 0.0], (len(s), 1))
    return Surface(index, s, local, normal, tangent, spacing)


def build_surfaces(geom: HandGeometry, cfg: PhysicsConfig) -> tuple[Surface, ...]:
    sp = cfg.sample_spacing_mm
    prox = (cfg.proximal_pad_start_mm, cfg.proximal_pad_end_mm, cfg.proximal_pad_offset_mm, sp)
    # the palm: a line at z = palm_z across the hand, normal +z0 (its "link frame" is frame 0)
    palm_s = np.arange(-40.0, geom.base_offset_mm + 40.0, sp)
    palm = Surface(
        PALM, palm_s, np.stack([palm_s, np.full_like(palm_s, cfg.palm_z_mm)], axis=1),
        np.tile([0.0, 1.0], (len(palm_s), 1)), np.tile([1.0, 0.0], (len(palm_s), 1)), sp,
    )  # fmt: skip
    return (
        _distal_surface(DISTAL1, geom.pad, sp),
        _straight_surface(PROXIMAL1, *prox),
        _distal_surface(DISTAL2, geom.pad, sp),
        _straight_surface(PROXIMAL2, *prox),
        palm,
    )


def link_frames(
    pose: HandPose, geom: HandGeometry
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(origin, ex, ey) of each surface's link frame in frame 0, in surface order."""
    frames = []
    for finger in (Finger.ONE, Finger.TWO):
        prox, dist = pose.finger(finger)
        O = np.array([0.0 if finger is Finger.ONE else geom.base_offset_mm, 0.0])
        C = np.array(distal_joint(finger, prox, geom))
        ex_d, ey_d = frame3_axes(finger, prox + dist)
        ex_p, ey_p = frame3_axes(finger, prox)
        frames.append((C, np.array(ex_d), np.array(ey_d)))
        frames.append((O, np.array(ex_p), np.array(ey_p)))
    frames.append((np.zeros(2), np.array([1.0, 0.0]), np.array([0.0, 1.0])))
    return frames


def to_world(frame: tuple[np.ndarray, np.ndarray, np.ndarray], local: np.ndarray) -> np.ndarray:
    o, ex, ey = frame
    return o + local[..., :1] * ex + local[..., 1:2] * ey


def rot(psi: float) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s], [s, c]])


@dataclass(slots=True)
class Anchor:
    """Where object and surface stuck together at the end of the previous step."""

    obj_point: np.ndarray  # object frame
    local_point: np.ndarray  # surface link frame
    u: float  # elastic tangential displacement, mm


@dataclass(frozen=True, slots=True)
class ContactTruth:
    """Ground truth of one contact region (never visible to the controller)."""

    surface: str
    point: tuple[float, float]  # pressure centroid on the surface, frame 0 (y, z)
    s_mm: float  # surface parameter of the centroid (L for a distal pad)
    object_point: tuple[float, float]  # the same point in the object's frame
    normal_force_n: float
    tangential_force_n: float
    slipping: bool


@dataclass(slots=True)
class _Eval:
    residual: np.ndarray
    contacts: dict[int, tuple[np.ndarray, np.ndarray, float, float, np.ndarray, float, bool]]
    pressures: dict[int, tuple[np.ndarray, np.ndarray]]  # surface → (sample indices, pressure)
    max_depth: float = 0.0  # deepest geometric overlap of a surface into the object, mm


@dataclass(slots=True)
class PhysicsState:
    pose: np.ndarray  # object (y, z, ψ) in frame 0
    held_by_fixture: bool = True
    present: bool = False  # placed between the fingers (while in the fixture)
    dropped: bool = False
    anchors: dict[int, Anchor] = field(default_factory=dict)
    slips: int = 0
    slip_distance_mm: float = 0.0
    psi_min: float = math.inf
    psi_max: float = -math.inf
    slipping: set[int] = field(default_factory=set)


class ContactPhysics:
    """The quasi-static world of one object between the coupled fingers."""

    def __init__(self, geom: HandGeometry, cfg: PhysicsConfig, outline: Outline, pose: HandPose,
                 object_pose: tuple[float, float, float]) -> None:  # fmt: skip
        self.geom, self.cfg, self.outline = geom, cfg, outline
        self.surfaces = build_surfaces(geom, cfg)
        spec = outline.spec
        self.width_mm = min(spec.depth_mm, cfg.pad_width_mm)
        kp, ko = cfg.pad_stiffness_n_per_mm3, spec.material.stiffness_n_per_mm3
        self.k = kp * ko / (kp + ko)  # pad and object in series
        # once the pad is squeezed to its backing, only the object (and the backing) yield
        self.knee = cfg.pad_thickness_mm * (1.0 + kp / ko)
        self.k_bottomed = 1.0 / (1.0 / ko + 1.0 / cfg.backing_stiffness_n_per_mm3)
        self.mu = spec.material.friction
        g = np.asarray(cfg.gravity_m_per_s2, dtype=float)
        self.gravity_n = spec.material.mass_g / 1000.0 * g  # (x0, y0, z0) newtons
        self.hand_pose = pose
        self.state = PhysicsState(np.asarray(object_pose, dtype=float))
        self._jacobian: np.ndarray | None = None
        self._last = _Eval(np.zeros(3), {}, {})
        self._substep(pose)

    # --- geometry of one evaluation -----------------------------------------------------------

    def _world_samples(self, pose: HandPose) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        frames = link_frames(pose, self.geom)
        out = []
        self._bounds = []
        for surf, fr in zip(self.surfaces, frames, strict=True):
            pts = to_world(fr, surf.local)
            _, ex, ey = fr
            n = surf.normal[:, :1] * ex + surf.normal[:, 1:2] * ey
            t = surf.tangent[:, :1] * ex + surf.tangent[:, 1:2] * ey
            out.append((pts, n, t))
            self._bounds.append((pts.min(axis=0), pts.max(axis=0)))
        return out

    def _evaluate(
        self, x: np.ndarray, world: list, frames: list | None = None, slip: dict | None = None
    ) -> _Eval:
        """Net force and moment on the object at pose x (the residual), and the contacts.

        Sticking contacts pull with their tangential spring, uncapped; the contacts in ``slip``
        (surface → sign) slide with the Coulomb force μ·N in that direction.
        """
        c, R = x[:2], rot(float(x[2]))
        force = self.gravity_n[1:].copy()
        moment = 0.0
        contacts: dict = {}
        pressures: dict = {}
        max_depth = 0.0
        box = self.outline.half_extent
        wds = self.width_mm * self.cfg.sample_spacing_mm
        reach = self.outline.bound_radius
        for j, (pts, n, t) in enumerate(world):
            lo, hi = self._bounds[j]
            if np.any(c + reach < lo) or np.any(c - reach > hi):
                continue  # this surface is nowhere near the object
            local = (pts - c) @ R  # object frame
            near = np.nonzero(np.all(np.abs(local) <= box, axis=1))[0]
            if near.size == 0:
                continue
            d = self.outline.sdf(local[near])
            inside = d < 0.0
            if not inside.any():
                continue
            idx = near[inside]
            overlap = -d[inside]
            max_depth = max(max_depth, float(overlap.max()))
            # the finger yields along the pad normal (structure and servo, in series with the pad)
            e = 0.0 if SURFACE_FINGER[j] is None else self._yield(overlap, wds)
            keep = overlap > e
            idx, overlap = idx[keep], overlap[keep]
            p = self._pressure(overlap - e)  # N/mm²
            f = (p * wds)[:, None] * n[idx]
            Fn = f.sum(axis=0)
            N = float(np.linalg.norm(Fn))
            arm = pts[idx] - c
            moment += float(np.sum(arm[:, 0] * f[:, 1] - arm[:, 1] * f[:, 0]))
            force += Fn
            w = p / p.sum()
            # where pad and object touch: each pad point pushed back by its overlap (finger
            # yield plus pad compression) lies on the object's surface
            centroid = w @ (pts[idx] - overlap[:, None] * n[idx])
            tan = w @ t[idx]
            tan /= np.linalg.norm(tan)
            u = 0.0
            anchor = self.state.anchors.get(j)
            if anchor is not None and frames is not None:
                obj_now = c + R @ anchor.obj_point
                surf_now = to_world(frames[j], anchor.local_point)
                u = anchor.u + float((obj_now - surf_now) @ tan)
            slipping = slip is not None and j in slip
            ft = slip[j] * self.mu * N if slipping else -self.cfg.tangential_stiffness_n_per_mm * u
            fvec = ft * tan
            force += fvec
            arm_c = centroid - c
            moment += float(arm_c[0] * fvec[1] - arm_c[1] * fvec[0])
            s_centroid = float(w @ self.surfaces[j].s[idx])
            contacts[j] = (centroid, tan, N, ft, u, s_centroid, slipping)
            pressures[j] = (idx, p)
        scale = 1.0 / max(self.outline.bound_radius, 1.0)  # moment in force units
        residual = np.array([force[0], force[1], moment * scale])
        return _Eval(residual, contacts, pressures, max_depth)

    def _pressure(self, compression: np.ndarray) -> np.ndarray:
        """Contact pressure (N/mm²) for a local compression (mm): pad and object in series up
        to the knee where the pad bottoms out on its backing, far stiffer beyond."""
        soft = self.k * np.minimum(compression, self.knee)
        return soft + self.k_bottomed * np.maximum(compression - self.knee, 0.0)

    def _yield(self, overlap: np.ndarray, wds: float) -> float:
        """How far the finger backs off along the pad normal: the root e of
        h(e) = k_f·e − Σ p(δ − e)·w·ds (finger structure and servo in series with the contact).

        h is piecewise linear, increasing and concave, so Newton's method from e = 0 climbs to
        the root from below and lands on it exactly once it reaches the root's segment.
        """
        kf, k, kb, knee = self.cfg.finger_stiffness_n_per_mm, self.k, self.k_bottomed, self.knee
        e = 0.0
        for _ in range(50):
            c = overlap - e
            active = c > 0.0
            stiff = c > knee
            force = wds * float(self._pressure(c[active]).sum())
            slope = kf + wds * (k * float(np.count_nonzero(active & ~stiff))
                                + kb * float(np.count_nonzero(stiff)))  # fmt: skip
            step = (force - kf * e) / slope
            if step <= 1e-12:
                break
            e += step
        return e

    # --- stepping -----------------------------------------------------------------------------

    def step(self, pose: HandPose) -> None:
        """Move the fingers to ``pose`` (in substeps no larger than max_joint_step_deg)."""
        cur = self.hand_pose
        delta = max(abs(a - b) for a, b in zip(
            (pose.phi2, pose.phi3, pose.phi4, pose.phi5),
            (cur.phi2, cur.phi3, cur.phi4, cur.phi5), strict=True))  # fmt: skip
        if delta == 0.0 and not self.state.held_by_fixture:
            return  # quasi-static: nothing moved, nothing changes
        n = max(1, math.ceil(math.degrees(delta) / self.cfg.max_joint_step_deg))
        for i in range(1, n + 1):
            f = i / n
            self._substep(HandPose(
                cur.phi2 + f * (pose.phi2 - cur.phi2), cur.phi3 + f * (pose.phi3 - cur.phi3),
                cur.phi4 + f * (pose.phi4 - cur.phi4), cur.phi5 + f * (pose.phi5 - cur.phi5),
            ))  # fmt: skip

    def _substep(self, pose: HandPose) -> None:
        self.hand_pose = pose
        st = self.state
        frames = link_frames(pose, self.geom)
        world = self._world_samples(pose)
        if st.dropped:
            self._last = _Eval(np.zeros(3), {}, {})
            return
        if st.held_by_fixture:
            ev = self._evaluate(st.pose, world)
            # A person places the object only where the fingers leave room for it, and pulls
            # it back if a finger sweeps through it before the grasp.
            limit = self.cfg.fixture_max_overlap_mm if st.present else 0.0
            st.present = ev.max_depth <= limit
            if not st.present:
                self._last = _Eval(np.zeros(3), {}, {})
                return
            n1 = ev.contacts.get(DISTAL1, (None, None, 0.0))[2]
            n2 = ev.contacts.get(DISTAL2, (None, None, 0.0))[2]
            self._last = ev
            if min(n1, n2) > max(self.cfg.release_force_n, 0.0) and min(n1, n2) > 0.0:
                st.held_by_fixture = False
                self._anchor(ev, st.pose, carry=False)
                self._solve(world, frames)
            return
        self._solve(world, frames)

    def _solve(self, world: list, frames: list) -> None:
        """Find the balancing pose: first with every contact sticking, then with the contacts
        whose friction would exceed μ·N sliding at μ·N (an active set, grown until consistent)."""
        st = self.state
        slip: dict[int, float] = {}
        x, ev, converged = st.pose.copy(), None, False
        for _ in range(len(self.surfaces) + 1):
            x, ev, converged = self._newton(st.pose.copy(), world, frames, slip)
            if not converged:  # a kink (contact appearing, friction switching): MINPACK's hybrid
                x, ev, converged = self._hybrid(st.pose.copy(), world, frames, slip)
            over = {
                j: math.copysign(1.0, c[3])
                for j, c in ev.contacts.items()
                if j not in slip and abs(c[3]) > self.mu * c[2]
            }
            if not converged or not over:
                break
            slip.update(over)
        n1 = ev.contacts[DISTAL1][2] if DISTAL1 in ev.contacts else 0.0
        n2 = ev.contacts[DISTAL2][2] if DISTAL2 in ev.contacts else 0.0
        if not converged or n1 <= 0.0 or n2 <= 0.0:
            st.dropped = True
            st.anchors.clear()
            self._last = _Eval(np.zeros(3), {}, {})
            return
        self._anchor(ev, x, carry=True)
        st.pose = x
        st.psi_min = min(st.psi_min, float(x[2]))
        st.psi_max = max(st.psi_max, float(x[2]))
        self._last = ev

    def _newton(
        self, x: np.ndarray, world: list, frames: list, slip: dict[int, float]
    ) -> tuple[np.ndarray, _Eval, bool]:
        """Damped Newton on the 3 pose coordinates. The Jacobian (finite differences) is kept
        from step to step and refreshed only when a move fails to lower the residual."""
        ev = self._evaluate(x, world, frames, slip)
        tol = 1e-6 + 1e-5 * sum(c[2] for c in ev.contacts.values())
        lim = np.array([2.0, 2.0, math.radians(3.0)])  # a Newton move stays physical
        J, fresh = self._jacobian, False
        for _ in range(60):
            r = ev.residual
            if np.max(np.abs(r)) < tol:
                return x, ev, True
            if J is None:
                J, fresh = self._fd_jacobian(x, r, world, frames, slip), True
            dx = np.linalg.lstsq(J, -r, rcond=None)[0]
            dx *= min(1.0, float(np.min(lim / (np.abs(dx) + 1e-300))))
            base, step = float(np.linalg.norm(r)), 1.0
            while step > 1e-3:
                ev_c = self._evaluate(x + step * dx, world, frames, slip)
                if float(np.linalg.norm(ev_c.residual)) < base:
                    x, ev = x + step * dx, ev_c
                    break
                step /= 2
            else:
                if fresh:
                    return x, ev, False
                J = None  # stale Jacobian: refresh and try again
                continue
            if fresh:
                self._jacobian = J
            elif float(np.linalg.norm(ev.residual)) > 0.25 * base:
                J = None  # slow progress: the kept Jacobian is too far off
        return x, ev, bool(np.max(np.abs(ev.residual)) < tol)

    def _hybrid(
        self, x: np.ndarray, world: list, frames: list, slip: dict[int, float]
    ) -> tuple[np.ndarray, _Eval, bool]:
        """Powell's hybrid method (scipy) as the fallback of :meth:`_newton`."""
        sol = optimize.root(
            lambda v: self._evaluate(v, world, frames, slip).residual, x, method="hybr",
            options={"xtol": 1e-12, "maxfev": 400},
        )  # fmt: skip
        ev = self._evaluate(sol.x, world, frames, slip)
        tol = 1e-6 + 1e-5 * sum(c[2] for c in ev.contacts.values())
        moved = np.abs(sol.x - x)
        sane = moved[0] < 5.0 and moved[1] < 5.0 and moved[2] < math.radians(10.0)
        return sol.x, ev, bool(np.max(np.abs(ev.residual)) < tol) and sane

    def _fd_jacobian(
        self, x: np.ndarray, r: np.ndarray, world: list, frames: list, slip: dict[int, float]
    ) -> np.ndarray:
        h = np.array([1e-4, 1e-4, 1e-5])
        J = np.empty((3, 3))
        for k in range(3):
            xk = x.copy()
            xk[k] += h[k]
            J[:, k] = (self._evaluate(xk, world, frames, slip).residual - r) / h[k]
        return J

    def _anchor(self, ev: _Eval, x: np.ndarray, carry: bool) -> None:
        """Re-anchor every contact at its current centroid, keeping the elastic displacement."""
        st = self.state
        frames = link_frames(self.hand_pose, self.geom)
        c, R = x[:2], rot(float(x[2]))
        anchors = {}
        for j, (centroid, _tan, _n, ft, u, _s, slipping) in ev.contacts.items():
            if slipping:  # the spring keeps only what the Coulomb force stretches
                u_el = -ft / self.cfg.tangential_stiffness_n_per_mm
                st.slips += 0 if j in st.slipping else 1  # count slip onsets, not steps
                st.slip_distance_mm += abs(u - u_el)
                u = u_el
            o, ex, ey = frames[j]
            rel = centroid - o
            local = np.array([rel @ ex, rel @ ey])
            anchors[j] = Anchor(R.T @ (centroid - c), local, u if carry else 0.0)
        st.slipping = {j for j, cinfo in ev.contacts.items() if cinfo[6]}
        st.anchors = anchors

    # --- results ------------------------------------------------------------------------------

    @property
    def held(self) -> bool:
        return not self.state.dropped

    def pressures(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Surface index → (sample indices, pressure N/mm²) of the last step."""
        return self._last.pressures

    def contacts(self) -> list[ContactTruth]:
        x = self.state.pose
        c, R = x[:2], rot(float(x[2]))
        out = []
        for j, (centroid, _t, N, ft, _u, s, slipping) in sorted(self._last.contacts.items()):
            obj = R.T @ (centroid - c)
            out.append(ContactTruth(SURFACE_NAMES[j], (float(centroid[0]), float(centroid[1])), s,
                                    (float(obj[0]), float(obj[1])), N, ft, slipping))  # fmt: skip
        return out

    def joint_torques_n_mm(self) -> dict[str, float]:
        """Torque the contacts put on each coupled joint (N·mm), from the last step's pressures,
        in joint coordinates: positive turns the joint towards larger angles (closing, for the
        proximal joints). Finger 1's joints turn clockwise in the y0z0 plane as their angles
        grow, Finger 2's (mirrored) counter-clockwise, hence the sign per finger."""
        frames = link_frames(self.hand_pose, self.geom)
        world = self._world_samples(self.hand_pose)
        tau = {"phi2": 0.0, "phi3": 0.0, "phi4": 0.0, "phi5": 0.0}
        names = {Finger.ONE: ("phi2", "phi3"), Finger.TWO: ("phi4", "phi5")}
        wds = self.width_mm * self.cfg.sample_spacing_mm
        for j, (idx, p) in self._last.pressures.items():
            finger = SURFACE_FINGER[j]
            if finger is None:
                continue
            pts, n, _ = world[j]
            f = -(p * wds)[:, None] * n[idx]  # force on the finger
            prox_name, dist_name = names[finger]
            O = frames[j + 1][0] if j in (DISTAL1, DISTAL2) else frames[j][0]
            for name, origin in ((prox_name, O), (dist_name, frames[j][0])):
                if name == dist_name and j not in (DISTAL1, DISTAL2):
                    continue
                arm = pts[idx] - origin
                moment = float(np.sum(arm[:, 0] * f[:, 1] - arm[:, 1] * f[:, 0]))
                tau[name] += -moment if finger is Finger.ONE else moment
        return tau
