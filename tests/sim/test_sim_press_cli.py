"""`sdh2svc sim --press SPEC` and the lines typed into it while it runs."""

from __future__ import annotations

import asyncio

import pytest

from sdh2svc.cli import main, sim_command
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand
from sdh2svc.sim.clock import run_fast


def test_a_bad_press_spec_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["sim", "--press", "pad=3,x=10,y=12"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "argument --press: missing force" in err and "Traceback" not in err


def test_typed_lines_press_release_or_say_what_is_wrong() -> None:
    cfg = load_config(use_env=False)

    async def main() -> None:
        async with simulated_hand(cfg, Simulated(fast=True)) as bench:
            presses = bench.sim.world.presses
            assert sim_command(bench, "  \n") is None
            said = sim_command(bench, "press pad=3 x=10 y=12 force=2 radius=4 duration=1.5 at=5")
            assert said == (
                "pressing pad 3 at (10, 12) mm, 2 N over r = 4 mm for 1.5 s, 5 s from now"
            )
            assert sim_command(bench, "press pad=3 x=10 y=50 force=2") == (
                "bad press: y_mm = 50 is off pad 3 (0…44.2 mm along)"
            )
            said = sim_command(bench, "press pad=3 x=10")
            assert said is not None and said.startswith("bad press: missing y, force")
            said = sim_command(bench, "poke pad=3")
            assert said is not None and said.startswith("unknown command 'poke'")
            now = asyncio.get_running_loop().time()
            assert presses.pressure(now) is None and presses.pressure(now + 5.1) is not None
            sim_command(bench, "press pad=0 x=10 y=12 force=1")
            assert sim_command(bench, "release") == "released 1 press(es)"  # the one on now
            assert presses.pressure(now + 5.1) is not None  # the later one stays

    run_fast(main())


def test_a_press_off_its_pad_stops_sim_before_it_serves(
    capsys: pytest.CaptureFixture[str],
) -> None:
    status = main(["sim", "--no-pty", "--dsa-port", "0", "--sdh-port", "0",
                   "--press", "pad=3,x=10,y=50,force=1"])  # fmt: skip
    assert status == 2
    err = capsys.readouterr().err
    assert "--press pad=3,x=10,y=50,force=1: y_mm = 50 is off pad 3 (0…44.2 mm along)" in err
