"""The two serial links against the paced emulators (115200 baud both ways, the SDH2 firmware's
processing time; real time): delivered tactile frames/s vs the line-limited maximum for the
actual frame sizes, frame age, push and pull (TCP on loopback); joint round-trip times for ASCII
and binary; and SCHUNK's joint benchmark loop (binary `pos` + `tvav`, ASCII `pos`, `v`, `vel`)
over the pty, in real time and on the virtual clock, beside the real hand's published rate."""

from __future__ import annotations

import asyncio
import statistics
import time

from bench.common import percentile
from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.sdh2 import PUBLISHED_LOOP_HZ

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


async def vendor_loop(link: JointLink, n: int) -> float:
    """SCHUNK's benchmark cycle (protocols.md §2.7) ``n`` times in the velocity controller with
    zero velocities; cycles per second of the loop's clock. Binary: `pos` + `tvav`; ASCII:
    `pos`, `v`, `vel`."""
    await link.set_controller(1)
    zeros = [0.0] * 7
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    for _ in range(n):
        await link.get_actual()
        if link.binary:
            await link.tvav(zeros)
        else:
            await link.set_velocities(zeros)
            await link.get_velocity()
    return n / (loop.time() - t0)


async def _loop_rates(url: str, n: int) -> dict[str, float]:
    rates = {}
    for name in ("binary", "ascii"):
        binary = name == "binary"  # binary_crc: the RS-232 form the published figure is for
        link = await JointLink.open(url, binary=binary, binary_crc=binary or None)
        try:
            rates[name] = await vendor_loop(link, n)
        finally:
            await link.close()
    return rates


async def _virtual_rates() -> dict[str, float]:
    cfg = load_config(use_env=False)
    async with simulated_hand(cfg, Simulated(fast=True)) as bench:
        return await _loop_rates(bench.sim.urls("sdh")[0], 200)


def _print_loops(out: dict[str, float], real: dict[str, float]) -> None:
    virtual = run_fast(_virtual_rates())
    print("  SCHUNK's joint benchmark loop vs the real SDH2 on RS-232 (SDHLibrary-CPP 0.0.2.0 "
          "release notes):")  # fmt: skip
    for name, what in (("binary", "pos + tvav"), ("ascii", "pos, v, vel")):
        ref = PUBLISHED_LOOP_HZ[name]
        r, v = real[name], virtual[name]
        print(f"    {name:6s} ({what}): {r:5.1f} Hz real time over the pty, {v:5.1f} Hz on "
              f"the virtual clock; real hand ≈ {ref:g} Hz → ratio {r / ref:.2f} / "
              f"{v / ref:.2f}")  # fmt: skip
        out[f"loop_{name}_hz"], out[f"loop_{name}_ratio"] = r, r / ref
        out[f"loop_{name}_virtual_ratio"] = v / ref
    print("    (the ASCII `v` values go out as 0.000, not SCHUNK's %f: 21 bytes fewer a cycle, "
          "≈ 6 % faster)")  # fmt: skip


async def _main() -> tuple[dict[str, float], dict[str, float]]:
    cfg = load_config(overrides=["sim.object=egg"], use_env=False)
    out: dict[str, float] = {}
    async with simulated_hand(cfg, Simulated(pty=True)) as bench:
        hand = bench.sim
        # hold the egg so frames carry a real contact (sizes as in a run)
        hand.world.move_joints(0.0, [90.0, -30.0, 30.0, -90.0, 0.0, -30.0, 30.0], [True] * 7)
        hand.world.move_joints(0.0, [90.0, -4.0, 4.0, -90.0, 0.0, -4.0, 4.0], [True] * 7)
        dsa, sdh = hand.urls("dsa")[-1], hand.urls("sdh")[-1]  # TCP
        pty = hand.urls("sdh")[0]
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
        real = await _loop_rates(pty, 100)
    return out, real


def run() -> dict[str, float]:
    out, real = asyncio.run(_main())
    _print_loops(out, real)
    return out
