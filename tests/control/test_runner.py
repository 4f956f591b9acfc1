"""The runner on the simulated hand, through the real drivers and bytes, in fast mode (virtual
clock over Unix sockets): phases, the safety supervisor's reactions, e-stop, recording."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import subprocess
import sys
from collections import Counter
from collections.abc import AsyncIterator, Callable, Coroutine
from pathlib import Path
from typing import Any, TypeVar

import pytest

from sdh2svc.bus.joint import JointLink
from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Bench, Hand, Simulated, connect_hand
from sdh2svc.control import runner as runner_module
from sdh2svc.control.observer import BaseObserver, Event, EventKind
from sdh2svc.control.runner import Phase, Runner
from sdh2svc.control.sample import Sample
from sdh2svc.model.kinematics import pad_gap
from sdh2svc.protocol.sdh import AxisState
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.lab import SimulatedHand

T = TypeVar("T")


def cfg_with(tmp: Path, *extra: str) -> Settings:
    return load_config(overrides=[f"storage.db_path='{tmp / 'runs.sqlite'}'", *extra],
                       use_env=False)  # fmt: skip


@contextlib.asynccontextmanager
async def rig(cfg: Settings, tmp: Path) -> AsyncIterator[tuple[SimulatedHand, Runner]]:
    """The simulated hand in fast mode (its emulators and endpoints) and a runner on it."""
    async with connect_hand(cfg, Simulated(fast=True)) as hand:
        assert hand.bench is not None
        runner = Runner(cfg.control(), hand.joints, hand.tactile, observer=Seen())
        yield hand.bench.sim, runner


@contextlib.asynccontextmanager
async def bench_rig(cfg: Settings) -> AsyncIterator[tuple[Hand, Bench, Runner, asyncio.Task[Any]]]:
    """The simulated hand in fast mode, its bench (the world to change mid-run) and a runner
    already running."""
    async with connect_hand(cfg, Simulated(fast=True)) as hand:
        assert hand.bench is not None
        runner = Runner(cfg.control(), hand.joints, hand.tactile, observer=Seen())
        yield hand, hand.bench, runner, asyncio.create_task(runner.run())


class Seen(BaseObserver):
    """A test's observer: every event as (kind, detail), and hooks called on each."""

    def __init__(self) -> None:
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.hooks: list[Callable[[Event], None]] = []
        self.samples: list[Sample] = []

    def sample(self, sample: Sample) -> None:
        self.samples.append(sample)

    def event(self, event: Event) -> None:
        self.events.append((event.kind, event.detail))
        for hook in self.hooks:
            hook(event)


def seen(runner: Runner) -> Seen:
    assert isinstance(runner.observer, Seen)
    return runner.observer


