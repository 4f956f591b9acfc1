"""A force above the ceiling in every phase, and outages of 10–30 s, through the service in this
process on the virtual clock (the app over ASGI; the hand in fast mode: seconds of wall time).

A person presses a distal pad (POST /api/sim/press) during the pre-shape, the grasp or the
rolling: the run faults with force_ceiling, says so before the fingers open, opens them to the
pre-shape in increments of at most ``safety.max_step_deg`` within the joint limits, and then
nothing moves; an e-stop during that opening stops it and keeps why it was opening. A joint or
tactile line cut or silent for 10–30 s in the pre-shape, mid-grasp or mid-roll, or the joint
line during the opening at a run's end: the run faults, the fingers move at most one increment
(in the pre-shape, as far as the move goes until a frame is stale), the status shows the line
down and runs are refused until it is back, nothing moves when it comes back, and a new run
then starts. The tactile line lost during that opening lets the opening finish (it needs no
frames) and no further.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from sdh2svc.bus.joint import LinkLost
from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Bench, Real, Simulated, simulated_hand
from sdh2svc.service.hand_service import HandService
from sdh2svc.sim.cable import Cable
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.lab import SimulatedHand
from tests.service.test_sim_press import service

FINGERS = (1, 2, 3, 4, 5, 6)  # the coupled fingers and the thumb
EPS = 1e-4  # the binary protocol's float32 angles
WATCH_S = 5.0  # how long a still hand is watched (virtual seconds)
# 30 N over r = 10 mm on Finger 1's distal pad: F ≈ 7.4 against 3 × Fd = 6 (a 4 mm press
# saturates its cells and reads F ≈ 3)
PRESS = {"pad": 1, "x_mm": 10.0, "y_mm": 10.0, "force_n": 30.0, "radius_mm": 10.0,
         "duration_s": 30.0}  # fmt: skip


def _cfg(tmp: Path, phase: str = "") -> Settings:
    """The service's configuration; one stroke when the test waits for the opening at the end."""
    strokes = ["rolling.cycles=1"] if phase == "releasing" else []
    return load_config(overrides=[f"storage.db_path='{tmp / 'runs.sqlite'}'", *strokes],
                       use_env=False)  # fmt: skip


@contextlib.asynccontextmanager
async def _cabled(
    cfg: Settings, tmp: Path, *, plugged: bool = True
) -> AsyncIterator[tuple[Bench, dict[str, Cable], Real]]:
    """The simulated hand in fast mode behind a cable per line (to cut, hold or plug), and
    where a service finds it; ``plugged=False``: the hand switched off (or unplugged) yet."""
    async with simulated_hand(cfg, Simulated(fast=True)) as bench:
        cables = {n: Cable.unix(bench.sim.urls(n)[0], str(tmp / f"{n}.sock"))
                  for n in ("dsa", "sdh")}  # fmt: skip
        try:
            if plugged:
                for cable in cables.values():
                    await cable.plug()
            yield bench, cables, Real(cables["dsa"].url, cables["sdh"].url, patient=not plugged)
        finally:
            for cable in cables.values():
                await cable.close()


def _moved(a: Sequence[float], b: Sequence[float]) -> float:
    return max(abs(a[i] - b[i]) for i in FINGERS)


@dataclass(frozen=True)
class Command:
    """A target command as it went out: the run's phase and message then, the targets, and the
    hand's true angles then."""

    phase: str
    message: str
    targets: tuple[float, ...]
    actual: tuple[float, ...]


Around = Callable[[Sequence[float], Callable[[Sequence[float]], Awaitable[Any]]], Awaitable[Any]]


def _around_targets(station: HandService, around: Around) -> None:
    """Every target command the service sends from now on goes through ``around(angles, send)``."""
    joints = station.joints
    assert joints is not None
    for name in ("set_targets", "send_targets"):
        original = getattr(joints, name)
        setattr(joints, name, lambda angles, _send=original: around(angles, _send))


def _spy(station: HandService, sim: SimulatedHand) -> list[Command]:
    """Every target command the service sends from now on."""
    sent: list[Command] = []

    async def spied(angles: Sequence[float], send: Callable[[Sequence[float]], Awaitable[Any]]
                    ) -> Any:  # fmt: skip
        run = station.status()["run"] or {}
        sent.append(Command(run.get("state", ""), run.get("message", ""), tuple(angles),
                            sim.sdh.actual_deg))  # fmt: skip
        return await send(angles)

    _around_targets(station, spied)
    return sent


