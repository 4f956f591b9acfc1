"""Validation of the simulated world: contact mechanics and the tactile sensor model."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from sdh2svc.config import Settings, load_config
from sdh2svc.connect import hand_model
from sdh2svc.model.friction import omega
from sdh2svc.model.geometry import pad_point_from_L, virtual_joint
from sdh2svc.model.kinematics import (
    Finger,
    HandPose,
    Point,
    contact_point,
    finger_ik,
    segment,
)
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import Shape, get_object, parse_object
from sdh2svc.sim.physics import DISTAL1, DISTAL2, PALM, PROXIMAL1, PROXIMAL2

rad, deg = math.radians, math.degrees
OPEN = [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0]


def quiet(**extra: str) -> Settings:
    """Defaults with sensor noise and creep off (deterministic readings), and the sensor at the
    library's nominal gain, so the library-unit grasp thresholds below mean small true forces."""
    sets = ["sim.sensor.noise=false", "sim.sensor.creep=false", "sim.sensor.gain_vs_library=1.0"]
    return load_config(overrides=[*sets, *(f"{k}={v}" for k, v in extra.items())], use_env=False)


class Rig:
    """A PhysicsWorld driven directly in degrees, as the joint emulator would."""

    def __init__(self, cfg: Settings, name: str | Shape) -> None:
        self.cfg, self.ctx = cfg, cfg.model_context()
        shape = get_object(name) if isinstance(name, str) else name
        self.w = PhysicsWorld(hand_model(cfg), cfg.sim, shape)
        self.q = list(OPEN)
        self.t = 0.0
        self.move(self.q)

    def move(self, q: list[float], dt: float = 0.02) -> None:
        self.q = list(q)
        self.t += dt
        self.w.move_joints(self.t, self.q, [True] * 7)

    def roll_step(self) -> None:
        """Finger 2 one Δφ = 0.25° along its route (k = 2), Finger 1 mirroring it."""
        q = self.q
        q[5] -= 0.25
        q[6] += 0.5
        q[1] += 0.25
        q[2] -= 0.5
        self.move(q)

    def counts(self) -> np.ndarray:
        return self.w.tactile_frame(self.t, [0.5] * 6, [0] * 6)

    def distal(self, frame: np.ndarray):
        a = self.cfg.axes
        off = np.cumsum([0] + [r * c for r, c in self.w.matrix_shapes])
        m = [
            frame[off[i] : off[i + 1]].reshape(13, 6)
            for i in (a.finger1_distal_matrix, a.finger2_distal_matrix)
        ]
        return self.ctx.contact(m[0]), self.ctx.contact(m[1])

    def force(self) -> float:
        c1, c2 = self.distal(self.counts())
        return (c1.force_library + c2.force_library) / 2

    def grasp(self, fd: float = 2.0, mirror_distal: bool = True) -> None:
        """Close the coupled fingers in a mirror pose until the library force reaches fd."""
        while self.force() < fd:
            q = self.q
            assert q[1] < 40, "no grasp"
            q[1] += 0.05
            q[5] += 0.05
            if mirror_distal:
                q[2] -= 0.05
                q[6] -= 0.05
            self.move(q)
        assert self.w.truth().held

    def contact(self, surface: str):
        return next(c for c in self.w.truth().contacts if c.surface == surface)


def true_AB(rig: Rig) -> tuple[Point, Point]:
    return Point(*rig.contact("distal1").point), Point(*rig.contact("distal2").point)


def measured_AB(rig: Rig) -> tuple[Point, Point]:
    """A and B as the controller sees them: joint angles + where on each pad the contact is."""
    geom, q = rig.cfg.hand, rig.q
    vj1 = virtual_joint(*pad_point_from_L(rig.contact("distal1").s_mm, geom.pad))
    vj2 = virtual_joint(*pad_point_from_L(rig.contact("distal2").s_mm, geom.pad))
    A = contact_point(Finger.ONE, rad(q[1]), rad(q[2]), *vj1, geom)
    B = contact_point(Finger.TWO, rad(q[5]), rad(q[6]), *vj2, geom)
    return A, B


