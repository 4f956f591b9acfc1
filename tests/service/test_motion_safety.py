"""A real service next to a hand that keeps its last command, as the SDH2 firmware does.

The simulated hand runs in this test's process (its emulators keep a velocity or a move going
whoever is connected); ``sdh2svc serve`` runs as its own process and reaches the joint line
through a :class:`~sdh2svc.sim.cable.Cable` that the test cuts. The pass condition never depends
on how long something took: the fingers must not have moved more than one increment (≤ 1°)
however long the test waited — the old velocity grasp moved 3 °/s for as long as one looked.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from sdh2svc.client import AsyncClient, Conflict, Unauthorized, Unavailable, run_state
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand
from sdh2svc.sim.cable import Cable
from sdh2svc.sim.lab import SimulatedHand
from tests.live_service import AT_PRESHAPE, LiveService, start_run, start_service
from tests.service.conftest import PATIENT

STEP_DEG = 1.0  # safety.max_step_deg: the furthest a finger may go without a fresh command
WATCH_S = 2.0  # how long the test watches a hand nobody commands (longer only makes it stricter)
FINGER_AXES = (1, 2, 3, 4, 5, 6)  # the coupled fingers and the thumb


@pytest.fixture
async def hand() -> AsyncIterator[tuple[SimulatedHand, Cable]]:
    at_preshape = [AT_PRESHAPE[1]]  # (the services these tests start have it too)
    async with simulated_hand(load_config(overrides=at_preshape), Simulated()) as bench:
        sim = bench.sim
        host, port = sim.urls("sdh")[0].removeprefix("socket://").rsplit(":", 1)
        cable = Cable(host, int(port))
        await cable.plug()
        try:
            yield sim, cable
        finally:
            await cable.close()


def _angles(sim: SimulatedHand) -> tuple[float, ...]:
    """Where the joints are now: the emulator brought up to the present, as its line would."""
    sim.sdh.next_wakeup(asyncio.get_running_loop().time())
    return sim.sdh.actual_deg


def _moved(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return max(abs(a[i] - b[i]) for i in FINGER_AXES)


async def _serve(tmp: Path, sim: SimulatedHand, cable: Cable) -> LiveService:
    """The service on the hand in this process (started on a thread: the hand must answer)."""
    extra = ["--dsa", sim.urls("dsa")[0], "--sdh", cable.url]
    return await asyncio.to_thread(start_service, tmp, viewer=False, sim=False, extra=extra)


async def _stop(svc: LiveService, sig: int = signal.SIGTERM) -> int:
    return await asyncio.to_thread(svc.stop, sig)


def _faulted_and_down(st: dict[str, Any]) -> bool:
    """The run has faulted and the service sees the joint line down."""
    return (
        not st["hand"]["connected"]["joints"] and (st["last_run"] or {}).get("status") == "faulted"
    )


async def _start_grasp(svc: LiveService, sim: SimulatedHand) -> None:
    async with svc.client() as client:
        await start_run(client)
        await client.wait_status(run_state("grasping"))
    # let the fingers close for a while: they are moving when the fault comes
    start = _angles(sim)
    async with asyncio.timeout(30):
        while _moved(_angles(sim), start) < 0.3:
            await asyncio.sleep(0.02)


async def test_cable_cut_during_the_grasp_leaves_the_fingers_still(
    hand: tuple[SimulatedHand, Cable], tmp_path: Path
) -> None:
    sim, cable = hand
    svc = await _serve(tmp_path, sim, cable)
    try:
        await _start_grasp(svc, sim)
        await cable.cut()
        at_cut = _angles(sim)
        async with svc.client() as client:  # while the line is down a run is refused, not begun
            await client.wait_status(_faulted_and_down, 30.0)
            runs = len(await client.runs())
            with pytest.raises(Unavailable, match=r"the joint line \(.*\) is down"):
                await client.start_run()
            with pytest.raises(Unavailable, match=r"the joint line \(.*\) is down"):
                await client.open_hand()
            assert len(await client.runs()) == runs  # nothing recorded
        await asyncio.sleep(WATCH_S)
        assert _moved(_angles(sim), at_cut) <= STEP_DEG
        await cable.plug()  # the link comes back: the service stops all axes, nothing moves
        async with svc.client() as client:
            st = await client.wait_status(lambda st: st["hand"]["connected"]["joints"], 30.0)
        assert st["last_run"]["status"] == "faulted", st["last_run"]
        await asyncio.sleep(WATCH_S / 2)
        assert _moved(_angles(sim), at_cut) <= STEP_DEG
    finally:
        assert await _stop(svc) == 0, "".join(svc.log)


@contextlib.asynccontextmanager
async def _silenced_mid_grasp(
    hand: tuple[SimulatedHand, Cable], tmp: Path, *, lose: bool = False
) -> AsyncIterator[tuple[LiveService, tuple[float, ...]]]:
    """A service mid-grasp whose joint line has just fallen silent, its port still open (with
    ``lose``, what is sent meanwhile is lost): the service and the angles when it fell silent;
    the line answers again on leaving."""
    sim, cable = hand
    svc = await _serve(tmp, sim, cable)
    try:
        await _start_grasp(svc, sim)
        cable.hold(lose=lose)
        yield svc, _angles(sim)
    finally:
        cable.resume()
        assert await _stop(svc) == 0, "".join(svc.log)


async def test_an_estop_the_silent_line_lost_powers_the_hand_off_once_it_answers(
    hand: tuple[SimulatedHand, Cable], tmp_path: Path
) -> None:
    """The e-stop answers after one reply's timeout (not after the link's retries), saying the
    hand has not confirmed yet. A hung controller loses what was sent to it: the power-off
    never arrives, and the stop's attempts end in failure. Once the line answers again (the
    link's next poll), the power-off it owes goes out first; the fingers never moved."""
    sim, cable = hand
    async with _silenced_mid_grasp(hand, tmp_path, lose=True) as (svc, at_hold), \
            svc.client() as client:  # fmt: skip
        out = await client.estop()
        assert out["estopped"] is True and out["hand_reached"] is False, out
        assert "has not confirmed the stop yet" in out["detail"], out
        st = await client.wait_run((await client.status())["run"]["id"], timeout=60.0)
        assert st["status"] == "e-stopped", st
        assert all(sim.sdh.powered)  # nothing reached the hand
        # every client sees it in the status, not only the one that asked
        await client.wait_status(lambda st: st["estop"] is not None, 10.0)
        assert (await client.status())["estop"]["hand_reached"] is False
        cable.resume()
        await client.wait_status(lambda st: not any(sim.sdh.powered), 30.0)
        st = await client.wait_status(lambda st: st["estop"]["hand_reached"], 10.0)
        assert st["estopped"] is True
        assert _moved(_angles(sim), at_hold) <= STEP_DEG


