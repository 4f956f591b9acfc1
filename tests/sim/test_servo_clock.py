"""The joint controller's servo clock in fast mode: a lazy clock, which wakes for no tick and
is caught up whenever the emulator or the world is read, gives the run of a clock that wakes
at every tick — the same bytes at the same times, the same physics."""

from __future__ import annotations

import asyncio
from typing import Any

from sdh2svc.config import load_config
from sdh2svc.connect import hand_model
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.endpoint import MemoryEndpoint
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.lab import ServoClock
from sdh2svc.sim.sdh2 import Sdh2Emulator

OPEN = [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0]  # the coupled fingers around the egg
GRASP = "p=90,-5,5,0,0,-5,5"  # pressing into it


async def _session(lazy: bool) -> tuple[list[tuple[float, bytes]], list[Any], int]:
    cfg = load_config(use_env=False)
    world = PhysicsWorld(hand_model(cfg), cfg.sim)
    world.move_joints(0.0, OPEN, [True] * 7)  # where the hand stands at power-on
    sdh = Sdh2Emulator(world)
    clock = ServoClock(sdh, world, lazy=lazy).start()
    out: list[tuple[float, bytes]] = []
    seen: list[Any] = []
    async with MemoryEndpoint(sdh, on_output=lambda data, t: out.append((t, data))) as ep:
        for line in ("con=0", "v=40,40,40,40,40,40,40", "a=300,300,300,300,300,300,300", GRASP,
                     "m"):  # fmt: skip
            ep.write(line.encode() + b"\r\n")
            await asyncio.sleep(0.013)
        await asyncio.sleep(0.2)  # on the way: no command, nobody looks
        for _ in range(50):  # closing onto the egg: read angles, truth and the servo between
            ep.write(b"pos\r\n")
            await asyncio.sleep(0.0117)
            # the world first (a truth steps the physics to the joints), then the emulator
            seen.append((world.truth(), world.object_now(), sdh.actual_deg))
        seen.append(world.truth())
    clock.cancel()
    return out, seen, world.sensor.rng.bit_generator.state["state"]["state"]


def test_a_lazy_servo_clock_runs_as_one_that_wakes_at_every_tick() -> None:
    eager = run_fast(_session(lazy=False))
    lazy = run_fast(_session(lazy=True))
    assert lazy == eager  # bit for bit: the replies and their times, poses, contacts, truth
    truth = eager[1][-1]
    assert truth.held and truth.contacts  # the run did grasp: there was physics to get wrong
    assert len(eager[0]) > 60
