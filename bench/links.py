"""The two serial links against the paced emulators (115200 baud, real time, TCP on loopback):
delivered tactile frames/s vs the line-limited maximum for the actual frame sizes, frame age,
push and pull; joint round-trip times for ASCII and binary."""

from __future__ import annotations

import asyncio
import statistics
import time

from bench.common import percentile
from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand

SECONDS = 6.0


async def _tactile(url: str, rate_hz: float) -> dict[str, float | str]:
    bus = await TactileBus.open(url)
    try:
        sub = bus.subscribe({1, 5}, rate_hz)
        loop = asyncio.get_running_loop()
        ages, sizes, n = [], [], 0
        await sub.next_frame(timeout=2.0)
        t0 = loop.time()
        while loop.time() - t0 < SECONDS:
            f = await sub.next_frame(timeout=2.0)
            ages.append((loop.time() - f.arrival) * 1000)
            sizes.append(f.wire_bytes)
            n += 1
        elapsed = loop.time() - t0
        st = bus.stats
        mean_size = statistics.fmean(sizes)
        line_max = 11520 / mean_size  # 10 bits per byte at 115200 baud
        possible = min(line_max, 30.0, rate_hz)  # the line, the controller's cap, the ask
        return {
            "mode": st.mode.value, "fps": n / elapsed, "frame_bytes": mean_size,
            "line_max_fps": line_max, "possible": possible, "ratio": (n / elapsed) / possible,
            "age_p50_ms": statistics.median(ages), "age_p99_ms": percentile(ages, 99),
            "utilisation_pct": st.line_utilisation_pct,
        }  # fmt: skip
    finally:
        await bus.close()


async def _joint(url: str, binary: bool, n: int = 200) -> tuple[float, float]:
    link = await JointLink.open(url, binary=binary)
    try:
        rtt = []
        for _ in range(n):
            t0 = time.perf_counter()
            await link.get_actual()
            rtt.append((time.perf_counter() - t0) * 1000)
        return statistics.median(rtt), percentile(rtt, 99)
    finally:
        await link.close()


async def _main() -> dict[str, float]:
    cfg = load_config(overrides=["sim.object=egg"], use_env=False)
    out: dict[str, float] = {}
    async with simulated_hand(cfg, Simulated()) as bench:
        hand = bench.sim
        # hold the egg so frames carry a real contact (sizes as in a run)
        hand.world.move_joints(0.0, [90.0, -30.0, 30.0, -90.0, 0.0, -30.0, 30.0], [True] * 7)
        hand.world.move_joints(0.0, [90.0, -4.0, 4.0, -90.0, 0.0, -4.0, 4.0], [True] * 7)
        dsa, sdh = hand.urls("dsa")[0], hand.urls("sdh")[0]
        print(f"links vs the paced emulators (115200 baud, {SECONDS:g} s per case, real time)")
        for label, rate in (("push (30 Hz asked)", 30.0), ("pull (10 Hz asked)", 10.0)):
            r = await _tactile(dsa, rate)
            out[label] = float(r["ratio"])
            print(
                f"  tactile {label}: scheduler chose {r['mode']}; {r['fps']:5.1f} frames/s of "
                f"{r['possible']:5.1f} possible → ratio {r['ratio']:.3f}"
            )
            print(
                f"      (line limit {r['line_max_fps']:.1f} fps at {r['frame_bytes']:.0f} B/frame,"
                f" controller cap 30 fps); age at delivery p50 {r['age_p50_ms']:.2f} ms, p99 "
                f"{r['age_p99_ms']:.2f} ms; line {r['utilisation_pct']:.0f} % busy"
            )
        for binary in (False, True):
            p50, p99 = await _joint(sdh, binary)
            name = "binary" if binary else "ASCII"
            out[f"joint_{name}_p50_ms"] = p50
            print(f"  joint round trip, get actual angles ({name:6s}): p50 {p50:5.2f} ms, "
                  f"p99 {p99:5.2f} ms")  # fmt: skip
        print(
            "  push is picked when the asked rate is ≥ 90 % of what push delivers (controller cap"
            " or line limit): a pull round trip per frame would only cost rate"
        )
    return out


def run() -> dict[str, float]:
    return asyncio.run(_main())