def test_stick_finger1_on_circle_around_B() -> None:
    """Finger 1 turns A around B (thesis §3.3), as the controller would command it from what it
    measures: the contacts stay put on both pads, Λ stays, σ follows — while ωA stays inside the
    cone (here ωA grows by ≈1.2° per 0.25° of σ, so 12 steps stay inside 90° ± 31°)."""
    cfg = quiet()
    rig = Rig(cfg, "stick98")
    rig.grasp()
    geom, lim = cfg.hand, cfg.finger_limits(Finger.ONE)
    A0, B0 = measured_AB(rig)
    lam0, sig0 = segment(A0, B0)
    s1, s2 = rig.contact("distal1").s_mm, rig.contact("distal2").s_mm
    sig_true0 = segment(*true_AB(rig))[1]
    for step in range(1, 13):
        r, theta = virtual_joint(*pad_point_from_L(rig.contact("distal1").s_mm, geom.pad))
        sigma = sig0 - rad(0.25) * step
        A = Point(B0.y - lam0 * math.cos(sigma), B0.z - lam0 * math.sin(sigma))
        sol = finger_ik(Finger.ONE, A, r, theta, (rad(rig.q[1]), rad(rig.q[2])), geom, lim).solution
        assert sol is not None
        rig.move([*rig.q[:1], deg(sol.proximal), deg(sol.distal), *rig.q[3:]])
        t = rig.w.truth()
        assert t.held and t.slips == 0
        lam, sig = segment(*true_AB(rig))
        assert lam == pytest.approx(98.46, abs=0.2)
        assert deg(sig - sig_true0) == pytest.approx(deg(sigma - sig0), abs=0.3)
    assert rig.contact("distal1").s_mm == pytest.approx(s1, abs=1.0)
    assert rig.contact("distal2").s_mm == pytest.approx(s2, abs=1.0)


def test_circle_rolls_by_the_arc_length_relation() -> None:
    cfg = quiet(**{"sim.physics.gravity_m_per_s2": "[0.0, 0.0, 0.0]"})
    rig = Rig(cfg, "cylinder")
    rig.grasp()
    R = 34.0
    c0 = rig.contact("distal2")
    ang0 = math.atan2(c0.object_point[1], c0.object_point[0])
    for _ in range(60):  # Finger 2 follows its route, Finger 1 keeps the grip by the mirror
        rig.roll_step()
    t = rig.w.truth()
    assert t.held and t.slips == 0
    c1 = rig.contact("distal2")
    ang1 = math.atan2(c1.object_point[1], c1.object_point[0])
    on_object = R * abs(math.remainder(ang1 - ang0, 2 * math.pi))
    on_pad = abs(c1.s_mm - c0.s_mm)
    assert on_pad > 3.0  # it really rolled
    assert on_pad == pytest.approx(on_object, rel=0.05)


def omega_A(rig: Rig) -> float:
    """ωA from the truth: the pad tangent at the true contact against the true A→B."""
    geom, q = rig.cfg.hand, rig.q
    x3 = pad_point_from_L(rig.contact("distal1").s_mm, geom.pad)[0]
    A, B = true_AB(rig)
    return omega(Finger.ONE, rad(q[1] + q[2]), x3, A, B, geom.pad)


def test_tilting_out_of_the_cone_slips_then_drops() -> None:
    """With two contacts the forces act along AB: the contacts slip when ω leaves 90° ± α.
    Soft fingers (1 N/mm): this mirror tilt also squeezes, and stiffer fingers stall their
    joints at the torque limit before the cone is left. The squeeze keeps growing while the
    egg slides along the pads towards their tips (≈ 37 N when it leaves them): the distal
    motors are given the torque for it (the stock 1.4 N·m stall them first, holding it)."""
    cfg = quiet(**{"sim.physics.finger_stiffness_n_per_mm": "1.0",
                   "sim.physics.torque_limit_distal_n_mm": "5000.0"})  # fmt: skip
    rig = Rig(cfg, "egg")
    rig.grasp()
    alpha = math.atan(get_object("egg").material.friction)
    omega_at_slip = None
    for _ in range(600):
        before = omega_A(rig)
        q = rig.q
        q[2] += 0.2  # both pads turn their normals away from AB, mirror-symmetrically
        q[6] += 0.2
        rig.move(q)
        t = rig.w.truth()
        if omega_at_slip is None and t.slips:
            omega_at_slip = before
        if t.dropped:
            break
        assert not t.blocked_axes  # the pads really turned as commanded
        assert abs(omega_A(rig) - math.pi / 2) < alpha + rad(1.0)  # never held outside the cone
    assert omega_at_slip is not None and t.dropped
    assert deg(abs(omega_at_slip - math.pi / 2)) == pytest.approx(deg(alpha), abs=1.0)


def test_squeezing_harder_raises_force_and_reading_monotonically() -> None:
    cfg = quiet()
    rig = Rig(cfg, "egg")
    rig.grasp(fd=0.5)
    forces, sums = [], []
    for _ in range(10):
        q = rig.q
        q[1] += 0.05
        q[5] += 0.05
        rig.move(q)
        forces.append(rig.contact("distal1").normal_force_n)
        sums.append(int(rig.counts().astype(np.int64).sum()))
    assert all(b > a for a, b in itertools.pairwise(forces))
    assert all(b > a for a, b in itertools.pairwise(sums))