def fast(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_fast(main())


@pytest.mark.parametrize(
    ("obj", "extra"),
    [("egg", ()), ("rubber", ()), ("cylinder", ("rolling.lambda_gain=3.0",))],  # λ = 3: thesis
)
def test_full_run_completes_its_strokes_without_a_drop(
    tmp_path: Path, obj: str, extra: tuple[str, ...]
) -> None:
    cfg = cfg_with(tmp_path, f"sim.object={obj!r}", *extra)

    async def main() -> tuple[Any, list, Any, list[Sample]]:
        async with rig(cfg, tmp_path) as (hand, runner):
            truth: list[Any] = []

            def snapshot(e: Event) -> None:
                if e.kind is EventKind.PHASE and e.detail["phase"] == "releasing":
                    truth.append(hand.world.truth())

            seen(runner).hooks.append(snapshot)
            result = await runner.run()
            return result, seen(runner).events, truth[0], seen(runner).samples

    result, events, truth, samples = fast(main)
    phases = [d["phase"] for k, d in events if k == "phase"]
    assert phases == ["connecting", "pre-shape", "grasping", "rolling", "releasing", "done"]
    assert result.status == "completed" and result.strokes == cfg.rolling.cycles
    at = [s.iteration for s in samples if s.reversal is not None]
    assert sum(result.reversals.values()) == len(at) >= 2 * cfg.rolling.cycles
    assert result.summary()["reversals"] == dict(sorted(result.reversals.items()))
    assert min(b - a for a, b in zip([0, *at], at, strict=False)) >= 5  # every half stroke moved
    assert truth.held and not truth.dropped and truth.slips == 0
    assert truth.rotation_range_deg > 5.0  # it really rolled
    assert max(result.forces) < cfg.safety.force_ceiling_factor * cfg.rolling.grasp_force
    # one iteration per fresh tactile frame: none skipped, none used twice
    assert result.frames_skipped == 0
    assert result.iterations == pytest.approx(result.rolling_s * cfg.run.tactile_rate_hz, rel=0.05)
    # the recognition ran on every iteration: its estimate in the samples and the summary
    assert len(samples) == result.iterations
    assert all(s.rotation_est is not None for s in samples)
    both = sum(s.contact1_kind is not None and s.contact2_kind is not None for s in samples)
    assert both >= 0.9 * len(samples)
    assert samples[-1].object_class is not None
    summary = result.summary()["recognition"]
    assert summary["object_class"] == samples[-1].object_class
    assert [d["recognition"] for k, d in events if k == "end"] == [summary]


def test_force_ceiling_stops_and_opens_the_hand(tmp_path: Path) -> None:
    cfg = cfg_with(tmp_path, "safety.force_ceiling_factor=1.05")

    async def main() -> tuple[Any, list, bool]:
        async with rig(cfg, tmp_path) as (hand, runner):
            result = await runner.run()
            return result, seen(runner).events, hand.world.truth().held

    result, events, held_after = fast(main)
    phases = [d["phase"] for k, d in events if k == "phase"]
    assert result.status == "faulted" and result.message.startswith("force_ceiling")
    tripped = float(re.split(r"F[12] = ", result.message)[1].split()[0])  # the tripping pad
    assert tripped > 1.05 * cfg.rolling.grasp_force
    assert phases[-2:] == ["releasing", "faulted"] and not held_after


def test_a_step_the_supervisor_refuses_is_the_faults_iteration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The refused step is recorded (its sample, its reversal) and the fault is that same
    iteration's, the run's stroke count the one its events show: not the iteration before,
    with a reversal after the fault and a stroke count behind the events."""
    cfg = cfg_with(tmp_path, "rolling.cycles=3")
    real = runner_module.safety.rolling_step

    def refuse_the_third_reversal(r: Any, fd: float, s: Any) -> Any:
        if r.reversal is not None and r.state.half_strokes == 3:
            return runner_module.safety.Violation(runner_module.Fault.STUCK, "(the test's)")
        return real(r, fd, s)

    monkeypatch.setattr(runner_module.safety, "rolling_step", refuse_the_third_reversal)

    async def main() -> tuple[Any, list[Event], list[Sample]]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            events: list[Event] = []
            seen(runner).hooks.append(events.append)
            return await runner.run(), events, seen(runner).samples

    result, events, samples = fast(main)
    assert result.status == "faulted" and "(the test's)" in result.message
    fault = next(e for e in events if e.kind is EventKind.FAULT)
    last = [e for e in events if e.kind is EventKind.REVERSAL][-1]
    assert fault.iteration == last.iteration == samples[-1].iteration
    assert last.detail["half_strokes"] == 3 and result.strokes == last.detail["stroke"] == 1


def test_a_finger_beyond_its_limits_by_more_than_a_step_is_a_joint_fault(tmp_path: Path) -> None:
    """Axis 1 rests 1.5° beyond a limit narrowed since (its reading still plausible): the
    pre-shape's first increment would be a 1.5° step; the run faults, naming the axis, and
    nothing moves."""
    cfg = cfg_with(tmp_path, "limits.max_deg=[90.0, 0.0, 90.0, 90.0, 90.0, 90.0, 90.0]",
                   "sim.start_deg=[0.0, 1.5, 0.0, -90.0, 0.0, 0.0, 0.0]")  # fmt: skip

    async def main() -> tuple[Any, Any]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            result = await runner.run()
            return result, await runner.joints.get_actual()

    result, angles = fast(main)
    said = "joint_error: axis 1 is at 1.5°, outside its joint limits [-90, 0]°"
    assert result.status == "faulted" and result.message.startswith(said), result.message
    assert angles[1] == pytest.approx(1.5, abs=0.05)  # not driven to the limit in one step


def test_no_object_is_a_grasp_fault(tmp_path: Path) -> None:
    # the fingers close as commanded, so the grasp's timeout does not end it: the pads do,
    # once they come within 5 mm of each other with nothing touched
    cfg = cfg_with(tmp_path, "sim.object_height_mm=300.0", "run.grasp_timeout_s=5.0")

    async def main() -> Any:
        async with rig(cfg, tmp_path) as (_hand, runner):
            result = await runner.run()
            return result, await runner.joints.get_actual()

    result, angles = fast(main)
    assert result.status == "faulted" and result.iterations == 0
    assert result.message.startswith("no_contact: fingers closed without touching anything (the "
                                     "pads "), result.message  # fmt: skip
    pose = cfg.control().axes.pose(angles)
    assert 4.0 < pad_gap(pose, cfg.model_context().geom) < 5.0  # stopped as they came close


def test_an_object_between_pads_that_do_not_sense_stops_the_grasp_at_once(tmp_path: Path) -> None:
    # every cell of both distal pads dead: the fingers close on the egg, are stopped by it, and
    # no pad feels it. The grasp ends within its stall window, not after its timeout
    dead = [[m, r, c] for m in (1, 5) for r in range(13) for c in range(6)]
    cfg = cfg_with(tmp_path, f"sim.sensor.dead_texels={json.dumps(dead)}")

    async def main() -> Any:
        async with rig(cfg, tmp_path) as (_hand, runner):
            times: dict[str, float] = {}
            seen(runner).hooks.append(
                lambda e: times.setdefault(e.detail.get("phase", e.kind), e.t)
            )
            return await runner.run(), times

    result, times = fast(main)
    assert result.status == "faulted" and result.iterations == 0
    assert result.message.startswith("no_contact: the fingers stopped closing with nothing "
                                     "touched"), result.message  # fmt: skip
    # the fingers close ≈ 27° to the egg at ≈ 1.9 °/s, then stop: a fault ≈ 2 s later
    assert times["faulted"] - times["grasping"] < cfg.run.grasp_timeout_s


async def _until_touched(hand: Any, runner: Runner, cfg: Settings) -> None:
    """Until a distal pad reads a contact during the grasp (a subscription of the test's own)."""
    axes = cfg.control().axes
    m1, m2 = axes.finger1_distal_matrix, axes.finger2_distal_matrix
    while runner.phase is not Phase.GRASPING:
        await asyncio.sleep(0.01)
    sub = hand.tactile.subscribe({m1, m2}, cfg.run.tactile_rate_hz)
    while True:
        f = await sub.next_frame()
        forces = [runner.ctx.contact(f.matrices[m]).force for m in (m1, m2)]
        if max(forces) > cfg.rolling.contact_force_min:
            return


def test_an_object_taken_away_after_the_touch_stops_the_fingers_before_the_pads_meet(
    tmp_path: Path,
) -> None:
    # the egg touched, then taken from between the fingers: nothing touches any more, so the
    # pads' gap ends the grasp as it ends an empty one, not the timeout (the fingers would close
    # into each other for the rest of it)
    cfg = cfg_with(tmp_path)

    async def main() -> Any:
        async with bench_rig(cfg) as (hand, bench, runner, run):
            await _until_touched(hand, runner, cfg)
            bench.place(bench.obj, height_mm=400.0)  # out of the fingers' reach
            result = await run
            return result, await runner.joints.get_actual()

    result, angles = fast(main)
    assert result.status == "faulted" and result.iterations == 0
    assert result.message.startswith("no_contact: the contact was lost and the fingers closed "
                                     "without touching anything"), result.message  # fmt: skip
    pose = cfg.control().axes.pose(angles)
    assert 4.0 < pad_gap(pose, cfg.model_context().geom) < 5.0


def test_pads_that_go_dead_on_the_object_during_the_grasp_stop_it_at_once(tmp_path: Path) -> None:
    # both distal matrices fail just after the touch: the fingers close on at full speed into
    # an object no pad feels, and stop against it. The stall ends the grasp ≈ 2 s later
    cfg = cfg_with(tmp_path)

    async def main() -> Any:
        async with bench_rig(cfg) as (hand, bench, runner, run):
            await _until_touched(hand, runner, cfg)
            axes = cfg.control().axes
            bench.sim.world.sensor.fail([axes.finger1_distal_matrix,
                                         axes.finger2_distal_matrix])  # fmt: skip
            dead_at = asyncio.get_running_loop().time()
            result = await run
            return result, asyncio.get_running_loop().time() - dead_at

    result, after = fast(main)
    assert result.status == "faulted" and result.iterations == 0
    assert result.message.startswith("no_contact: no pad reads the contact any more, and the "
                                     "fingers stopped closing"), result.message  # fmt: skip
    assert after < 4.0, after  # the stall window (2 s) and the squeeze's own second


def test_a_pad_that_dies_mid_roll_is_named_when_the_run_is_stuck(tmp_path: Path) -> None:
    # Finger 2's distal matrix fails while the egg rolls, Finger 1's still holding it: every
    # iteration then reverses for a lost contact until the run is stuck; the fault says which
    # pad reads nothing while the other holds the grip (the frames cannot tell a pad that
    # stopped reading from an object slid off it: both are said)
    cfg = cfg_with(tmp_path)

    async def main() -> Any:
        async with bench_rig(cfg) as (_hand, bench, runner, run):
            while runner.phase is not Phase.ROLLING:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.5)
            bench.sim.world.sensor.fail([cfg.control().axes.finger2_distal_matrix])
            return await run

    result = fast(main)
    assert result.status == "faulted", result.message
    assert result.message.startswith("stuck: "), result.message
    assert "(last: contact_lost): Finger 2's distal pad reads no contact while Finger 1's " \
        "reads F1 = " in result.message, result.message  # fmt: skip
    assert result.message.endswith("(the object slid off that pad, or the pad stopped reading)")


@pytest.mark.parametrize("lines", [(), ("sim.links.sdh_binary_latency_ms=12",),
                                   ("sim.links.baud=9600",)])  # fmt: skip
def test_an_untouched_grasp_closes_at_its_approach_speed(
    tmp_path: Path, lines: tuple[str, ...]
) -> None:
    """Until a pad touches, the fingers close at run.grasp_approach_velocity_deg_s however old
    the joint angles each frame reads are and however late the frames come (the SDH2
    answering 12 ms late instead of 2: three exchanges a frame no longer fit in its 33 ms;
    lines at 9600 baud): each frame's increment starts from the previous target and covers
    the time since the last frame. Stepping one period from the newest angles, the fingers
    closed at 0.63, 0.23 and 0.10 × the (then 3°/s) speed, and the last two timed out."""
    cfg = cfg_with(tmp_path, *lines)

    async def main() -> tuple[float, float]:
        async with bench_rig(cfg) as (hand, bench, runner, run):
            while runner.phase is not Phase.GRASPING:
                await asyncio.sleep(0.01)
            loop = asyncio.get_running_loop()
            t0, a0 = loop.time(), _true_angles(bench.sim)
            await _until_touched(hand, runner, cfg)
            t1, a1 = loop.time(), _true_angles(bench.sim)
            run.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await run
            i = cfg.control().axes.phi2
            return abs(a1[i] - a0[i]), t1 - t0

    closed, took = fast(main)
    assert closed > 20.0, closed  # the egg is ≈ 25° from the pre-shape
    assert closed / took == pytest.approx(cfg.run.grasp_approach_velocity_deg_s, rel=0.05)


def _true_angles(sim: SimulatedHand) -> tuple[float, ...]:
    """Where the joints are now: the emulator brought up to the present."""
    sim.sdh.next_wakeup(asyncio.get_running_loop().time())
    return sim.sdh.actual_deg


def test_silent_sensor_stream_faults_and_holds(tmp_path: Path) -> None:
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[Any, tuple[float, ...], tuple[float, ...]]:
        async with rig(cfg, tmp_path) as (hand, runner):

            async def unplug() -> None:
                while runner.phase is not Phase.ROLLING:
                    await asyncio.sleep(0.01)
                await asyncio.sleep(0.3)
                hand.endpoints["dsa"][0].disconnect(5.0)

            task = asyncio.create_task(unplug())
            result = await runner.run()
            await task
            emu = hand.sdh
            return result, emu.target_deg, emu.actual_deg

    result, target, actual = fast(main)
    assert result.status == "faulted" and result.message.startswith("stale_sensor")
    assert max(abs(t - a) for t, a in zip(target, actual, strict=True)) < 0.5  # held in place


def test_emergency_stop_mid_roll(tmp_path: Path) -> None:
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[
        Any, Phase, tuple[AxisState, ...], tuple[float, ...], tuple[float, ...]
    ]:
        async with rig(cfg, tmp_path) as (hand, runner):
            run = asyncio.create_task(runner.run())
            while runner.phase is not Phase.ROLLING:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.2)
            await runner.emergency_stop()
            with contextlib.suppress(asyncio.CancelledError):
                await run
            states = await runner.joints.get_state()
            return runner.result, runner.phase, states, hand.sdh.target_deg, hand.sdh.actual_deg

    result, phase, states, target, actual = fast(main)
    assert phase is Phase.ESTOPPED and result.status == "e-stopped"
    assert all(s is AxisState.DISABLED for s in states)
    assert max(abs(t - a) for t, a in zip(target, actual, strict=True)) < 0.5


