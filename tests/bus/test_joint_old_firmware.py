"""JointLink against firmware older than the commands SDHLibrary gates by release.

SDHLibrary-CPP (``sdh/sdh.cpp``) never sends ``vlim`` before 0.0.2.1, ``alim`` before 0.0.2.7 or
``con`` before 0.0.2.6 ("setting the controller would yield an error from the firmware (unknown
command)"); it uses fixed limits and the pose controller instead. The link must connect to such
a hand in the same way (it already speaks ASCII to firmware older than the binary frames).
"""

from __future__ import annotations

import pytest

from sdh2svc.bus.joint import ControllerMode, JointLink, JointLinkError
from sdh2svc.sim.endpoint import serve_device
from sdh2svc.sim.sdh2 import Sdh2Emulator, Sdh2Options
from sdh2svc.sim.world import ScriptedWorld

SHAPES = [(14, 6), (13, 6)] * 3


@pytest.mark.parametrize(
    ("version", "vlim_fixed", "alim_fixed"),
    [("0.0.2.0", True, True), ("0.0.2.5", False, True), ("0.0.2.6", False, True)],
)
async def test_connects_to_firmware_without_alim_or_con(
    version: str, vlim_fixed: bool, alim_fixed: bool
) -> None:
    opts = Sdh2Options(version=version, soc_version=version)
    dev = Sdh2Emulator(ScriptedWorld(SHAPES), options=opts)
    async with serve_device(dev, "tcp") as ep:
        link = await JointLink.open(ep.url, binary=True)
        try:
            assert link.version == version
            assert not link.binary  # older than the binary frames
            assert link.controller is ControllerMode.POSE
            if vlim_fixed:  # SDHLibrary's fixed defaults for firmware before 0.0.2.1
                assert link.velocity_limits == (85.7, 200.0, 157.8, 200.0, 157.8, 200.0, 157.8)
            else:
                assert link.velocity_limits == opts.velocity_limit
            if alim_fixed:  # ... and before 0.0.2.7
                assert link.acceleration_limits == (5000.0, 400.0, 1500.0, 400.0, 1500.0, 400.0,
                                                    1500.0)  # fmt: skip
            assert await link.set_controller(ControllerMode.POSE) is ControllerMode.POSE
            if version < "0.0.2.6":
                with pytest.raises(JointLinkError):
                    await link.set_controller(ControllerMode.VELOCITY)
            await link.set_targets((10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            assert await link.move() >= 0.0
            await link.hold()
        finally:
            await link.close()


async def test_emulator_refuses_what_old_firmware_lacks() -> None:
    dev = Sdh2Emulator(ScriptedWorld(SHAPES), options=Sdh2Options(version="0.0.2.5"))
    replies = [dev_reply(dev, line) for line in (b"alim\r\n", b"con\r\n", b"vlim\r\n")]
    assert replies[0] == b"E13\r\n" and replies[1] == b"E13\r\n"
    assert replies[2].startswith(b"VLIM=")


def dev_reply(dev: Sdh2Emulator, line: bytes) -> bytes:
    dev.receive(line, 0.0)
    out = b""
    while (chunk := dev.next_packet(0.0)) is not None:
        out += chunk
    return out
