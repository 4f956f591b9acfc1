"""The simulated hand: contact physics and the tactile sensor model behind the emulators' seam.

:class:`PhysicsWorld` implements :class:`~sdh2svc.sim.world.HandWorld`: the joint-controller
emulator asks where the joints are when its servos pull towards a reference, the tactile emulator
asks what the six pads read. Ground truth (object pose, true contacts and forces, slips, drops)
is available through :meth:`PhysicsWorld.truth` to tests and to the simulator's own telemetry —
never to the controller, which sees only the bytes.

The rolling plane model assumes axis 0 (φ1) at 90°, the fingers facing each other.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sdh2svc.config import Settings
from sdh2svc.model.kinematics import HandPose
from sdh2svc.sim.objects import Box, Circle, Ellipse, Outline, Polygon, Stick, get_object
from sdh2svc.sim.physics import (
    DISTAL1,
    DISTAL2,
    PROXIMAL1,
    PROXIMAL2,
    ContactPhysics,
    ContactTruth,
)
from sdh2svc.sim.sensor import PadRaster, TactileSensorModel
from sdh2svc.sim.simconfig import SimConfig

ObjectSpecT = Stick | Box | Ellipse | Circle | Polygon


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


class PhysicsWorld:
    """Both coupled fingers, one object, six tactile pads; advances lazily to each ``now``."""

    def __init__(self, settings: Settings, sim: SimConfig, obj: ObjectSpecT | None = None) -> None:
        self.settings, self.sim = settings, sim
        self.axes = settings.axes
        layouts = [settings.tactile.proximal, settings.tactile.distal] * 3
        self.shapes = tuple((lay.rows, lay.cols) for lay in layouts)
        self._angles = [0.0] * 7
        self._blocked: set[int] = set()
        self._seed = sim.seed
        a, phys = self.axes, sim.physics
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
        target = [
            float(r) if on else a
            for r, on, a in zip(reference_deg, powered, self._angles, strict=True)
        ]
        self._stall(target)
        self._angles = target
        self.physics.step(self._pose())
        return tuple(self._angles)

    def tactile_frame(
        self, now: float, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        return self.sensor.frame(
            now, self.physics.pressures(), self.physics.width_mm, sensitivity, threshold
        )

    # --- the object ---------------------------------------------------------------------------

    def place(self, obj: ObjectSpecT, *, height_mm: float | None = None,
              angle_deg: float | None = None) -> None:  # fmt: skip
        """Put ``obj`` between the fingertips, held by the fixture until the fingers grasp it."""
        s, sim = self.settings, self.sim
        self.obj = obj
        outline = Outline(obj)
        pose = (
            s.hand.base_offset_mm / 2,
            sim.object_height_mm if height_mm is None else height_mm,
            math.radians(sim.object_angle_deg if angle_deg is None else angle_deg),
        )
        self.physics = ContactPhysics(s.hand, sim.physics, outline, self._pose(), pose)
        pitch = s.tactile.texel_pitch_mm
        pad = s.hand.pad
        distal_centre = pad.pad_base_to_active_mm + pad.sensor_active_length_mm / 2
        phys = sim.physics
        prox_centre = (phys.proximal_pad_start_mm + phys.proximal_pad_end_mm) / 2
        surf = self.physics.surfaces
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
        layouts = [s.tactile.proximal, s.tactile.distal] * 3
        per_count = s.calibration.pressure_per_count_n_per_mm2
        self.sensor = TactileSensorModel(sim.sensor, layouts, rasters, per_count, self._seed)

    # --- joints -------------------------------------------------------------------------------

    def _pose(self) -> HandPose:
        a, q = self.axes, self._angles
        return HandPose(*(math.radians(q[i]) for i in (a.phi2, a.phi3, a.phi4, a.phi5)))

    def _stall(self, target: list[float]) -> None:
        """A joint whose contact torque has reached the motor's limit cannot push further."""
        self._blocked.clear()
        if self.physics.state.dropped:
            return
        tau = self.physics.joint_torques_n_mm()
        for axis, name, limit in self._limits:
            t = tau[name]
            pushing = (target[axis] - self._angles[axis]) * t < 0  # moving against the load
            if abs(t) >= limit and pushing:
                target[axis] = self._angles[axis]
                self._blocked.add(axis)

    # --- ground truth -------------------------------------------------------------------------

    def truth(self) -> Truth:
        st = self.physics.state
        rng = math.degrees(st.psi_max - st.psi_min) if st.psi_max >= st.psi_min else 0.0
        return Truth(
            object=self.obj.name or self.obj.kind,
            size_mm=float(self.obj.size_mm),
            held=self.physics.held and not st.held_by_fixture,
            dropped=st.dropped,
            in_fixture=st.held_by_fixture,
            pose=(float(st.pose[0]), float(st.pose[1]), float(st.pose[2])),
            contacts=tuple(self.physics.contacts()),
            slips=st.slips,
            slip_distance_mm=st.slip_distance_mm,
            rotation_range_deg=rng,
            blocked_axes=tuple(sorted(self._blocked)),
        )

    def truth_dict(self) -> dict[str, Any]:
        """:meth:`truth` as plain JSON-ready data."""
        return asdict(self.truth())