def test_an_estop_after_the_run_ended_stops_the_hand_and_keeps_the_end(tmp_path: Path) -> None:
    """The service e-stops while a run that has ended is still being recorded: the hand stops,
    but the run keeps its own end (it was relabelled e-stopped, and the task recording it was
    cancelled, so that its end was never written)."""
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[Any, Phase, tuple[AxisState, ...], bool]:
        async with rig(cfg, tmp_path) as (_hand, runner):

            async def stop_soon() -> None:
                while runner.phase is Phase.IDLE:
                    await asyncio.sleep(0.01)
                runner.request_stop()

            stopper = asyncio.create_task(stop_soon())
            await runner.run()  # in this task, as RecordedRun.execute runs it
            await stopper
            recording = asyncio.current_task()
            assert recording is not None
            await runner.emergency_stop()
            states = await runner.joints.get_state()
            return runner.result, runner.phase, states, recording.cancelling() > 0

    result, phase, states, cancelled = fast(main)
    assert result.status == "stopped" and phase is Phase.STOPPED
    assert all(s is AxisState.DISABLED for s in states)  # the hand is e-stopped all the same
    assert not cancelled


def test_parameters_changed_during_the_grasp_are_the_grasps_from_its_next_frame(
    tmp_path: Path,
) -> None:
    # a user lowers Fd for a fragile object while the fingers close: the grasp holds at the new
    # Fd (it squeezed on to the old one while the status showed the new)
    cfg = cfg_with(tmp_path)

    async def main() -> list[tuple[str, dict[str, Any]]]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            run = asyncio.create_task(runner.run())
            while runner.phase is not Phase.GRASPING:
                await asyncio.sleep(0.01)
            runner.set_params(runner.params.model_copy(update={"grasp_force": 1.0}))
            while runner.phase is not Phase.ROLLING:
                await asyncio.sleep(0.01)
            runner.request_stop()
            await run
            return seen(runner).events

    events = fast(main)
    kinds = [k for k, _ in events]
    assert kinds.index(EventKind.PARAMS) < kinds.index(EventKind.GRASPED)
    grasped = next(d for k, d in events if k == EventKind.GRASPED)
    assert 1.0 <= grasped["F"] < 1.5, grasped  # the default Fd is 2


