"""POST /api/sim/press (and DELETE): a person's press on a simulated pad through the service, in
this process on the virtual clock (the app over ASGI; the hand in fast mode)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import httpx
import numpy as np

from sdh2svc.bus.tactile import Subscription
from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Real, Simulated, Where, simulated_hand
from sdh2svc.service.app import Services, close_services, create_app, open_services
from sdh2svc.sim.clock import run_fast

PRESS = {"pad": 2, "x_mm": 10.0, "y_mm": 24.0, "force_n": 2.0, "radius_mm": 4.0, "duration_s": 0.3}


@contextlib.asynccontextmanager
async def service(cfg: Settings, where: Where) -> AsyncIterator[tuple[httpx.AsyncClient, Services]]:
    services = await open_services(cfg, where, viewer=False)
    try:
        transport = httpx.ASGITransport(app=create_app(services))
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
            yield c, services
    finally:
        await close_services(services)


async def within(sub: Subscription, n: int, ok: Callable[[np.ndarray], bool]) -> np.ndarray:
    """The first of the next ``n`` frames whose matrix 2 is ``ok``; fails if none is."""
    for _ in range(n):
        m = (await sub.next_frame()).matrices[2]
        if ok(m):
            return m
    raise AssertionError(f"not within {n} frames")


def test_a_press_through_the_api_reads_in_the_next_frames(tmp_path: Path) -> None:
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            for bad, field in (({**PRESS, "force_n": 0}, "force_n"),
                               ({**PRESS, "force_n": 1e4}, "force_n"),
                               ({**PRESS, "duration_s": 61}, "duration_s"),
                               ({**PRESS, "pad": 6}, "pad"),
                               ({**PRESS, "force_n": True}, "force_n"),
                               ({**PRESS, "colour": "red"}, "colour")):  # fmt: skip
                r = await c.post("/api/sim/press", json=bad)
                assert r.status_code == 422 and field in r.json()["details"][0], r.text
            r = await c.post("/api/sim/press", json={**PRESS, "y_mm": 48.0})  # 14 rows: 47.6 mm
            assert r.status_code == 422 and "off its pad" in r.json()["error"], r.text
            assert "y_mm = 48 is off pad 2" in r.json()["details"][0]

            tactile = services.station.tactile
            assert tactile is not None
            sub = tactile.subscribe([2], 30.0)
            assert not (await sub.next_frame()).matrices[2].any()
            r = await c.post("/api/sim/press", json={"pad": 2, "x_mm": 10, "y_mm": 24,
                                                     "force_n": 2})  # fmt: skip
            assert r.status_code == 202, r.text
            assert r.json() == {**PRESS, "radius_mm": 3.0, "duration_s": 1.0}  # the defaults
            # frames already sampled or on the line when the press began do not show it (how
            # many depends on where the request fell in the frame period): within 5 frames
            pressed = await within(sub, 5, lambda m: m.any())
            row, col = np.unravel_index(int(pressed.argmax()), pressed.shape)
            assert (row, col) in ((6, 2), (7, 2), (6, 3), (7, 3))  # 24 mm along, 10 across
            r = await c.request("DELETE", "/api/sim/press", json={})
            assert r.status_code == 200 and r.json() == {"released": 1}
            await within(sub, 5, lambda m: not m.any())
            sub.close()

    run_fast(main())


def test_no_press_on_a_real_hand(tmp_path: Path) -> None:
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> None:
        async with simulated_hand(cfg, Simulated(fast=True)) as served:
            real = Real(served.sim.urls("dsa")[0], served.sim.urls("sdh")[0])
            async with service(cfg, real) as (c, _):
                r = await c.post("/api/sim/press", json=PRESS)
                assert r.status_code == 404 and "not in simulation" in r.json()["error"]
                r = await c.request("DELETE", "/api/sim/press", json={})
                assert r.status_code == 404

    run_fast(main())