async def _until_phase(station: HandService, phase: str) -> None:
    async with asyncio.timeout(120):
        while station.run is None or station.run.runner.phase.value != phase:
            await asyncio.sleep(0.01)


async def _until_ended(station: HandService) -> None:
    async with asyncio.timeout(120):
        while station.running:
            await asyncio.sleep(0.01)


async def _start(c: httpx.AsyncClient, station: HandService, phase: str, after_s: float) -> None:
    r = await c.post("/api/runs", json={})
    assert r.status_code == 201, r.text
    await _until_phase(station, phase)
    await asyncio.sleep(after_s)  # the fingers are moving when the fault comes


# --- a force above the ceiling in every phase ------------------------------------------------


@pytest.mark.parametrize("estop", [False, True], ids=["opens", "estop"])
@pytest.mark.parametrize(("phase", "after_s"), [("pre-shape", 0.5), ("grasping", 1.0),
                                                ("rolling", 0.5)])  # fmt: skip
def test_a_pad_press_above_the_ceiling_faults_and_opens_the_hand_in_steps(
    tmp_path: Path, phase: str, after_s: float, estop: bool
) -> None:
    cfg = _cfg(tmp_path)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            station = services.station
            assert station.bench is not None
            sim = station.bench.sim
            sent = _spy(station, sim)
            await _start(c, station, phase, after_s)
            await _press_until_said(c, station, phase)
            if estop:  # a few increments into the opening
                n = len(sent)
                while len(sent) < n + 3:
                    await asyncio.sleep(0.005)
                assert (await c.post("/api/estop")).json()["hand_reached"] is True
            await _until_ended(station)
            end = sim.sdh.actual_deg
            await asyncio.sleep(WATCH_S)
            assert _moved(sim.sdh.actual_deg, end) < EPS  # nothing moves afterwards
            _check_opening(cfg, sent)
            last = _check_record(station, phase)
            if estop:
                assert last["status"] == "e-stopped", last
                assert last["message"].startswith("emergency stop (after force_ceiling: ")
                assert not any(sim.sdh.powered)
            else:
                assert last["status"] == "faulted", last
                assert last["message"].startswith("force_ceiling: ")
                assert _moved(end, cfg.run.preshape_deg) < 0.5  # open: the object let go

    run_fast(main())


async def _press_until_said(c: httpx.AsyncClient, station: HandService, phase: str) -> None:
    """Press Finger 1's distal pad; the run leaves ``phase`` for the opening, saying why."""
    assert (await c.post("/api/sim/press", json=PRESS)).status_code == 202
    assert station.run is not None
    runner = station.run.runner
    async with asyncio.timeout(5):  # the next frames trip it
        while runner.phase.value == phase:
            await asyncio.sleep(0.005)
    run = (await c.get("/api/status")).json()["run"]
    assert run["state"] == "releasing", run
    # said before it opens, with the pressed pad's own force (the other barely touches)
    assert run["message"].startswith("force_ceiling: F1 = "), run  # pad 1: Finger 1's


def _check_opening(cfg: Settings, sent: list[Command], said: str = "force_ceiling") -> None:
    """Every target within the joint limits; the opening's increments ≤ max_step_deg from
    where the fingers were, each sent with the run's message beginning with ``said`` (the
    fault, already said)."""
    lim = cfg.limits
    for s in sent:
        assert all(lo <= t <= hi for t, lo, hi in zip(s.targets, lim.min_deg, lim.max_deg,
                                                      strict=True)), s  # fmt: skip
    opening = [s for s in sent if s.phase == "releasing"]
    assert opening and all(s.message.startswith(said) for s in opening)
    assert max(_moved(s.targets, s.actual) for s in opening) <= cfg.safety.max_step_deg + EPS


def _check_record(station: HandService, phase: str) -> dict[str, Any]:
    """The run's record: the fault between ``phase`` and the opening, and the status's end;
    returns the status's last run."""
    assert station.store is not None and station.run is not None
    row = station.store.run(station.run.run_id)
    assert row is not None
    events = [e for e in station.store.events(row["id"]) if e["kind"] in ("phase", "fault")]
    kinds = [(e["kind"], e["detail"].get("fault") or e["detail"].get("phase")) for e in events]
    said = kinds.index(("fault", "force_ceiling"))
    assert kinds[said - 1 : said + 2] == [("phase", phase), ("fault", "force_ceiling"),
                                          ("phase", "releasing")], kinds  # fmt: skip
    assert station.last_run is not None and row["status"] == station.last_run["status"]
    return station.last_run