def test_a_force_ceiling_says_so_before_it_opens_and_an_estop_keeps_it(tmp_path: Path) -> None:
    """A force above the ceiling opens the hand: the fault is said as the opening starts (the
    status showed a plain `releasing` for its 3 s), and an e-stop during the opening ends the
    run e-stopped without losing why it was opening (the fault event came only after it)."""
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[list[tuple[str, dict[str, Any]]], str, Any]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            run = asyncio.create_task(runner.run())
            while runner.phase is not Phase.ROLLING:
                await asyncio.sleep(0.01)
            # the grip (≈ Fd = 2) is far above 3 × 0.3: the ceiling trips at the next iteration
            runner.set_params(runner.params.model_copy(update={"grasp_force": 0.3}))
            while runner.phase is not Phase.RELEASING:
                await asyncio.sleep(0.01)
            before = list(seen(runner).events)
            during = runner.result.message
            await runner.emergency_stop()
            with contextlib.suppress(asyncio.CancelledError):
                await run
            return before, during, runner.result

    before, during, result = fast(main)
    faults = [d for k, d in before if k == EventKind.FAULT]
    assert [f["fault"] for f in faults] == ["force_ceiling"], before
    assert during.startswith("force_ceiling: ")
    assert result.status == "e-stopped"
    assert result.message == f"emergency stop (after {during})"