def test_creep_raises_the_reading_under_constant_load() -> None:
    # at the configured gain: at the nominal one a grasp step on stiff fingers saturates cells
    cfg = load_config(overrides=["sim.sensor.noise=false"], use_env=False)
    rig = Rig(cfg, "egg")
    rig.grasp()
    readings = []
    for _ in range(8):
        rig.move(rig.q, dt=1.0)
        readings.append(int(rig.counts().astype(np.int64).sum()))
    assert all(b > a for a, b in itertools.pairwise(readings))
    assert readings[-1] > readings[0] * 1.05
    true_n = rig.contact("distal1").normal_force_n
    rig.move(rig.q, dt=1.0)
    assert rig.contact("distal1").normal_force_n == pytest.approx(true_n)  # the load is constant


def test_tactile_centroid_matches_true_contact() -> None:
    """The raw centroid S lies within a texel half-pitch (±1.7 mm) of the true contact."""
    pad = load_config(use_env=False).hand.pad
    row0 = pad.pad_base_to_active_mm + pad.sensor_active_length_mm / 2 + 6 * 3.4
    checked = 0
    for height in (110.0, 117.0, 124.0, 131.0, 138.0):
        cfg = quiet(**{"sim.object_height_mm": str(height)})
        rig = Rig(cfg, "egg")
        rig.grasp()
        c1, _ = rig.distal(rig.counts())
        s_true = row0 - rig.contact("distal1").s_mm
        if 0.0 <= s_true <= 40.8:
            assert c1.S_mm == pytest.approx(s_true, abs=1.7)
            checked += 1
    assert checked >= 4


def test_box_end_face_turns_onto_its_edge() -> None:
    """Turning the rubber block against pad 1: face–face contact (pressure over the whole end
    face) changes to face–edge (on a corner), seen on the tactile pad as a jump of S."""
    cfg = quiet()
    rig = Rig(cfg, "rubber")
    rig.grasp()
    geom, lim = cfg.hand, cfg.finger_limits(Finger.ONE)
    A0, B0 = measured_AB(rig)
    lam0, sig0 = segment(A0, B0)
    # face–face: on the end face, away from its edges (the face overhangs the 16 mm flat part)
    assert abs(rig.contact("distal1").object_point[1]) < 9.0
    assert (
        rig.distal(rig.counts())[0].blobs[0].last_row
        - rig.distal(rig.counts())[0].blobs[0].first_row
        >= 3
    )
    S = [rig.distal(rig.counts())[0].S_mm]
    for step in range(1, 8):
        r, theta = virtual_joint(*pad_point_from_L(rig.contact("distal1").s_mm, geom.pad))
        sigma = sig0 + rad(0.25) * step
        A = Point(B0.y - lam0 * math.cos(sigma), B0.z - lam0 * math.sin(sigma))
        sol = finger_ik(Finger.ONE, A, r, theta, (rad(rig.q[1]), rad(rig.q[2])), geom, lim).solution
        assert sol is not None
        rig.move([*rig.q[:1], deg(sol.proximal), deg(sol.distal), *rig.q[3:]])
        assert rig.w.truth().held
        S.append(rig.distal(rig.counts())[0].S_mm)
    corner = rig.contact("distal1").object_point
    assert abs(corner[1]) > 9.0 and abs(corner[0]) > 29.0  # on the edge (corner radius 1 mm)
    assert max(abs(b - a) for a, b in itertools.pairwise(S)) > 2 * 3.4  # a jump of ≥ 2 rows


def test_same_calls_same_frames() -> None:
    """The world is deterministic for a seed (noise and creep on)."""

    def run() -> list[bytes]:
        cfg = load_config(overrides=["sim.sensor.gain_vs_library=1.0"], use_env=False)
        rig = Rig(cfg, "egg")
        rig.grasp()
        out = []
        for _ in range(5):
            q = rig.q
            q[5] -= 0.25
            rig.move(q)
            out.append(rig.counts().tobytes())
        return out

    assert run() == run()


def test_finger_pressing_a_stiff_object_stalls_at_its_torque_limit() -> None:
    cfg = quiet()
    rig = Rig(cfg, "egg")
    rig.grasp()
    blocked_seen, lag = False, 0.0
    for _ in range(40):
        q = rig.q
        q[1] += 1.0
        q[5] += 1.0
        actual = rig.w.move_joints(rig.t + 0.02, q, [True] * 7)
        rig.t += 0.02
        if rig.w.truth().blocked_axes:
            blocked_seen = True
        lag = max(lag, q[1] - actual[1], q[5] - actual[5])
        rig.q = list(actual)  # a stalled servo stays where it is
    t = rig.w.truth()
    assert blocked_seen and lag > 0.5
    tau = rig.w.physics.joint_torques_n_mm()
    assert abs(tau["phi2"]) >= cfg.sim.physics.torque_limit_proximal_n_mm  # stalled there
    assert t.held  # pressed hard, but not through the object