# --- outages of 10-30 s ----------------------------------------------------------------------


OUTAGES = [  # (line, how, phase, after_s, outage_s)
    ("sdh", "cut", "grasping", 1.0, 20.0),
    ("sdh", "silent", "grasping", 1.0, 30.0),
    ("sdh", "cut", "rolling", 0.5, 10.0),
    ("sdh", "silent", "rolling", 0.5, 20.0),
    ("dsa", "cut", "grasping", 1.0, 10.0),
    ("dsa", "cut", "rolling", 0.5, 30.0),
    ("dsa", "cut", "pre-shape", 0.3, 10.0),
    ("dsa", "silent", "rolling", 0.5, 20.0),
    ("dsa", "silent", "grasping", 1.0, 10.0),
    ("sdh", "cut", "pre-shape", 0.3, 10.0),
    ("sdh", "silent", "pre-shape", 0.3, 20.0),
    ("dsa", "silent", "pre-shape", 0.3, 10.0),
    ("sdh", "cut", "releasing", 0.3, 10.0),
    ("sdh", "silent", "releasing", 0.3, 20.0),
]


def _down(st: dict[str, Any], line: str, reasons: set[str] | None = None) -> bool:
    """Whether the status shows ``line`` down; it then says why (and only then): kept in
    ``reasons``."""
    key = "joints" if line == "sdh" else "tactile"
    down = not st["hand"]["connected"][key]
    why = st["links"][f"{key}_down"]
    assert (why is not None) == down, st["links"]
    if why is not None and reasons is not None:
        reasons.add(why)
    return down


@pytest.mark.parametrize(("line", "how", "phase", "after_s", "outage_s"), OUTAGES)
def test_a_long_outage_faults_the_run_and_nothing_moves(
    tmp_path: Path, line: str, how: str, phase: str, after_s: float, outage_s: float
) -> None:
    cfg = _cfg(tmp_path, phase)

    async def main() -> None:
        async with (
            _cabled(cfg, tmp_path) as (bench, cables, where),
            service(cfg, where) as (c, services),
        ):
            await _outage(c, services.station, bench.sim, cables[line], line, how,
                          (phase, after_s), outage_s)  # fmt: skip
            bench.place()  # as in a lab: the object back between the fingertips
            await _new_run_works(c, services.station)

    run_fast(main())


async def _outage(
    c: httpx.AsyncClient, station: HandService, sim: SimulatedHand, cable: Cable, line: str,
    how: str, at: tuple[str, float], outage_s: float,
) -> None:  # fmt: skip
    """The line out for ``outage_s`` from ``at`` (phase, s into it), watched, then back."""
    loop, cfg = asyncio.get_running_loop(), station.cfg
    step = cfg.safety.max_step_deg
    if at[0] == "pre-shape" and line == "dsa":  # paced by joint round trips, not frames: on
        step += cfg.run.preshape_velocity_deg_s * cfg.safety.stale_frame_ms / 1000  # till stale
    await _start(c, station, *at)
    began, t0 = sim.sdh.actual_deg, loop.time()
    if how == "cut":
        await cable.cut()
    else:
        cable.hold()
    down_at = said_at = None
    reasons: set[str] = set()
    while loop.time() - t0 < outage_s:
        await asyncio.sleep(0.1)
        assert _moved(sim.sdh.actual_deg, began) <= step + EPS  # one increment (or as above)
        st = (await c.get("/api/status")).json()
        run = st["run"]
        if _down(st, line, reasons) and down_at is None:
            down_at = loop.time()
        if said_at is None and run["message"]:
            said_at = loop.time()
        if run["status"] != "running":  # faulted: the line shows down, runs are refused
            assert run["status"] == "faulted" and _down(st, line), st
            assert (await c.post("/api/runs", json={})).status_code == 503
    assert down_at is not None and said_at is not None
    # the status said why: the line silent with its port open, or the cable's end and the
    # refused reconnects
    said = ("(its port is open)",) if how == "silent" else ("end of stream", "refused")
    assert any(w in r for r in reasons for w in said), reasons
    fault = {"sdh": "joint_error: ", "dsa": "stale_sensor: "}[line]
    assert station.last_run is not None and station.last_run["message"].startswith(fault)
    # a silent joint line fails a command within two replies' timeouts; the run says so then,
    # not after its halt's commands have timed out too (seconds later)
    assert said_at - down_at <= 1.5, (said_at - down_at, station.last_run)
    back = sim.sdh.actual_deg
    if how == "cut":
        await cable.plug()
    else:
        cable.resume()
    async with asyncio.timeout(30):  # the link reconnects by itself (back-off up to 4 s)
        while _down((await c.get("/api/status")).json(), line):
            await asyncio.sleep(0.1)
    await asyncio.sleep(WATCH_S)
    # nothing moves when it comes back; a line that was silent delivers what it held back (as a
    # stalled converter does), at most the run's last command: one increment
    limit = EPS if how == "cut" else step + EPS
    assert _moved(sim.sdh.actual_deg, back) < limit