def test_cli_run_json_and_the_recorded_run(tmp_path: Path) -> None:
    db = tmp_path / "runs.sqlite"
    args = [sys.executable, "-m", "sdh2svc", "run", "--sim", "--fast", "--object", "egg",
            "--cycles", "1", "--json", "--set", f"storage.db_path='{db}'"]  # fmt: skip
    r = subprocess.run(args, capture_output=True, text=True, timeout=300)
    out = json.loads(r.stdout)
    keys = ("status", "strokes", "iterations", "reversals", "lambda_initial_mm", "force",
            "sigma_range_deg", "loop_hz", "latency_ms", "frames", "run_id", "truth")  # fmt: skip
    assert set(keys) <= set(out), set(keys) - set(out)
    assert set(out["force"]) == {"mean", "sd", "min", "max"}
    assert set(out["truth"]) >= {"object", "size_mm", "dropped", "slips", "rotation_range_deg"}
    assert out["truth"]["object"] == "egg" and out["frames"]["received"] > 0
    assert (r.returncode == 0) == (out["status"] == "completed")
    base = [sys.executable, "-m", "sdh2svc", "runs"]
    dbset = ["--set", f"storage.db_path='{db}'"]
    listing = subprocess.run([*base, "list", *dbset], capture_output=True, text=True, timeout=60)
    assert f"{out['run_id']:5d}" in listing.stdout
    shown = subprocess.run([*base, "show", str(out["run_id"]), *dbset], capture_output=True,
                           text=True, timeout=60)  # fmt: skip
    run = json.loads(shown.stdout)
    assert run["status"] == out["status"] and run["iterations"] == out["iterations"]
    # the summary counts the reversals by reason; each one is an event with its iteration
    reasons = Counter(e["detail"]["reason"] for e in run["events"] if e["kind"] == "reversal")
    assert out["reversals"] == run["summary"]["reversals"] == dict(sorted(reasons.items()))
    assert sum(reasons.values()) >= 2
    csv_out = subprocess.run([*base, "export", str(out["run_id"]), "--format", "csv", *dbset],
                             capture_output=True, text=True, timeout=60)  # fmt: skip
    assert len(csv_out.stdout.strip().splitlines()) == out["iterations"] + 1
    missing = subprocess.run([*base, "show", "999", *dbset], capture_output=True, text=True,
                             timeout=60)  # fmt: skip
    assert missing.returncode == 3 and "no run 999" in missing.stderr
    from sdh2svc.service.store import RunStore

    store = RunStore(db)
    try:  # every recorded frame is linked to the iteration it was the frame of
        its = [it for _t, it, _ts, _tex in store.frames(out["run_id"])]
        samples = [s["iteration"] for s in store.samples(out["run_id"], 0, 10**6)]
    finally:
        store.close()
    assert its == samples and len(its) == out["iterations"]


