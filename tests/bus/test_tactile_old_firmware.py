"""TactileBus against DSACON32m firmware that cannot send single frames.

SDHLibrary-CPP ``sdh/dsa.cpp`` (``cDSA::ReadFrame``): "DSACON32m firmware release up to and
including 288 except 269 are not able to handle single frame acquisition. Instead they start
sending as fast as possible right away. So stop acquiring immediately after frame was received"
— it sends the stop after every pull frame on such firmware. It also refuses the threshold
commands below R268 (``SetMatrixThreshold``/``GetMatrixThreshold``). And a controller whose
reported texel size is not the configured pitch (SDHLibrary computes areas with the report).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from sdh2svc.bus.tactile import Mode, TactileBus, TactileError, TactileOptions
from sdh2svc.protocol import dsa
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.dsacon import DsaconEmulator, DsaconOptions
from sdh2svc.sim.endpoint import TcpEndpoint, UnixEndpoint
from sdh2svc.sim.world import ScriptedWorld

SHAPES = [(14, 6), (13, 6)] * 3


def test_emulator_streams_after_a_pull_on_old_firmware() -> None:
    emu = DsaconEmulator(ScriptedWorld(SHAPES), options=DsaconOptions(sw_version=288))
    emu.connected(0.0)
    emu.receive(dsa.configure_acquisition(acquire=True, framerate=0), 0.0)
    parser, frames = dsa.PacketParser(), 0
    for step in range(31):  # one second
        while (packet := emu.next_packet(step / 30)) is not None:
            frames += sum(
                1
                for ev in parser.feed(packet)
                if isinstance(ev, dsa.Packet) and ev.id == dsa.PacketId.FULL_FRAME
            )
    assert frames > 20  # a stream at the maximum rate, not one frame


@pytest.mark.parametrize("sw_version", [288, 0x2900])
def test_pull_mode_stays_one_frame_per_request(sw_version: int, tmp_path: Path) -> None:
    """On the virtual clock: 2 s of a 2 Hz pull subscription (without the stop after each
    frame, R288 streamed 59 frames meanwhile)."""

    async def main() -> int:
        emu = DsaconEmulator(ScriptedWorld(SHAPES), options=DsaconOptions(sw_version=sw_version))
        async with UnixEndpoint(emu, str(tmp_path / "dsa.sock"), whole_packets=True) as ep:
            bus = await TactileBus.open(ep.url)
            try:
                with bus.subscribe(range(6), 2.0):
                    async with asyncio.timeout(5.0):
                        while bus.mode is not Mode.PULL:
                            await asyncio.sleep(0.01)
                    start = bus.stats.frames
                    await asyncio.sleep(2.0)
                    got = bus.stats.frames - start
                if sw_version < 268:
                    with pytest.raises(TactileError):
                        await bus.get_threshold(0)
                return got
            finally:
                await bus.close()

    got = run_fast(main())
    assert 3 <= got <= 6, f"{got} frames in 2 s at 2 Hz"


@pytest.mark.parametrize(("reported", "said"), [(3.4, False), (3.41, False), (3.8, True)])
async def test_a_texel_size_other_than_the_configured_pitch_is_said_at_open(
    reported: float, said: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """SDHLibrary computes contact areas with the texel size the controller reports; this
    project with the configured pitch (what the device reports is unconfirmed): a report that
    differs is said, naming both (the hand is not refused for it)."""
    emu = DsaconEmulator(ScriptedWorld(SHAPES), options=DsaconOptions(texel_size_mm=reported))
    async with TcpEndpoint(emu) as ep:
        with caplog.at_level("WARNING", logger="sdh2svc.bus.tactile"):
            bus = await TactileBus.open(ep.url, TactileOptions(pitch_mm=3.4))
        await bus.close()
    warned = [r.getMessage() for r in caplog.records if "texel" in r.getMessage()]
    assert bool(warned) is said, warned
    if said:
        assert "3.8 × 3.8 mm" in warned[0] and "texel_pitch_mm = 3.4 mm" in warned[0]