@pytest.mark.parametrize("how", ["cut", "silent"])
def test_a_tactile_outage_while_opening_lets_the_opening_finish(tmp_path: Path, how: str) -> None:
    """The opening at a run's end needs no frames (it checks no force: opening is the remedy for
    a high F) and each of its increments is commanded from the joint angles just read. A tactile
    line lost then lets it finish at the pre-shape, and no further: the object is let go. Then
    nothing moves, the status shows the line down, runs are refused until it is back."""
    cfg = _cfg(tmp_path, "releasing")

    async def main() -> None:
        async with simulated_hand(cfg, Simulated(fast=True)) as bench:
            sim = bench.sim
            cable = Cable.unix(sim.urls("dsa")[0], str(tmp_path / "dsa.sock"))
            await cable.plug()
            try:
                where = Real(cable.url, sim.urls("sdh")[0])
                async with service(cfg, where) as (c, services):
                    station = services.station
                    sent = _spy(station, sim)
                    await _start(c, station, "releasing", 0.3)  # the fingers are opening
                    if how == "cut":
                        await cable.cut()
                    else:
                        cable.hold()
                    await _until_ended(station)
                    end = sim.sdh.actual_deg
                    assert _moved(end, cfg.run.preshape_deg) < 0.5, end  # open: let go
                    _check_opening(cfg, sent, said="")  # no fault: the run's own end
                    assert station.last_run is not None
                    assert station.last_run["status"] == "completed", station.last_run
                    loop = asyncio.get_running_loop()
                    t0 = loop.time()
                    while loop.time() - t0 < 3.0:  # the line is seen down (at stall_s)
                        st = (await c.get("/api/status")).json()
                        if _down(st, "dsa"):
                            break
                        await asyncio.sleep(0.1)
                    assert _down(st, "dsa"), st["links"]
                    assert (await c.post("/api/runs", json={})).status_code == 503
                    await asyncio.sleep(WATCH_S)
                    assert _moved(sim.sdh.actual_deg, end) < EPS  # nothing moves afterwards
                    if how == "cut":
                        await cable.plug()
                    else:
                        cable.resume()
                    async with asyncio.timeout(30):  # back by itself
                        while _down((await c.get("/api/status")).json(), "dsa"):
                            await asyncio.sleep(0.1)
                    bench.place()
                    await _new_run_works(c, station)
            finally:
                await cable.close()

    run_fast(main())


async def _new_run_works(c: httpx.AsyncClient, station: HandService) -> None:
    await _start(c, station, "grasping", 0.5)
    assert (await c.post("/api/runs/stop", json={})).status_code == 202
    await _until_ended(station)
    assert station.last_run is not None and station.last_run["status"] == "stopped"


# --- an e-stop whose latch refuses the run's next command ------------------------------------


@pytest.mark.parametrize("phase", ["rolling", "releasing"])
def test_an_estop_whose_latch_refuses_the_runs_next_command_ends_the_run_estopped(
    tmp_path: Path, phase: str
) -> None:
    """The e-stop latches the link at once and stops the run's task a loop iteration later; a
    command the run sends in between is refused by the latch. The run must still end
    e-stopped (keeping a force-ceiling fault it was answering), never as a fault of that refused
    command: an e-stop came in the audit as an opening's command went out, and the run was
    recorded 'faulted: force_ceiling'."""
    cfg = _cfg(tmp_path)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            station = services.station
            joints = station.joints
            assert joints is not None and station.bench is not None
            fired: list[asyncio.Future[Any]] = []  # the e-stop, once it came

            async def racing(angles: Sequence[float], _original: Any) -> Any:
                run = station.run
                if not fired and run is not None and run.runner.phase.value == phase:
                    fired.append(asyncio.ensure_future(station.estop()))
                    await asyncio.sleep(0)  # the e-stop's first step: the link has latched
                    assert joints.estopped
                return await _original(angles)

            _around_targets(station, racing)
            await _start(c, station, "rolling", 0.5)
            if phase == "releasing":
                assert (await c.post("/api/sim/press", json=PRESS)).status_code == 202
            await _until_ended(station)
            assert fired and (await fired[0])["hand_reached"] is True
            last = station.last_run
            assert last is not None and last["status"] == "e-stopped", last
            if phase == "releasing":
                assert last["message"].startswith("emergency stop (after force_ceiling: "), last
            else:
                assert last["message"] == "emergency stop", last
            assert station.store is not None and station.run is not None
            events = station.store.events(station.run.run_id)
            ends = [e["detail"]["status"] for e in events if e["kind"] == "end"]
            assert ends == ["e-stopped"], ends
            faults = [e["detail"]["fault"] for e in events if e["kind"] == "fault"]
            assert faults == ([] if phase == "rolling" else ["force_ceiling"]), faults

    run_fast(main())