def test_cli_run_prints_a_readable_summary(tmp_path: Path) -> None:
    """Without --json: rounded figures with their units, and the simulation's truth in words."""
    args = [sys.executable, "-m", "sdh2svc", "run", "--sim", "--fast", "--object", "cylinder",
            "--cycles", "1", "--set", f"storage.db_path='{tmp_path / 'runs.sqlite'}'"]  # fmt: skip
    r = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert re.search(r"Λ at grasp \d+\.\d mm\n", r.stdout), r.stdout
    assert re.search(r"simulation truth: cylinder \(68\.0 mm\), turned over \d+\.\d°, \d+ slips\n",
                     r.stdout), r.stdout  # fmt: skip


def test_fast_mode_reproduces_a_run_bit_for_bit(tmp_path: Path) -> None:
    """The same seed, the same run: every recorded sample identical, through all the bytes."""
    from sdh2svc.service.headless import run_once
    from sdh2svc.service.store import RunStore

    def once(name: str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        cfg = cfg_with(tmp_path / name, "rolling.cycles=1", "sim.object='rubber'")
        (tmp_path / name).mkdir()
        summary = run_fast(run_once(cfg, Simulated(fast=True)))
        store = RunStore(cfg.storage.db_path)
        try:
            return summary, store.samples(summary["run_id"], 0, 10**6)
        finally:
            store.close()

    a, samples_a = once("a")
    b, samples_b = once("b")
    assert a["status"] == "completed" and len(samples_a) > 20
    assert samples_a == samples_b
    assert a["reversals"] == b["reversals"] and a["force"] == b["force"]


def test_a_headless_run_stopped_through_its_runner_records_why(tmp_path: Path) -> None:
    """`sdh2svc run`'s Ctrl-C (its runner's stop): the run was recorded `stopped` with no
    message. The caller's reason is the message now; a second stop keeps the first's."""
    from sdh2svc.service.headless import run_once
    from sdh2svc.service.store import RunStore

    cfg = cfg_with(tmp_path, "rolling.cycles=3")
    runners: list[Runner] = []

    async def stop_once_rolling() -> None:
        while not runners or runners[0].phase is not Phase.ROLLING:
            await asyncio.sleep(0.01)
        runners[0].request_stop("by Ctrl-C or SIGTERM: the fingers opened to the pre-shape")
        runners[0].request_stop("as the service shut down")

    async def main() -> dict[str, Any]:
        stopper = asyncio.create_task(stop_once_rolling())
        summary = await run_once(cfg, Simulated(fast=True), started=runners.append)
        await stopper
        return summary

    summary = run_fast(main())
    assert summary["status"] == "stopped", summary
    assert summary["message"] == "by Ctrl-C or SIGTERM: the fingers opened to the pre-shape"
    store = RunStore(cfg.storage.db_path)
    try:
        record = store.run(summary["run_id"])
    finally:
        store.close()
    assert record is not None and record["summary"]["message"] == summary["message"]


def test_emergency_stop_mid_grasp(tmp_path: Path) -> None:
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[Any, Phase, tuple[AxisState, ...]]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            run = asyncio.create_task(runner.run())
            while runner.phase is not Phase.GRASPING:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.3)
            await runner.emergency_stop()
            with contextlib.suppress(asyncio.CancelledError):
                await run
            return runner.result, runner.phase, await runner.joints.get_state()

    result, phase, states = fast(main)
    assert phase is Phase.ESTOPPED and result.status == "e-stopped"
    assert all(s is AxisState.DISABLED for s in states)