async def test_a_silent_joint_line_faults_the_run_and_shows_as_down(
    hand: tuple[SimulatedHand, Cable], tmp_path: Path
) -> None:
    """The run faults within two replies' timeouts (not after every retry), the status shows
    the line down and runs are refused; once it answers again it shows connected, and the
    fingers never moved."""
    sim, cable = hand
    async with _silenced_mid_grasp(hand, tmp_path) as (svc, at_hold), svc.client() as client:
        st = await client.wait_status(_faulted_and_down, 30.0)
        assert "the line is silent" in st["last_run"]["message"], st["last_run"]
        with pytest.raises(Unavailable, match="does not answer"):
            await client.start_run()
        cable.resume()
        await client.wait_status(lambda st: st["hand"]["connected"]["joints"], 30.0)
        assert _moved(_angles(sim), at_hold) <= STEP_DEG


async def test_a_run_waits_for_the_tactile_line(tmp_path: Path) -> None:
    """With the tactile line down a run is refused (503, nothing recorded); once it is back,
    the same request starts a run."""
    at_preshape = [AT_PRESHAPE[1]]  # (the services these tests start have it too)
    async with simulated_hand(load_config(overrides=at_preshape), Simulated()) as bench:
        sim = bench.sim
        host, port = sim.urls("dsa")[0].removeprefix("socket://").rsplit(":", 1)
        dsa = Cable(host, int(port))
        await dsa.plug()
        extra = ["--dsa", dsa.url, "--sdh", sim.urls("sdh")[0]]
        svc = await asyncio.to_thread(start_service, tmp_path, viewer=False, sim=False,
                                      extra=extra)  # fmt: skip
        try:
            async with svc.client() as client:
                await dsa.cut()
                await client.wait_status(lambda st: not st["hand"]["connected"]["tactile"], 30.0)
                with pytest.raises(Unavailable, match=r"the tactile line \(.*\) is down"):
                    await client.start_run()
                assert await client.runs() == []
                await dsa.plug()
                await client.wait_status(lambda st: st["hand"]["connected"]["tactile"], 30.0)
                run = await start_run(client)
                await client.stop_run()
                assert (await client.wait_run(run["run_id"], timeout=60.0))["id"] == run["run_id"]
        finally:
            await dsa.close()
            assert await _stop(svc) == 0, "".join(svc.log)


async def test_kill_during_the_grasp_then_restart_leaves_the_fingers_still(
    hand: tuple[SimulatedHand, Cable], tmp_path: Path
) -> None:
    sim, cable = hand
    svc = await _serve(tmp_path, sim, cable)
    try:
        await _start_grasp(svc, sim)
    finally:
        await _stop(svc, signal.SIGKILL)
    at_kill = _angles(sim)
    await asyncio.sleep(WATCH_S)
    assert _moved(_angles(sim), at_kill) <= STEP_DEG
    again = await _serve(tmp_path, sim, cable)
    try:
        async with again.client() as client:
            st = await client.status()
            assert st["hand"]["connected"]["joints"]
            runs = await client.runs()
        assert runs[0]["status"] == "interrupted"
        # the status says so too: a person should look (the object may still be held)
        assert st["last_run"]["id"] == runs[0]["id"], st["last_run"]
        assert st["last_run"]["status"] == "interrupted", st["last_run"]
        assert "may still hold the object" in st["last_run"]["message"]
        await asyncio.sleep(WATCH_S / 2)
        assert _moved(_angles(sim), at_kill) <= STEP_DEG
    finally:
        assert await _stop(again) == 0, "".join(again.log)