def test_an_estop_on_a_silent_joint_line_shows_the_run_estopped_at_once(tmp_path: Path) -> None:
    """The joint line falls silent mid-roll (a hung controller), then the e-stop comes: its
    power-off waits behind the attempt in flight, but the status says the run is e-stopped in
    the same instant as the latch (it said `rolling` beside `estopped: true` for seconds)."""
    cfg = _cfg(tmp_path)

    async def main() -> None:
        async with (
            _cabled(cfg, tmp_path) as (_, cables, where),
            service(cfg, where) as (c, services),
        ):
            station = services.station
            await _start(c, station, "rolling", 0.5)
            cables["sdh"].hold()
            await asyncio.sleep(0.05)  # the run's next exchange now waits on the line
            estop = asyncio.ensure_future(c.post("/api/estop"))
            while station.joints is None or not station.joints.estopped:
                await asyncio.sleep(0)
            polls = 0
            while not estop.done():  # the power-off on its way through the silence
                st = (await c.get("/api/status")).json()
                assert st["estopped"] and st["run"]["state"] == "e-stopped", st["run"]
                polls += 1
                await asyncio.sleep(0.1)
            assert polls >= 3, polls  # it waited (≈ a reply's timeout) meanwhile
            assert (await estop).json()["hand_reached"] is False  # owed to the hand
            cables["sdh"].resume()
            await _until_ended(station)
            assert station.last_run is not None
            assert station.last_run["status"] == "e-stopped", station.last_run

    run_fast(main())


# --- stop and e-stop from every phase --------------------------------------------------------


@pytest.mark.parametrize("action", ["stop", "estop"])
@pytest.mark.parametrize("phase", ["pre-shape", "grasping", "rolling", "releasing", "opening"])
def test_stop_and_estop_work_from_every_phase(tmp_path: Path, phase: str, action: str) -> None:
    """A run in each of its moving phases, or the hand opening (POST /api/hand/open), 0.3 s in.
    A stop ends the run with the hand opened to the pre-shape (a run already opening finishes
    that, completed), or holds an opening hand where it is; an e-stop turns the motors off where
    the fingers are and ends the run e-stopped. Then nothing moves."""
    cfg = _cfg(tmp_path, phase)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            station = services.station
            assert station.bench is not None
            sim = station.bench.sim
            said: list[tuple[str, dict[str, Any]]] = []  # the hand's own events
            hand_event = station._hand_event

            def note(kind: Any, detail: dict[str, Any]) -> None:
                said.append((kind, detail))
                hand_event(kind, detail)

            station._hand_event = note  # type: ignore[method-assign]
            if phase == "opening":  # from the pose the hand starts in
                assert (await c.post("/api/hand/open", json={})).status_code == 202
                await asyncio.sleep(0.3)
                assert station.opening
            else:
                await _start(c, station, phase, 0.3)
            if action == "stop":
                assert (await c.post("/api/runs/stop", json={})).status_code == 202
            else:
                r = await c.post("/api/estop")
                assert r.status_code == 200 and r.json()["hand_reached"] is True, r.text
            await _until_ended(station)
            async with asyncio.timeout(5):
                while station.opening:
                    await asyncio.sleep(0.01)
            end = sim.sdh.actual_deg
            await asyncio.sleep(WATCH_S)
            assert _moved(sim.sdh.actual_deg, end) < EPS  # nothing moves afterwards
            assert any(sim.sdh.powered) is (action == "stop")
            opened = _moved(end, cfg.run.preshape_deg) < 0.5
            last = station.last_run
            if phase == "opening":
                assert last is None and not opened  # held where the stop found it
                # said as stopped, before the e-stop's own event, however the stop met it
                stopped = ("opened", {"completed": False, "message": "stopped"})
                assert said == [("open", {}), stopped, *([("estop", {})] if action == "estop"
                                                         else [])], said  # fmt: skip
            elif action == "stop":
                assert last is not None and opened
                assert last["status"] == ("completed" if phase == "releasing" else "stopped")
            else:
                assert last is not None and last["status"] == "e-stopped", last

    run_fast(main())