def test_an_estop_while_the_runs_command_is_on_the_line_powers_off_right_after_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the link stops the hand before the run's task is cancelled: the command on the line
    # finishes and the power-off follows it. (Cancelled first, the task abandoned the command
    # mid-reply: the line resynchronised first, ≈ 90 ms instead of ≈ 5–10.)
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[float, int, Any]:
        async with bench_rig(cfg) as (hand, bench, runner, run):
            sdh = bench.sim.sdh
            while runner.phase is not Phase.ROLLING:
                await asyncio.sleep(0.01)
            on_line = asyncio.Event()
            attempt = JointLink._attempt

            async def watched(self: JointLink, conn: Any, req: Any, *a: Any, **kw: Any) -> Any:
                if req.keyword == "m":  # the run's move, going out now
                    on_line.set()
                return await attempt(self, conn, req, *a, **kw)

            monkeypatch.setattr(JointLink, "_attempt", watched)
            await on_line.wait()
            loop = asyncio.get_running_loop()
            t0, resyncs = loop.time(), hand.joints.stats.resyncs
            stop = asyncio.create_task(runner.emergency_stop())
            while any(sdh.powered):
                await asyncio.sleep(0.0005)
            off_ms = (loop.time() - t0) * 1000
            await stop
            with contextlib.suppress(asyncio.CancelledError):
                await run
            return off_ms, hand.joints.stats.resyncs - resyncs, runner.result

    off_ms, resyncs, result = fast(main)
    assert result.status == "e-stopped"
    assert resyncs == 0 and off_ms < 30.0, (off_ms, resyncs)


