"""Fast mode: the virtual clock runs paced serial lines and emulators as fast as the CPU allows,
deterministically, over real Unix-domain sockets opened through pyserial URLs."""

from __future__ import annotations

import asyncio
from pathlib import Path

import serial_asyncio

import sdh2svc.bus  # noqa: F401  (registers unix:// with pyserial)
from sdh2svc.config import load_config
from sdh2svc.connect import hand_model
from sdh2svc.protocol import dsa
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.dsacon import DsaconEmulator
from sdh2svc.sim.endpoint import UnixEndpoint
from sdh2svc.sim.hand import PhysicsWorld


async def _push_session(sock: Path, seconds: float) -> tuple[list[bytes], float]:
    """Open the DSACON32m emulator over unix://, stream push frames for ``seconds`` of the
    line's (virtual) time, and return the frame payloads and the virtual time it took."""
    cfg = load_config(use_env=False)
    # noise and creep on: the frames vary from one to the next
    world = PhysicsWorld(hand_model(cfg), cfg.sim)
    world.move_joints(0.0, [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0], [True] * 7)
    world.move_joints(0.0, [90.0, -5.0, 5.0, 0.0, 0.0, -5.0, 5.0], [True] * 7)  # the egg, held
    emu = DsaconEmulator(world)
    loop = asyncio.get_running_loop()
    async with UnixEndpoint(emu, str(sock)) as ep:
        reader, writer = await serial_asyncio.open_serial_connection(url=ep.url, baudrate=115200)
        parser = dsa.PacketParser()
        t0 = loop.time()
        writer.write(dsa.configure_acquisition(acquire=True, framerate=30))
        frames: list[bytes] = []
        while loop.time() - t0 < seconds:
            for ev in parser.feed(await reader.read(4096)):
                if isinstance(ev, dsa.Packet) and ev.id == dsa.PacketId.FULL_FRAME:
                    frames.append(ev.payload)
        writer.write(dsa.configure_acquisition(acquire=False, framerate=0))
        elapsed = loop.time() - t0
        writer.close()
    return frames, elapsed


def test_fast_mode_streams_many_seconds_quickly_and_identically(tmp_path: Path) -> None:
    frames_a, sim_a = run_fast(_push_session(tmp_path / "a.sock", 10.0))
    frames_b, sim_b = run_fast(_push_session(tmp_path / "b.sock", 10.0))
    assert sim_a >= 10.0
    assert len(frames_a) >= 290  # 30 fps for 10 virtual seconds (the controller's cap)
    # The same bytes, frame for frame (timestamps included), for the same seed.
    assert frames_a == frames_b and sim_a == sim_b
    texels = [dsa.decode_frame_payload(f, 486).texels for f in frames_a]
    assert all(t.max() > 500 for t in texels)  # the held egg presses the distal pads
    assert len({t.tobytes() for t in texels}) > len(texels) // 2  # noisy, creeping readings


def test_executor_work_runs_inline_without_moving_the_clock() -> None:
    async def main() -> tuple[float, float, int]:
        loop = asyncio.get_running_loop()
        ticker = asyncio.ensure_future(asyncio.sleep(0.001))  # a timer the clock could jump to
        t0 = loop.time()
        result = await asyncio.to_thread(sum, range(10))
        t1 = loop.time()
        await ticker
        return t0, t1, result

    t0, t1, result = run_fast(main())
    assert result == 45 and t1 == t0
