"""The simulated world's configuration value (config/sim.toml, under the key ``sim``)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, Strict, field_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.hand import HAND_MAX_DEG, HAND_MIN_DEG
from sdh2svc.protocol.sdh import NUM_AXES
from sdh2svc.sim.objects import get_object
from sdh2svc.sim.physics import PhysicsConfig
from sdh2svc.sim.sensor import SensorModelConfig


class LinksConfig(Finite):
    """Where and how the simulated devices are served."""

    host: str
    dsa_tcp_port: Annotated[int, Field(ge=0, le=65535)]
    sdh_tcp_port: Annotated[int, Field(ge=0, le=65535)]
    pty: bool
    baud: Annotated[int, Field(ge=300, le=4_000_000)]
    dsa_boot_s: Annotated[float, Field(ge=0.0, le=60.0)]
    bit_error_rate: Annotated[float, Field(ge=0.0, le=0.1)]
    sdh_ascii_latency_ms: Annotated[float, Field(ge=0.0, le=100.0)]
    sdh_binary_latency_ms: Annotated[float, Field(ge=0.0, le=100.0)]


# (wire axis, the fastest it moves, deg/s): an axis that moves slower than commanded
SlowAxis = tuple[
    Annotated[int, Strict(), Field(ge=0, le=NUM_AXES - 1)],
    Annotated[float, Field(ge=0.0, le=1000.0)],
]


class SimConfig(Finite):
    """The object, its placement, the contact physics and the sensor's imperfections."""

    seed: Annotated[int, Field(ge=0)]
    object: str
    object_height_mm: Annotated[float, Field(ge=0.0, le=400.0)]
    object_angle_deg: Annotated[float, Field(ge=-180.0, le=180.0)]
    replace_after_s: Annotated[float, Field(ge=0.0, le=3600.0)]
    # the hand's joint angles when the simulation starts (wire axes 0…6, deg): within what the
    # hand can reach (a configuration's tighter joint limits bound commands, not where a hand
    # was left)
    start_deg: Annotated[tuple[float, ...], Field(min_length=7, max_length=7)]
    # axes that move slower than commanded, whatever their servo is told (a worn gearbox, a
    # finger rubbing on something; 0 deg/s: jammed): (wire axis, deg/s) each
    slow_axes: tuple[SlowAxis, ...] = ()
    physics: PhysicsConfig
    sensor: SensorModelConfig
    links: LinksConfig

    @field_validator("start_deg")
    @classmethod
    def _reachable(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        outside = [f"axis {i}: {a:g} (the hand reaches {lo:g} … {hi:g})"
                   for i, (a, lo, hi) in enumerate(zip(v, HAND_MIN_DEG, HAND_MAX_DEG, strict=True))
                   if not lo <= a <= hi]  # fmt: skip
        if outside:
            raise ValueError("; ".join(outside))
        return v

    @field_validator("slow_axes")
    @classmethod
    def _each_axis_once(cls, v: tuple[tuple[int, float], ...]) -> tuple[tuple[int, float], ...]:
        axes = [axis for axis, _ in v]
        if twice := sorted({a for a in axes if axes.count(a) > 1}):
            raise ValueError(f"axis {twice[0]} is given more than one speed")
        return v

    @field_validator("object")
    @classmethod
    def _preset(cls, v: str) -> str:
        """A preset's name (an object file is given with ``--object-file``)."""
        try:
            get_object(v)
        except KeyError as e:  # its message names the presets
            raise ValueError(e.args[0]) from None
        return v