def test_lost_joint_line_faults_the_run(tmp_path: Path) -> None:
    cfg = cfg_with(tmp_path)

    async def main() -> Any:
        async with rig(cfg, tmp_path) as (hand, runner):

            async def unplug() -> None:
                while runner.phase is not Phase.ROLLING:
                    await asyncio.sleep(0.01)
                await asyncio.sleep(0.3)
                hand.endpoints["sdh"][0].disconnect(3.0)

            task = asyncio.create_task(unplug())
            result = await runner.run()
            await task
            return result

    result = fast(main)
    assert result.status == "faulted" and result.message.startswith("joint_error")


def test_an_unexpected_error_holds_the_hand_and_ends_the_run_faulted(tmp_path: Path) -> None:
    """An error the run does not expect (a bug; a pad unlike its configured layout raised
    ValueError in the contact estimate) ended the run's task with the fingers at their last
    target, no end event and the run's status `running`: now the hand is held and the run ends
    as a fault ends it, with the error named."""
    cfg = cfg_with(tmp_path)

    async def main() -> tuple[Any, list[tuple[str, dict[str, Any]]], Any, Any]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            task = asyncio.create_task(runner.run())
            while runner.phase is not Phase.GRASPING:
                await asyncio.sleep(0.01)
            await asyncio.sleep(2.0)  # closing on the object

            def broken(_frame: Any) -> Any:
                raise RuntimeError("a bug")

            runner._contacts = broken  # type: ignore[method-assign]
            result = await task
            held = await runner.joints.get_actual()
            await asyncio.sleep(1.0)
            return result, seen(runner).events, held, await runner.joints.get_actual()

    result, events, held, later = fast(main)
    assert result.status == "faulted"
    assert result.message == "internal_error: RuntimeError: a bug"
    assert [d["fault"] for k, d in events if k == EventKind.FAULT] == ["internal_error"]
    assert events[-1][0] == EventKind.END and events[-1][1]["status"] == "faulted"
    assert later == pytest.approx(held, abs=0.01)  # held: nothing moves on