# --- a service started before its hand ---------------------------------------------------------


def test_a_service_started_before_its_hand_waits_for_it(tmp_path: Path) -> None:
    """The PC boots first: the service used to exit at once (4) with the hand off or its
    adapters not plugged in, and with it the dashboard, the status and the e-stop. It comes up
    now: both lines down with why, runs refused, an e-stop taken and owed to the hand; once the
    hand is on, the owed power-off reaches it before anything else, and after a release a run
    works. Nothing moves meanwhile."""
    cfg = _cfg(tmp_path)

    async def main() -> None:
        async with _cabled(cfg, tmp_path, plugged=False) as (bench, cables, where):
            sim = bench.sim
            async with service(cfg, where) as (c, services):
                station = services.station
                began = sim.sdh.actual_deg
                await asyncio.sleep(3.0)
                st = (await c.get("/api/status")).json()
                assert st["hand"]["connected"] == {"joints": False, "tactile": False}
                for line in ("joints", "tactile"):
                    assert "cannot open" in st["links"][f"{line}_down"], st["links"]
                r = await c.post("/api/runs", json={})
                assert r.status_code == 503 and "is down" in r.text, r.text
                assert (await c.post("/api/estop")).status_code == 200
                st = (await c.get("/api/status")).json()
                assert st["estopped"] and st["estop"]["hand_reached"] is False
                for cable in cables.values():  # the hand switched on
                    await cable.plug()
                async with asyncio.timeout(30):
                    while not all((await c.get("/api/status")).json()["hand"]
                                  ["connected"].values()):  # fmt: skip
                        await asyncio.sleep(0.1)
                st = (await c.get("/api/status")).json()
                assert st["links"]["joints_down"] is None is st["links"]["tactile_down"]
                assert st["estop"]["hand_reached"] is True  # powered off first
                assert _moved(sim.sdh.actual_deg, began) < EPS
                assert (await c.post("/api/estop/release", json={})).status_code == 200
                await _new_run_works(c, station)

    run_fast(main())


@pytest.mark.parametrize("reached", [True, False], ids=["hand-reached", "line-failed"])
def test_an_estop_while_a_finished_run_is_recorded_is_said_as_the_hands(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reached: bool
) -> None:
    """The run has ended (stopped) and its end is still being written (the database held by
    another program) when an e-stop comes: the run keeps its end, and the hand's e-stop is
    published as the hand's own event (it was said nowhere), also when the line fails it."""
    from sdh2svc.service import recording
    from sdh2svc.service.telemetry import Event

    cfg = _cfg(tmp_path)
    writing = asyncio.Event()
    finish = recording.RecordedRun._finish

    async def slow_finish(self: recording.RecordedRun, *args: Any, **kw: Any) -> Any:
        writing.set()
        await asyncio.sleep(3.0)
        return await finish(self, *args, **kw)

    monkeypatch.setattr(recording.RecordedRun, "_finish", slow_finish)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            station = services.station
            published: list[Any] = []
            publish = station.hub.publish
            monkeypatch.setattr(station.hub, "publish",
                                lambda m: (published.append(m), publish(m))[1])  # fmt: skip
            await _start(c, station, "rolling", 0.5)
            assert (await c.post("/api/runs/stop", json={})).status_code == 202
            await writing.wait()
            assert station.running  # the run's task is writing its end
            if not reached:
                joints = station.joints
                assert joints is not None

                async def lost() -> Any:
                    raise LinkLost("the joint line is gone")

                monkeypatch.setattr(joints, "emergency_stop", lost)
            r = await c.post("/api/estop")
            assert r.status_code == 200 and r.json()["hand_reached"] is reached, r.text
            await _until_ended(station)
            kinds = [m.kind for m in published if isinstance(m, Event)]
            assert kinds.index("end") < kinds.index("estop"), kinds
            last = station.last_run
            assert last is not None and last["status"] == "stopped", last

    run_fast(main())
