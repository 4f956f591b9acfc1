"""The seam: one place opens a hand, real or simulated, and closes it in order."""

from __future__ import annotations

from sdh2svc.config import load_config
from sdh2svc.connect import Real, Simulated, connect_hand, simulated_hand
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.objects import get_object


def test_a_simulated_hand_comes_with_its_bench_and_closes_in_order() -> None:
    cfg = load_config(overrides=["sim.object='egg'"], use_env=False)

    async def main() -> None:
        async with connect_hand(cfg, Simulated(fast=True)) as hand:
            bench = hand.bench
            assert bench is not None and not hand.real
            assert hand.joints.connected and hand.tactile.connected
            assert hand.dsa_url.startswith("unix://") and hand.sdh_url.startswith("unix://")
            truth = bench.truth()
            assert truth.object == "egg" and truth.in_fixture and not truth.held
            assert truth.summary()["object"] == "egg"
            assert len(truth.scene(bench.outline)["outline"]) == 90
            bench.place(get_object("rubber"), angle_deg=10.0)
            assert bench.obj.name == "rubber" and bench.truth().object == "rubber"
            assert bench.outline.spec is bench.obj
        assert not hand.joints.connected and not hand.tactile.connected  # the links, closed
        assert all(not ep.running for eps in bench.sim.endpoints.values() for ep in eps)

    run_fast(main())


def test_a_real_hand_has_no_bench() -> None:
    """Its lines lead to a simulated hand served elsewhere: to the seam, a real hand."""
    cfg = load_config(use_env=False)

    async def main() -> None:
        async with simulated_hand(cfg, Simulated(fast=True)) as served:
            urls = Real(served.sim.urls("dsa")[0], served.sim.urls("sdh")[0])
            async with connect_hand(cfg, urls) as hand:
                assert hand.real and hand.bench is None
                assert hand.joints.connected and hand.tactile.connected

    run_fast(main())
