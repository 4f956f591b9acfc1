"""The simulated hand end to end, through bytes only: moving the fingers over the SDH2 line
changes what the DSACON32m line reports, as a real object between the fingertips would."""

from __future__ import annotations

import asyncio

import numpy as np
import serial_asyncio

from sdh2svc.config import Settings, load_config
from sdh2svc.connect import hand_model
from sdh2svc.model.contact import estimate_contact
from sdh2svc.protocol import dsa, sdh
from sdh2svc.sim.lab import start_simulated_hand


class Host:
    """A bare-bones host over the codecs: enough to move and to read one frame."""

    def __init__(self, cfg: Settings, sdh_url: str, dsa_url: str) -> None:
        self.cfg, self.sdh_url, self.dsa_url = cfg, sdh_url, dsa_url

    async def open(self) -> None:
        self.jr, self.jw = await serial_asyncio.open_serial_connection(url=self.sdh_url)
        self.tr, self.tw = await serial_asyncio.open_serial_connection(url=self.dsa_url)
        self.jp, self.tp = sdh.ReplyParser(), dsa.PacketParser()

    def close(self) -> None:
        self.jw.close()
        self.tw.close()

    async def cmd(self, keyword: str, values: list[float] | None = None) -> sdh.Reply:
        self.jw.write(sdh.encode_ascii(keyword, values))
        while True:
            for ev in self.jp.feed(await asyncio.wait_for(self.jr.read(256), 5.0)):
                assert not isinstance(ev, sdh.ErrorLine), ev
                if isinstance(ev, sdh.Reply):
                    return ev

    async def move_to(self, angles: list[float]) -> None:
        await self.cmd("p", angles)
        await self.cmd("m")
        while any(int(v) == 1 for v in (await self.cmd("state")).values):
            await asyncio.sleep(0.05)

    async def frame(self) -> list[np.ndarray]:
        self.tw.write(dsa.configure_acquisition(acquire=True, framerate=0))  # pull one frame
        while True:
            for ev in self.tp.feed(await asyncio.wait_for(self.tr.read(1024), 5.0)):
                if isinstance(ev, dsa.Packet) and ev.id == dsa.PacketId.FULL_FRAME:
                    f = dsa.decode_frame_payload(ev.payload, 486)
                    return dsa.split_matrices(f.texels, dsa.SDH2_MATRIX_SHAPES)

    def contact(self, m: np.ndarray):
        c = self.cfg
        return estimate_contact(m, c.tactile.distal, c.tactile.texel_pitch_mm, c.calibration,
                                c.hand.pad)  # fmt: skip


async def test_fingers_moving_over_bytes_change_the_tactile_frames() -> None:
    cfg = load_config(overrides=["sim.object=egg"], use_env=False)
    hand = await start_simulated_hand(hand_model(cfg), cfg.sim, pty=False, dsa_port=0, sdh_port=0)
    host = Host(cfg, hand.urls("sdh")[0], hand.urls("dsa")[0])
    try:
        await host.open()
        await host.cmd("con", [0])
        await host.cmd("v", [40.0] * 7)
        await host.move_to([90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0])
        open_frame = await host.frame()
        assert all(int(m.max()) == 0 for m in open_frame)  # nothing touches yet
        await host.move_to([90.0, -5.0, 5.0, 0.0, 0.0, -5.0, 5.0])  # close on the egg
        held = await host.frame()
        c1, c2 = host.contact(held[1]), host.contact(held[5])
        assert c1.present and c2.present and c1.force_library > 0.5
        assert abs(c1.S_mm - c2.S_mm) < 2.0  # a mirror grasp: the same spot on both pads
        assert hand.world.truth().held
        # Finger 2 rolls the egg along its route: the contacts move along the pads
        await host.move_to([90.0, -3.0, 1.0, 0.0, 0.0, -7.0, 9.0])
        rolled = await host.frame()
        r1, r2 = host.contact(rolled[1]), host.contact(rolled[5])
        assert r1.present and r2.present
        d1, d2 = r1.S_mm - c1.S_mm, r2.S_mm - c2.S_mm
        assert abs(d1) > 0.4 and abs(d2) > 0.4
        assert d1 * d2 < 0  # rolling: the contacts move opposite ways along the two pads
        assert not np.array_equal(rolled[5], held[5])
    finally:
        host.close()
        await hand.stop()