async def test_the_estop_latch_survives_a_restart(tmp_path: Path) -> None:
    svc = start_service(tmp_path, viewer=False, token="secret")
    try:
        async with AsyncClient(svc.url) as anon:  # no token: stopping is allowed
            assert (await anon.estop())["estopped"] is True
    finally:
        svc.stop(signal.SIGKILL)  # the PC loses power, say
    again = start_service(tmp_path, viewer=False, token="secret")
    try:
        async with again.client() as client, AsyncClient(again.url) as anon:
            st = await client.status()
            assert st["estopped"] and st["estop"]["since"]
            # the latch from disk powered the hand off in the new connection's handshake
            st = await client.wait_status(lambda st: st["estop"]["hand_reached"], 10.0)
            assert st["estopped"] and st["hand"]["connected"]["joints"]
            with pytest.raises(Conflict, match="e-stop"):
                await client.start_run()
            with pytest.raises(Conflict):
                await client.open_hand()
            with pytest.raises(Unauthorized):  # releasing needs the token
                await anon.release_estop()
            assert (await client.release_estop())["estopped"] is False
            assert (await client.status())["estop"] is None
    finally:
        assert again.stop() == 0, "".join(again.log)


async def test_after_a_fault_open_hand_releases_the_object(tmp_path: Path) -> None:
    """An e-stopped run leaves the fingers where they were; once released, Open hand opens them
    (in increments, to the run's own pre-shape pose), and refuses while a run or the e-stop is
    on."""
    cfg = load_config()
    svc = await asyncio.to_thread(start_service, tmp_path, viewer=False)
    try:
        async with svc.client() as client:
            await start_run(client)
            await client.wait_status(run_state("grasping"))
            with pytest.raises(Conflict, match="stop it first"):
                await client.open_hand()
            assert (await client.estop())["estopped"] is True
            with pytest.raises(Conflict, match="e-stop"):
                await client.open_hand()
            assert (await client.release_estop())["estopped"] is False
            held = await client.status()
            assert held["last_run"]["status"] == "e-stopped"
            assert (await client.open_hand()) == {"state": "opening"}  # 202
            st = await client.wait_status(lambda st: not st["hand"]["opening"])
            angles = st["hand"]["angles_deg"]
            assert max(abs(a - p) for a, p in zip(angles, cfg.run.preshape_deg, strict=True)) < 0.5
    finally:
        assert await _stop(svc) == 0, "".join(svc.log)


async def test_a_huge_body_during_a_run_does_not_disturb_it(
    tmp_path: Path, long_runs: tuple[str, ...]
) -> None:
    """300 MB sent in chunks (no Content-Length) by a client without the token, mid-run: refused
    after the first `service.max_body_kb` — the run goes on as if nothing happened. (Its
    watchdogs are PATIENT's: what it is about is the body, and a grasp faulted by a frame the
    loaded CI machine delayed, once, says nothing of that.)"""
    svc = await asyncio.to_thread(start_service, tmp_path, viewer=False, token="secret",
                                  extra=(*long_runs, *PATIENT))  # fmt: skip

    def chunks() -> Iterator[bytes]:
        block = b"[" + b"1," * (512 * 1024) + b"1]"
        for _ in range(300):
            yield block

    try:
        async with svc.client() as client:
            await start_run(client)
            before = (await client.wait_status(_rolling))["run"]["iteration"]
            refused = await asyncio.to_thread(_send_huge, svc.url, chunks())
            assert refused in (413, "reset")

            def rolled_on(st: dict[str, Any]) -> bool:
                assert st["run"]["state"] == "rolling", st["run"]
                return bool(st["run"]["iteration"] >= before + 60)

            await client.wait_status(rolled_on, timeout=30.0, poll_s=0.1)
            await client.estop()  # ends it where it is: a stop's release would add ≈ 5 s
    finally:
        assert await _stop(svc) == 0, "".join(svc.log)


def _rolling(st: dict[str, Any]) -> bool:
    """The run rolls; an AssertionError naming how it ended if it ended first (not a wait for
    a state that will never come)."""
    run = st.get("run") or {}
    assert run.get("status") in (None, "running"), f"the run ended before rolling: {run}"
    return run.get("state") == "rolling"


def _send_huge(url: str, body: Iterator[bytes]) -> int | str:
    try:
        r = httpx.patch(url + "/api/params", content=body, timeout=60,
                        headers={"Content-Type": "application/json"})  # fmt: skip
    except (httpx.WriteError, httpx.RemoteProtocolError, httpx.ReadError):
        return "reset"  # the service answered 413 and closed while we were still sending
    return r.status_code