# --- lazy stepping: the world steps the physics only every max_joint_step_deg or when read ----


def _press(step_deg: float, eager: bool) -> tuple[float, float]:
    """Drive both proximal joints 3° into the grasped egg in reference steps of ``step_deg``,
    one per 5 ms servo tick (``eager``: the physics stepped at every tick, as before the world
    was lazy). Returns how far Finger 1's proximal joint got and the torque on it."""
    rig = Rig(quiet(), "egg")
    rig.grasp()
    q = list(rig.q)
    start = q[1]
    actual = tuple(q)
    for _ in range(round(3.0 / step_deg)):
        q[1] += step_deg
        q[5] += step_deg
        rig.t += 0.005
        actual = rig.w.move_joints(rig.t, q, [True] * 7)
        if eager:
            rig.w.flush()
    assert rig.w.truth().held and rig.w.truth().blocked_axes
    return actual[1] - start, rig.w.physics.joint_torques_n_mm()["phi2"]


def test_a_lazily_stepped_finger_stalls_within_one_substep_of_an_eager_one() -> None:
    cfg = quiet()
    limit, substep = cfg.sim.physics.torque_limit_proximal_n_mm, cfg.sim.physics.max_joint_step_deg
    eager, _ = _press(0.02, eager=True)
    assert 0.5 < eager < 2.5  # it stalled on the way, well before the reference's 3°
    for step in (0.02, 0.05, substep):  # tiny servo ticks and coarse ones
        got, tau = _press(step, eager=False)
        assert abs(tau) >= limit  # stopped by the torque limit…
        assert eager <= got <= eager + substep + 1e-9  # …within one substep past where it bit


def test_tiny_moves_give_the_frame_and_truth_of_one_move_to_the_same_pose() -> None:
    def rig_at_grasp() -> Rig:
        rig = Rig(quiet(), "egg")
        rig.grasp()
        rig.counts()  # the physics stands at the grasp pose
        return rig

    tiny, once = rig_at_grasp(), rig_at_grasp()
    q = list(tiny.q)
    for _ in range(10):  # 0.2° in all, less than one substep: nothing is stepped meanwhile
        q[1] += 0.02
        q[6] -= 0.02
        tiny.t += 0.005
        assert tiny.w.move_joints(tiny.t, q, [True] * 7) == tuple(q)  # unstalled: the reference
    once.move(q, dt=tiny.t - once.t)
    assert np.array_equal(tiny.counts(), once.counts())
    assert tiny.w.truth() == once.w.truth()


def test_the_physics_steps_once_per_substep_of_joint_motion_or_when_read(monkeypatch) -> None:
    from sdh2svc.sim.physics import ContactPhysics

    rig = Rig(quiet(), "egg")
    rig.grasp()
    rig.counts()
    steps: list[float] = []
    step = ContactPhysics.step
    monkeypatch.setattr(ContactPhysics, "step", lambda self, pose: (steps.append(pose.phi2),
                                                                    step(self, pose)))  # fmt: skip
    q = list(rig.q)
    for _ in range(100):  # 2° in servo ticks of 0.02°
        q[1] += 0.02
        rig.move(q, dt=0.005)
    assert 8 <= len(steps) <= 10  # every 0.25° at most, not at every tick
    rig.counts()  # a tactile frame reads the state at the pose reached
    assert deg(steps[-1]) == pytest.approx(q[1])


def test_a_substep_without_a_balance_is_retried_in_halves(monkeypatch) -> None:
    """A solver that loses its way once (as a warm start past a kink of a thin object's contact
    can) does not drop the object: the way is retried in halves."""
    from sdh2svc.sim.physics import ContactPhysics

    steady, flaky = Rig(quiet(), "egg"), Rig(quiet(), "egg")
    steady.grasp()
    flaky.grasp()
    solve, failures = ContactPhysics._solve, [1]

    def lost_once(self, world, dq):  # type: ignore[no-untyped-def]
        if dq is not None and failures and failures.pop():
            return False
        return solve(self, world, dq)

    steady.roll_step()
    monkeypatch.setattr(ContactPhysics, "_solve", lost_once)
    flaky.roll_step()
    assert not failures and flaky.w.truth().held
    assert flaky.w.physics.hand_pose == steady.w.physics.hand_pose
    assert flaky.w.truth().pose == pytest.approx(steady.w.truth().pose, abs=1e-3)


