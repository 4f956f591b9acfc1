"""The seam: one place opens a hand, real or simulated, and closes it in order."""

from __future__ import annotations

import pytest

from sdh2svc.config import ConfigError, load_config
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
            said = hand.describe()  # a run's record: which firmware answered, too
            assert (said["sdh_firmware"], said["dsacon_firmware"]) == ("0.0.3.3", 0x2900)
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


def test_a_hand_whose_pads_differ_from_the_configuration_is_refused_naming_them() -> None:
    """A hand whose fingertip pads have 12 rows where the configuration says 13 was opened,
    shown up and healthy, and its first run failed as "a bug" (the contact estimate's
    ValueError); a proximal pad of another size went unnoticed. The controller's own account
    of its matrices is checked at every open."""
    lab = load_config(overrides=["tactile.distal.rows=12", "tactile.distal.mask=[]",
                                 "tactile.proximal.rows=10", "tactile.proximal.mask=[]"],
                      use_env=False)  # fmt: skip
    cfg = load_config(use_env=False)

    async def main() -> str:
        async with simulated_hand(lab, Simulated(fast=True)) as served:
            urls = Real(served.sim.urls("dsa")[0], served.sim.urls("sdh")[0])
            with pytest.raises(ConfigError) as refused:  # (sdh2svc run: exit 2, not 4)
                async with connect_hand(cfg, urls):
                    pass
            return str(refused.value)

    message = run_fast(main())
    assert message.startswith("invalid configuration: tactile line unix://")
    assert "matrix 0 (Finger 1 proximal pad, tactile.proximal) is 10 × 6 cells on the " \
           "controller, 14 × 6 in the configuration" in message  # fmt: skip
    assert "matrix 5 (Finger 2 distal pad, tactile.distal) is 12 × 6" in message


def test_a_simulated_hand_lays_its_pads_out_as_they_are_wired() -> None:
    """Finger 1's pads swapped in the wiring: the simulated controller reports (and fills) the
    matrices in that order, as the hand it emulates would."""
    cfg = load_config(overrides=["axes.finger1_proximal_matrix=1", "axes.finger1_distal_matrix=0"],
                      use_env=False)  # fmt: skip

    async def main() -> list[tuple[int, int]]:
        async with connect_hand(cfg, Simulated(fast=True)) as hand:
            return [m.shape for m in hand.tactile.matrix_infos]

    assert run_fast(main()) == [(13, 6), (14, 6), (14, 6), (13, 6), (14, 6), (13, 6)]


def test_a_speed_the_hand_cannot_reach_is_refused_as_it_is_opened() -> None:
    """run.preshape_velocity_deg_s = 150 on a hand whose slowest axis does 83 °/s: every run
    and every Open hand failed as an internal error ("a bug", exit 70)."""
    cfg = load_config(overrides=["run.preshape_velocity_deg_s=150"], use_env=False)

    async def main() -> str:
        with pytest.raises(ConfigError) as refused:
            async with connect_hand(cfg, Simulated(fast=True)):
                pass
        return str(refused.value)

    assert run_fast(main()) == (
        "invalid configuration: run.preshape_velocity_deg_s = 150: above the hand's velocity "
        "limit, 83 °/s on axis 0 (its vlim; allowed: preshape_velocity_deg_s ≤ 83)"
    )
