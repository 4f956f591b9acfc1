"""The simulated hand: contact physics and the tactile sensor model behind the emulators' seam.

:class:`PhysicsWorld` implements :class:`~sdh2svc.sim.world.HandWorld`: the joint-controller
emulator asks where the joints are when its servos pull towards a reference, the tactile emulator
asks what the six pads read. Ground truth (object pose, true contacts and forces, slips, drops)
is available through :meth:`PhysicsWorld.truth` to tests and to the simulator's own telemetry —
never to the controller, which sees only the bytes.

The world steps lazily. The joint emulator reports every 5 ms servo tick, which moves a joint
only a few hundredths of a degree; the contact physics already resolves joint motion in
substeps of ``max_joint_step_deg`` (0.25°), so one physics step per tick would mostly repeat
the same balance. :meth:`PhysicsWorld.move_joints` therefore only records the pose and steps the
physics when the joints would run a whole substep ahead of it, or when something reads the
physical state (a tactile frame, :meth:`~PhysicsWorld.truth`, :attr:`~PhysicsWorld.physics`, a
power change, :meth:`~PhysicsWorld.flush`). The torque limit is checked at every tick against the
last step's contact torques, which are never more than one substep behind: a finger pressing a
stiff object stops within 0.25° of where its torque reached the limit, as with coarse ticks.
Every read of the physical state from outside the joint emulator's stepping first calls
:attr:`PhysicsWorld.before_read`, so that a lazy servo clock (fast mode, :mod:`sdh2svc.sim.lab`)
can step the ticks due by then before anything is read.

The rolling plane model assumes axis 0 (φ1) at 90°, the fingers facing each other. The third
(middle) finger stands outside that plane: its joints follow their references like the others but
touch nothing, and it starts parked out of the way (:data:`MIDDLE_PARKED_DEG`), as the thesis parks
it. Any pad, its two included, reads what a person presses on it (:mod:`sdh2svc.sim.press`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sdh2svc.model.hand import AxisMap, TactileConfig, matrix_pads
from sdh2svc.model.kinematics import HandGeometry, HandPose
from sdh2svc.sim.objects import Outline, Shape, get_object
from sdh2svc.sim.physics import (
    DISTAL1,
    DISTAL2,
    PROXIMAL1,
    PROXIMAL2,
    ContactPhysics,
    ContactTruth,
)
from sdh2svc.sim.press import Press, Presses
from sdh2svc.sim.sensor import PadRaster, TactileSensorModel
from sdh2svc.sim.simconfig import SimConfig

# The middle finger's (proximal, distal) angles at power-on by default (config/sim.toml's
# start_deg), deg: opened away from the coupled fingers, out of their plane of work (thesis
# §2.9), as SCHUNK's grasping demo's start pose and the controller's pre-shape have it.
MIDDLE_PARKED_DEG = (-90.0, 0.0)


@dataclass(frozen=True, slots=True)
class HandModel:
    """What the simulation copies of the real hand (the model's sections of the configuration):
    its geometry, which wire axis and matrix is which, the pads' layouts. Not the controller's
    calibration: the simulated pads have their own (sim.sensor), which it may misjudge."""

    geometry: HandGeometry
    axes: AxisMap
    tactile: TactileConfig


@dataclass(frozen=True, slots=True)
class ObjectNow:
    """The object as the physics last stepped (:meth:`Bench.object_now`)."""

    pose: tuple[float, float, float]  # centre y, z (mm) and angle ψ (rad), frame 0
    held: bool  # by the fingers (not the fixture)
    dropped: bool
    in_fixture: bool
    slips: int  # slip onsets so far
    grip_peak_n: float  # the largest true grip so far (N; physics.PhysicsState.grip_peak_n)


@dataclass(frozen=True, slots=True)
class Truth:
    """What really happens, for tests and the simulator's telemetry."""

    object: str
    size_mm: float
    held: bool
    dropped: bool
    in_fixture: bool
    pose: tuple[float, float, float]  # object centre y, z (mm) and angle ψ (rad)
    contacts: tuple[ContactTruth, ...]
    slips: int
    slip_distance_mm: float
    rotation_range_deg: float
    blocked_axes: tuple[int, ...]

    def summary(self) -> dict[str, Any]:
        """What a run's summary keeps of it (never shown to the controller)."""
        return {"object": self.object, "size_mm": self.size_mm, "dropped": self.dropped,
                "slips": self.slips, "rotation_range_deg": self.rotation_range_deg}  # fmt: skip

    def scene(self, outline: Outline, points: int = 90) -> dict[str, Any]:
        """For the viewers: the object's state and ``points`` of its ``outline`` where it lies
        (hand frame, mm)."""
        y, z, psi = self.pose
        pts = outline.perimeter_points[:: max(1, len(outline.perimeter_points) // points)]
        c, s = math.cos(psi), math.sin(psi)
        world = np.column_stack([y + c * pts[:, 0] - s * pts[:, 1],
                                 z + s * pts[:, 0] + c * pts[:, 1]])  # fmt: skip
        return {
            "object": self.object, "size_mm": self.size_mm, "held": self.held,
            "dropped": self.dropped, "in_fixture": self.in_fixture, "pose": [y, z, psi],
            "slips": self.slips, "outline": np.round(world, 2).tolist(),
            "contacts": [asdict(c) for c in self.contacts],
        }  # fmt: skip


class PhysicsWorld:
    """Three fingers — the two coupled ones in contact with one object, the middle one parked —
    and six tactile pads that a person may press; advances lazily to each ``now``.

    ``_angles`` are the actual joint angles (what :meth:`move_joints` reports): the reference
    of each powered joint that is not stalled, the held angle of a stalled or limp one. The
    contact physics stands at ``_stepped``, at most one substep behind (see the module
    docstring); :meth:`flush` brings it up to ``_angles``.
    """

    def __init__(self, model: HandModel, sim: SimConfig, obj: Shape | None = None) -> None:
        self.model, self.sim = model, sim
        self.axes = model.axes
        layouts = [lay for _, lay in matrix_pads(model.axes, model.tactile)]  # as wired
        self.shapes = tuple((lay.rows, lay.cols) for lay in layouts)
        self._angles = [float(a) for a in sim.start_deg]
        self._stepped = list(self._angles)  # the joint angles the physics was last stepped to
        self._powered: tuple[bool, ...] | None = None  # as of the last move_joints
        # the last step's joints at their torque limit, (axis, torque), once asked
        self._tau: list[tuple[int, float]] | None = None
        self._blocked: set[int] = set()
        self._slow = sim.slow_axes
        self._moved_at: float | None = None  # the clock of the last move_joints
        self._seed = sim.seed
        # called before the physical state is read from outside the servo's own stepping: a
        # lazy servo clock catches up first (sim.lab.ServoClock)
        self.before_read: Callable[[], None] = _nothing
        self.presses = Presses(layouts, model.tactile.texel_pitch_mm, sim.sensor.spread_mm)
        a, phys = self.axes, sim.physics
        self._physical_axes = (a.phi2, a.phi3, a.phi4, a.phi5)  # the joints the physics sees
        self._max_lead_deg = phys.max_joint_step_deg
        prox, dist = phys.torque_limit_proximal_n_mm, phys.torque_limit_distal_n_mm
        self._limits = (  # (axis, joint, torque limit), in the order _stall checks them
            (a.phi2, "phi2", prox), (a.phi4, "phi4", prox),
            (a.phi3, "phi3", dist), (a.phi5, "phi5", dist),
        )  # fmt: skip
        self.place(obj or get_object(sim.object))

    # --- the seam -----------------------------------------------------------------------------

    @property
    def matrix_shapes(self) -> tuple[tuple[int, int], ...]:
        return self.shapes

    def move_joints(
        self, now: float, reference_deg: Sequence[float], powered: Sequence[bool]
    ) -> tuple[float, ...]:
        self._physics.clock = now
        on = self._powered
        if type(powered) is not tuple or powered != on:  # (the emulator passes a tuple of bools)
            on = tuple(bool(p) for p in powered)
            if on != self._powered:
                self._flush()  # the physics catches up before the servos' pull changes
                self._powered = on
        since = 0.0 if self._moved_at is None else max(0.0, now - self._moved_at)
        self._moved_at = now
        target = self._target(reference_deg, on, since)
        lead = self._lead(target)
        if lead >= self._max_lead_deg:
            # Catch up to the pose last reported first, so that the torque limit is checked
            # against contacts less than one substep behind the joints, never more.
            self._flush()
            target = self._target(reference_deg, on, since)
            lead = self._lead(target)
        self._angles = target
        if lead >= self._max_lead_deg:
            self._flush()  # a single tick moved a whole substep
        return tuple(target)

    def tactile_frame(
        self, now: float, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        self.before_read()
        self._physics.clock = now
        self._flush()
        phys = self._physics
        pressed = self.presses.pressure(now)
        return self.sensor.frame(
            now, phys.pressures(), phys.width_mm, sensitivity, threshold, pressed
        )

    def press(self, press: Press, start: float) -> None:
        """A person presses a pad from ``start`` (s, the world's clock) for the press's duration;
        ValueError if its centre is off the pad."""
        self.presses.add(press, start)

    def release(self, now: float) -> int:
        """Every press on at ``now`` is lifted; returns how many."""
        return self.presses.release(now)

    def flush(self) -> None:
        """Step the contact physics to the joints' actual pose (a no-op if it stands there)."""
        self.before_read()
        self._flush()

    def _flush(self) -> None:
        if self._lead(self._angles) > 0.0:
            self._physics.step(self._pose())
            self._tau = None
        self._stepped = list(self._angles)

    @property
    def physics(self) -> ContactPhysics:
        """The contact physics, first brought up to the joints' actual pose."""
        self.flush()
        return self._physics

    # --- the object ---------------------------------------------------------------------------

    def place(self, obj: Shape, *, height_mm: float | None = None,
              angle_deg: float | None = None) -> None:  # fmt: skip
        """Put ``obj`` between the fingertips, held by the fixture until the fingers grasp it."""
        self.before_read()  # the joints where they are now: the new world starts there
        s, sim = self.model, self.sim
        self.obj = obj
        self.outline = outline = Outline(obj)
        pose = (
            s.geometry.base_offset_mm / 2,
            sim.object_height_mm if height_mm is None else height_mm,
            math.radians(sim.object_angle_deg if angle_deg is None else angle_deg),
        )
        # a new world at the joints' actual pose: nothing of the old one is left to step
        self._physics = ContactPhysics(s.geometry, sim.physics, outline, self._pose(), pose)
        self._stepped, self._tau = list(self._angles), None
        pitch = s.tactile.texel_pitch_mm
        pad = s.geometry.pad
        distal_centre = pad.pad_base_to_active_mm + pad.sensor_active_length_mm / 2
        phys = sim.physics
        prox_centre = (phys.proximal_pad_start_mm + phys.proximal_pad_end_mm) / 2
        surf = self._physics.surfaces
        spread = sim.sensor.spread_mm

        def raster(j: int, centre: float, proximal: bool) -> PadRaster:
            layout = s.tactile.proximal if proximal else s.tactile.distal
            return PadRaster(surf[j].s, surf[j].ds, layout, pitch, centre, spread)

        a = self.axes
        rasters = {
            DISTAL1: (a.finger1_distal_matrix, raster(DISTAL1, distal_centre, False)),
            DISTAL2: (a.finger2_distal_matrix, raster(DISTAL2, distal_centre, False)),
            PROXIMAL1: (a.finger1_proximal_matrix, raster(PROXIMAL1, prox_centre, True)),
            PROXIMAL2: (a.finger2_proximal_matrix, raster(PROXIMAL2, prox_centre, True)),
        }
        layouts = [lay for _, lay in matrix_pads(s.axes, s.tactile)]
        self.sensor = TactileSensorModel(sim.sensor, layouts, rasters, self._seed)

    # --- joints -------------------------------------------------------------------------------

    def _pose(self) -> HandPose:
        a, q = self.axes, self._angles
        return HandPose(*(math.radians(q[i]) for i in (a.phi2, a.phi3, a.phi4, a.phi5)))

    def _target(
        self, reference_deg: Sequence[float], powered: Sequence[bool], since: float
    ) -> list[float]:
        """Where the joints go ``since`` s after the last move: each powered one to its
        reference unless it stalls or drags (``sim.slow_axes``), limp ones nowhere."""
        n = len(self._angles)
        if len(reference_deg) != n or len(powered) != n:
            raise ValueError(f"joint references and power for {n} axes expected")
        if all(powered):  # the usual case, at every servo tick
            target = list(map(float, reference_deg))
        else:
            ahead = zip(reference_deg, powered, self._angles, strict=True)
            target = [float(r) if on else a for r, on, a in ahead]
        self._stall(target)
        for axis, speed in self._slow:  # a dragging axis gets at most so far towards it
            at, reach = self._angles[axis], speed * since
            target[axis] = min(max(target[axis], at - reach), at + reach)
        return target

    def _lead(self, angles: Sequence[float]) -> float:
        """How far (deg) ``angles`` are ahead of the physics, the largest over its joints
        (written out: this runs several times per servo tick)."""
        i, j, k, m = self._physical_axes
        s = self._stepped
        return max(abs(angles[i] - s[i]), abs(angles[j] - s[j]), abs(angles[k] - s[k]),
                   abs(angles[m] - s[m]))  # fmt: skip

    def _stall(self, target: list[float]) -> None:
        """A joint whose contact torque has reached the motor's limit cannot push further.

        The torques are those of the last physics step (deliberately not flushed: this runs at
        every servo tick); :meth:`move_joints` keeps that step less than a substep behind."""
        if self._blocked:
            self._blocked.clear()
        at_limit = self._tau
        if at_limit is not None and not at_limit:  # mostly none: nothing to do, dropped or not
            return
        if self._physics.state.dropped:
            return
        if at_limit is None:
            tau = self._physics.joint_torques_n_mm()
            # only the joints at their torque limit can stall
            self._tau = at_limit = [(axis, tau[name]) for axis, name, limit in self._limits
                                    if abs(tau[name]) >= limit]  # fmt: skip
        for axis, t in at_limit:
            if (target[axis] - self._angles[axis]) * t < 0:  # moving against the load
                target[axis] = self._angles[axis]
                self._blocked.add(axis)

    # --- ground truth -------------------------------------------------------------------------

    def object_pose(self) -> tuple[float, float, float]:
        """The object's pose (y, z mm; ψ rad) as the physics last stepped — at most one substep
        behind the joints. Unlike :meth:`truth` it steps nothing, so an observer that reads it
        mid-run leaves the run exactly as it would have been unobserved."""
        self.before_read()
        pose = self._physics.state.pose
        return float(pose[0]), float(pose[1]), float(pose[2])

    def object_now(self) -> ObjectNow:
        """The object's pose and state as the physics last stepped; like :meth:`object_pose`,
        steps nothing (a run recorded with its truth stays bit for bit the run without)."""
        self.before_read()
        st = self._physics.state
        pose = (float(st.pose[0]), float(st.pose[1]), float(st.pose[2]))
        held = not st.dropped and not st.held_by_fixture
        return ObjectNow(pose, held, st.dropped, st.held_by_fixture, st.slips, st.grip_peak_n)

    def contacts_now(self) -> tuple[ContactTruth, ...]:
        """The contacts as the physics last stepped; like :meth:`object_pose`, steps nothing."""
        self.before_read()
        return tuple(self._physics.contacts())

    def truth(self) -> Truth:
        """The state at the joints' actual pose (this steps the physics up to it)."""
        phys = self.physics
        st = phys.state
        rng = math.degrees(st.psi_max - st.psi_min) if st.psi_max >= st.psi_min else 0.0
        return Truth(
            object=self.obj.name or self.obj.kind,
            size_mm=float(self.obj.size_mm),
            held=phys.held and not st.held_by_fixture,
            dropped=st.dropped,
            in_fixture=st.held_by_fixture,
            pose=(float(st.pose[0]), float(st.pose[1]), float(st.pose[2])),
            contacts=tuple(phys.contacts()),
            slips=st.slips,
            slip_distance_mm=st.slip_distance_mm,
            rotation_range_deg=rng,
            blocked_axes=tuple(sorted(self._blocked)),
        )


def _nothing() -> None:
    """No servo clock to catch up with."""