@pytest.mark.parametrize("multiple", [1, 2, 3])
def test_a_move_of_whole_substeps_takes_that_many(monkeypatch, multiple: int) -> None:
    """0.5° is two 0.25° substeps, not three (radians → degrees gives 0.5000000000000001)."""
    from sdh2svc.sim.physics import ContactPhysics

    rig = Rig(quiet(), "egg")
    rig.grasp()
    phys, calls, substep = rig.w.physics, [], ContactPhysics._substep

    def counted(self, pose, halvings=0):  # type: ignore[no-untyped-def]
        calls.append(halvings)
        return substep(self, pose, halvings)

    monkeypatch.setattr(ContactPhysics, "_substep", counted)
    p, d = phys.hand_pose, math.radians(multiple * phys.cfg.max_joint_step_deg)
    phys.step(HandPose(p.phi2, p.phi3, p.phi4 - d, p.phi5 + d))
    assert calls.count(0) == multiple


# --- the fast paths of the solver and the sensor against their plain definitions -------------


def _yield_reference(phys, overlap: np.ndarray, wds: float) -> float:
    """The finger's yield by plain Newton from e = 0 (the definition in ContactPhysics._yield)."""
    kf, e = phys.cfg.finger_stiffness_n_per_mm, 0.0
    for _ in range(200):
        c = overlap - e
        active, stiff = c > 0.0, c > phys.knee
        force = wds * float(phys._pressure(c[active]).sum())
        slope = kf + wds * (phys.k * np.count_nonzero(active & ~stiff)
                            + phys.k_bottomed * np.count_nonzero(stiff))  # fmt: skip
        step = (force - kf * e) / slope
        if step <= 1e-12:
            break
        e += step
    return e


@pytest.mark.parametrize("name", ["egg", "rubber", "cylinder"])
def test_finger_yield_fast_paths_match_newton_from_zero(name: str) -> None:
    phys = PhysicsWorld(hand_model(quiet()), quiet().sim, get_object(name)).physics
    rng = np.random.default_rng(7)
    wds = phys.width_mm * phys.cfg.sample_spacing_mm
    for trial in range(300):
        scale = (0.2, 1.0, 3.0, 8.0)[trial % 4]  # below and well beyond the pad's knee
        overlap = rng.random(int(rng.integers(1, 120))) * scale
        want = _yield_reference(phys, overlap, wds)
        phys._e_hint[0] = float(rng.random() * 2 * scale)  # any warm start, above or below
        got = phys._yield(overlap, wds, float(overlap.max()), 0)
        assert got == pytest.approx(want, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("name", ["egg", "rubber", "cylinder"])
def test_pressures_are_the_contact_samples_under_the_pad_law(name: str) -> None:
    """The pressures worked out from the last step's compressions are those of the samples still
    pressed once the finger yielded: the pad's law of (overlap − yield), the overlap being the
    depth of the object's surface below the pad along the pad's normal."""
    rig = Rig(quiet(), name)
    rig.grasp()
    phys = rig.w.physics
    x = phys.state.pose
    c, s = math.cos(float(x[2])), math.sin(float(x[2]))
    wds = phys.width_mm * phys.cfg.sample_spacing_mm
    got = phys.pressures()
    assert {DISTAL1, DISTAL2} <= set(got)
    for j, (idx, p) in got.items():
        pts, n, _cols = phys._surface(j)
        R = np.array([[c, -s], [s, c]])
        local = (pts - x[:2]) @ R
        touching = np.nonzero(phys.outline.sdf(local) < 0.0)[0]
        overlap = np.zeros(len(pts))
        overlap[touching] = phys.outline.exit_distance(local[touching], -n[touching] @ R)
        e = _yield_reference(phys, overlap[touching], wds) if j != PALM else 0.0
        want = touching[overlap[touching] > e]
        assert np.array_equal(idx, want)
        assert np.all(p > 0.0)
        assert np.allclose(p, phys._pressure(overlap[want] - e), rtol=1e-6, atol=1e-9)


def test_newton_move_and_surface_columns_match_their_definitions() -> None:
    from sdh2svc.sim.physics import _solve3, to_world

    rng = np.random.default_rng(3)
    for _ in range(50):
        J, r = rng.normal(size=(3, 3)), rng.normal(size=3)
        got = _solve3(J.tolist(), r.tolist())
        assert np.allclose(got, np.linalg.solve(J, -r), rtol=1e-9, atol=1e-12)
    rig = Rig(quiet(), "egg")
    rig.grasp()
    phys = rig.w.physics
    for j, surf in enumerate(phys.surfaces):
        pts, n, cols = phys._surface(j)
        _o, ex, ey = phys._frame_rows[j]
        assert np.allclose(pts, to_world(phys._frame_rows[j], surf.local), atol=1e-9)
        assert np.allclose(n, surf.normal[:, :1] * ex + surf.normal[:, 1:] * ey, atol=1e-12)
        assert np.allclose(cols[:, 2], pts[:, 0] * n[:, 1] - pts[:, 1] * n[:, 0], atol=1e-9)
        assert np.allclose(cols[:, 5], 1.0)
        assert np.allclose(cols[:, 8], surf.s)


def test_link_frames_match_the_kinematics() -> None:
    from sdh2svc.model.kinematics import Finger, HandPose, distal_joint, frame3_axes
    from sdh2svc.sim.physics import link_frame_rows

    geom = quiet().hand
    rng = np.random.default_rng(11)
    for _ in range(20):
        pose = HandPose(*rng.uniform(-1.5, 1.5, 4))
        want = []
        for finger in (Finger.ONE, Finger.TWO):
            prox, dist = pose.finger(finger)
            origin = (0.0 if finger is Finger.ONE else geom.base_offset_mm, 0.0)
            want.append((distal_joint(finger, prox, geom), *frame3_axes(finger, prox + dist)))
            want.append((origin, *frame3_axes(finger, prox)))
        want.append(((0.0, 0.0), (1.0, 0.0), (0.0, 1.0)))
        assert np.allclose(np.array(link_frame_rows(pose, geom)), np.array(want), atol=1e-12)


@pytest.mark.parametrize("name", ["egg", "rubber", "cylinder", "stick74", "triangle"])
def test_samples_inside_match_the_outline_sdf_with_depths_along_the_pad_normal(name: str) -> None:

    triangle = {"kind": "polygon", "vertices_mm": [[-30, -15], [30, -15], [0, 20]], "depth_mm": 8}
    obj = parse_object(triangle) if name == "triangle" else get_object(name)
    w = PhysicsWorld(hand_model(quiet()), quiet().sim, obj)
    phys = w.physics
    rng = np.random.default_rng(4)
    near_j = tuple(range(len(phys.surfaces)))
    for _ in range(20):
        cy, cz, psi = 33.0 + rng.normal() * 3, 100.0 + rng.normal() * 30, rng.normal()
        reach = phys.outline.bound_radius
        inside, depth, _starts, cols = phys._inside(
            near_j, cy, cz, math.cos(psi), math.sin(psi), reach * reach
        )
        pts = cols[:, 3:5]
        c, s = math.cos(psi), math.sin(psi)
        local = (pts - [cy, cz]) @ np.array([[c, -s], [s, c]])  # Rᵀ·(p − c), row-wise
        d = phys.outline.sdf(local)
        want = np.nonzero(d < 0.0)[0]
        # points within rounding of the boundary may fall either way
        edge = np.abs(d) < 1e-9
        assert set(inside.tolist()) - set(np.nonzero(edge)[0].tolist()) == set(
            want.tolist()) - set(np.nonzero(edge)[0].tolist())  # fmt: skip
        # each one's depth: from the sample along −n (into the finger) to the object's surface
        normal = cols[inside, 0:2] @ np.array([[c, -s], [s, c]])
        exit_ = local[inside] - depth[:, None] * normal
        # never less than the distance to the nearest surface (the ellipse's sdf is that only
        # near its boundary, to a µm: see Outline.sdf)
        near, tol = (-d[inside] < 1.0, 1e-3) if name == "egg" else (depth == depth, 1e-9)
        assert np.all(depth[near] >= -d[inside][near] - tol)
        assert np.allclose(phys.outline.sdf(exit_), 0.0, atol=1e-9)


def test_sensor_settings_match_the_emulator_seam_definition() -> None:
    from sdh2svc.sim.world import apply_sensor_settings

    w = PhysicsWorld(hand_model(quiet()), quiet().sim, get_object("egg"))
    rng = np.random.default_rng(9)
    raw = rng.random(w.sensor.offsets[-1]) * 5000
    for sens, thr in (([0.5] * 6, [0] * 6), ([0.1, 0.9, 0.5, 1.0, 0.3, 0.7], [0, 5, 100, 0, 7, 3])):
        want = apply_sensor_settings(raw, w.shapes, sens, thr)
        assert np.array_equal(w.sensor._apply_settings(raw, sens, thr), want)


def test_fast_mode_world_is_bit_for_bit_repeatable() -> None:
    """Warm starts, caches and the Jacobian kept between steps depend only on the calls made."""

    def run() -> tuple[tuple, bytes]:
        rig = Rig(load_config(use_env=False), "egg")  # noise and creep on
        rig.grasp()
        frames = []
        for _ in range(30):
            rig.roll_step()
            frames.append(rig.counts().tobytes())
        return rig.w.truth().pose, b"".join(frames)

    assert run() == run()


# --- the pads' compression: the depth of the object's surface along the pad's normal ---------


def _physics(spec):
    return PhysicsWorld(hand_model(quiet()), quiet().sim, spec).physics


def _place(phys, j: int, k: int, local: np.ndarray, normal: np.ndarray) -> tuple[float, ...]:
    """The object pose (y, z, ψ) that puts the object-frame point ``local`` on sample k of
    surface j, with the object-frame direction ``normal`` along that sample's pad normal."""
    pts, n, _cols = phys._surface(j)
    psi = math.atan2(n[k, 1], n[k, 0]) - math.atan2(normal[1], normal[0])
    c, s = math.cos(psi), math.sin(psi)
    centre = pts[k] - np.array([[c, -s], [s, c]]) @ local
    return float(centre[0]), float(centre[1]), psi


def _stick_end_first(phys, depth: float) -> tuple[float, ...]:
    """A stick along the normal of pad 1's middle sample, its end sunk ``depth`` into the pad."""
    n_samples = len(phys.surfaces[DISTAL1].s)
    half = phys.outline.spec.length_mm / 2
    # the end (half, 0) at depth below the sample; the stick's axis −x along the pad's normal
    return _place(phys, DISTAL1, n_samples // 2, np.array([half - depth, 0.0]),
                  np.array([-1.0, 0.0]))  # fmt: skip


def test_a_thin_stick_pushed_end_first_compresses_the_pad_by_its_whole_protrusion() -> None:
    """2 mm thick: −sdf would stop at the radius (1 mm) and the force with it, letting the pad
    through; along the normal the end sinks by all it protrudes, and the force keeps growing
    (linearly, once the whole rounded end is in)."""
    phys = _physics(get_object("stick98"))
    half, r = get_object("stick98").length_mm / 2, 1.0
    world = phys._world_samples(phys.hand_pose)
    depths = np.arange(0.25, 4.01, 0.25)
    forces = []
    for depth in depths:
        pose = _stick_end_first(phys, float(depth))
        ev = phys._evaluate(pose, world)  # (the stick's far end passes through other surfaces)
        y, z, psi = pose
        _i, got, _s, _c = phys._inside((DISTAL1,), y, z, math.cos(psi), math.sin(psi), 1e4)
        assert got.max() == pytest.approx(depth, abs=1e-9)  # the tip, under the sample
        centroid, _t, n_force = ev.contacts[DISTAL1][:3]
        forces.append(n_force)
        # where pad and stick touch: on the stick's rounded end, never inside it
        c, s = math.cos(psi), math.sin(psi)
        dy, dz = centroid[0] - y, centroid[1] - z
        obj = np.array([[c * dy + s * dz, c * dz - s * dy]])
        # (the pressure's mean of points on the convex end lies a little inside it)
        assert obj[0, 0] > half - r and abs(obj[0, 1]) < r
    assert all(b > a for a, b in itertools.pairwise(forces))
    # beyond the radius each 0.25 mm adds the same force (a constant contact width), until the
    # pad bottoms out on its backing (then the same, larger, force)
    steps = np.diff(forces)[(depths[1:] > 1.5) & (depths[1:] <= phys.knee)]
    assert len(steps) >= 2
    assert np.ptp(steps) < 0.05 * steps.mean()
    assert forces[-1] > 4 * forces[3]  # 4 mm against 1 mm (−sdf: about the same)


def test_fingers_closing_on_a_thin_stick_press_its_ends_and_never_pass_through() -> None:
    """Grasp the 2 mm stick between the fingertips and keep closing: the force grows until the
    motors stall, and each contact stays on its end of the stick."""
    rig = Rig(quiet(), "stick98")
    rig.grasp()
    half, r = get_object("stick98").length_mm / 2, 1.0
    forces = []
    for _ in range(60):
        q = rig.q
        q[1] += 0.05
        q[5] += 0.05
        actual = rig.w.move_joints(rig.t + 0.02, q, [True] * 7)
        rig.t += 0.02
        rig.q = list(actual)
        t = rig.w.truth()
        assert t.held
        for surface in ("distal1", "distal2"):
            x, y = rig.contact(surface).object_point
            assert abs(x) > half - r and abs(y) < r
        if t.blocked_axes:
            break
        forces.append(rig.contact("distal1").normal_force_n)
    assert t.blocked_axes  # pressed to the motors' torque limit, not through the stick
    assert all(b > a for a, b in itertools.pairwise(forces))
    assert forces[-1] > 10.0  # −sdf: ≈ 1.4 N, then the pads slid along the stick


@pytest.mark.parametrize(
    "spec",
    [
        get_object("rubber"),
        {"kind": "box", "width_mm": 60.0, "height_mm": 30.0, "depth_mm": 10.0},
        {"kind": "polygon", "vertices_mm": [[-40, -15], [40, -15], [25, 20], [-30, 18]],
         "depth_mm": 8.0},
    ],
)  # fmt: skip
@pytest.mark.parametrize("j", [PROXIMAL1, PROXIMAL2, PALM])
def test_a_flat_face_pressed_flat_is_compressed_by_its_distance_as_before(spec, j: int) -> None:
    """A face lying flat in a flat pad: along the normal or to the nearest surface, the depth is
    the same (the cases where the two agree do not change)."""
    spec = parse_object(spec) if isinstance(spec, dict) else spec
    phys = _physics(spec)
    o = phys.outline
    v, e, nu = o.vertices, o.edges, o.normals
    phys._world_samples(phys.hand_pose)
    k = len(phys.surfaces[j].s) // 2
    for depth in (0.05, 0.3, 0.8):
        # the first edge's middle, moved out by the rounding radius, sunk by depth below sample k
        local = v[0] + e[0] / 2 + (o.radius - depth) * nu[0]
        y, z, psi = _place(phys, j, k, local, -nu[0])
        reach = o.bound_radius
        inside, got, _starts, cols = phys._inside(
            (j,), y, z, math.cos(psi), math.sin(psi), reach * reach
        )
        c, s = math.cos(psi), math.sin(psi)
        obj = (cols[inside, 3:5] - [y, z]) @ np.array([[c, -s], [s, c]])
        # the samples over the face's flat part, off its ends (nearer the next face there)
        along = (obj - v[0]) @ e[0] / np.linalg.norm(e[0])
        flat = (along > 2.0) & (along < np.linalg.norm(e[0]) - 2.0)
        assert flat.sum() > 20
        assert np.allclose(got[flat], depth, atol=1e-9)
        assert np.allclose(got[flat], -o.sdf(obj[flat]), atol=1e-9)


UPRIGHT = "[0.0, 0.0, -9.81]"  # the hand upright: gravity towards the palm (m/s²)


def _box(mass_g: float, mu: float, stiffness: float = 2.0) -> Shape:
    return parse_object({"kind": "box", "width_mm": 50.0, "height_mm": 20.0, "depth_mm": 15.0,
                         "material": {"mass_g": mass_g, "friction": mu,
                                      "stiffness_n_per_mm3": stiffness}})  # fmt: skip


def _squeeze(rig: Rig, step: float) -> tuple[float, float]:
    """Both coupled fingers one mirror step closer (negative: apart); the distal pads' true
    normal forces."""
    q = rig.q
    q[1] += step
    q[5] += step
    q[2] -= step
    q[6] -= step
    rig.move(q)
    n = {c.surface: c.normal_force_n for c in rig.w.truth().contacts}
    return n.get("distal1", 0.0), n.get("distal2", 0.0)


def test_the_person_placing_a_heavy_object_lets_go_once_the_grip_bears_its_weight() -> None:
    """Gravity on: a 250 g box of μ 0.3 needs 2·μ·N ≥ m·g, N ≥ 4.1 N a pad, and the pads press
    its soft faces deeper than the fixture's overlap limit (1 mm) before that. The person
    placing it keeps holding it (not pulled back as from a finger sweeping through it) until
    the fingers bear its weight; then it hangs between them on friction alone."""
    cfg = quiet(**{"sim.physics.gravity_m_per_s2": UPRIGHT})
    box = _box(250.0, 0.3, stiffness=0.02)
    rig = Rig(cfg, box)
    need = box.material.mass_g / 1000 * 9.81 / (2 * box.material.friction)
    deepest = 0.0
    while rig.w.truth().in_fixture:
        assert rig.q[1] < 40, "never let go"
        n1, n2 = _squeeze(rig, 0.02)
        deepest = max(deepest, rig.w.physics._last.max_depth)
        assert rig.w.physics.state.present, (rig.q[1], n1, n2)
    assert deepest > cfg.sim.physics.fixture_max_overlap_mm
    assert min(n1, n2) > 0.8 * need  # (the pads' rounded ends carry a little of it)
    for _ in range(20):
        _squeeze(rig, 0.02)
        t = rig.w.truth()
        assert t.held and not t.dropped


def test_fingers_that_stop_closing_before_they_bear_the_weight_let_the_object_fall() -> None:
    """Gravity on: the fingers press the 250 g box at about a quarter of the grip its weight
    needs, then stop closing (they dither in place): after a second of a squeeze that no longer
    grows, the person lets go, and it falls. Weightless, that grip holds it (the person let go
    as soon as the fingers held it)."""
    for gravity, falls in ((UPRIGHT, True), ("[0.0, 0.0, 0.0]", False)):
        rig = Rig(quiet(**{"sim.physics.gravity_m_per_s2": gravity}), _box(250.0, 0.3))
        while min(_squeeze(rig, 0.02)) < 1.0:
            assert rig.q[1] < 40, "no touch"
        start = rig.t
        while rig.t - start < 0.9:  # (each move is 0.02 s)
            _squeeze(rig, 0.001 if round((rig.t - start) / 0.02) % 2 else -0.001)
            assert rig.w.truth().in_fixture is falls  # waiting for the fingers, with weight
        for _ in range(10):
            _squeeze(rig, -0.001)
            _squeeze(rig, 0.001)
        t = rig.w.truth()
        assert t.dropped is falls and t.in_fixture is False, (gravity, t)
