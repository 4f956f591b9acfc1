"""The run as an async state machine around the pure rolling step (hand-model §8, issue flow).

idle → connecting → pre-shape → grasping → rolling → releasing → done, with stopped, faulted and
e-stopped reachable from every state. One iteration per fresh tactile frame (never twice on the
same frame, never on a stale one); the joint command of an iteration goes out as soon as it is
computed. The safety supervisor (:mod:`sdh2svc.control.safety`) checks every proposal.

The runner talks to the two links only through their driver objects — the same whether the URLs
lead to a real hand or to the simulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from sdh2svc.bus.joint import ControllerMode, JointLink, JointLinkError
from sdh2svc.bus.tactile import FrameTimeout, Subscription, TactileBus, TactileError, TactileFrame
from sdh2svc.config import Settings
from sdh2svc.control.grasp import GraspLaw, grasp_step
from sdh2svc.control.motion import move_to_preshape
from sdh2svc.control.params import RollingParams
from sdh2svc.control.rolling import RollState, StepResult, grip_force, step
from sdh2svc.control.safety import Fault, clamp_targets
from sdh2svc.control.sample import Sample
from sdh2svc.model.contact import ContactEstimate
from sdh2svc.model.kinematics import HandPose


class Phase(StrEnum):
    IDLE = "idle"
    CONNECTING = "connecting"
    PRESHAPE = "pre-shape"
    GRASPING = "grasping"
    ROLLING = "rolling"
    RELEASING = "releasing"
    DONE = "done"
    STOPPED = "stopped"
    FAULTED = "faulted"
    ESTOPPED = "e-stopped"


class RunFault(Exception):
    def __init__(self, fault: Fault, message: str) -> None:
        super().__init__(message)
        self.fault = fault


@dataclass
class RunResult:
    """What a run did; ``status`` is completed | stopped | faulted | dropped | e-stopped."""

    status: str
    message: str = ""
    strokes: int = 0
    iterations: int = 0
    reversals: list[dict[str, Any]] = field(default_factory=list)
    lambda_initial_mm: float | None = None
    forces: list[float] = field(default_factory=list)
    sigmas: list[float] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    rolling_s: float = 0.0
    frames_skipped: int = 0  # fresh frames no rolling iteration ran on

    def summary(self) -> dict[str, Any]:
        f, lat = self.forces, sorted(self.latencies_ms)

        def pct(q: float) -> float | None:
            return lat[min(len(lat) - 1, round(q * (len(lat) - 1)))] if lat else None

        return {
            "status": self.status, "message": self.message, "strokes": self.strokes,
            "iterations": self.iterations, "reversals": self.reversals,
            "lambda_initial_mm": self.lambda_initial_mm,
            "force": {
                "mean": statistics.fmean(f) if f else None,
                "sd": statistics.pstdev(f) if len(f) > 1 else None,
                "min": min(f, default=None), "max": max(f, default=None),
            },
            "sigma_range_deg": (max(self.sigmas) - min(self.sigmas)) if self.sigmas else None,
            "loop_hz": self.iterations / self.rolling_s if self.rolling_s > 0 else None,
            "latency_ms": {"p50": pct(0.5), "p99": pct(0.99)},
            "frames_skipped": self.frames_skipped,
        }  # fmt: skip


class Runner:
    """One run on open links. ``on_sample``/``on_event`` receive everything worth recording."""

    def __init__(
        self,
        settings: Settings,
        joints: JointLink,
        tactile: TactileBus,
        *,
        params: RollingParams | None = None,
        on_sample: Callable[[Sample], None] | None = None,
        on_event: Callable[[float, int | None, str, dict[str, Any]], None] | None = None,
        on_frame: Callable[[float, TactileFrame], None] | None = None,
    ) -> None:
        self.settings, self.joints, self.tactile = settings, joints, tactile
        self.ctx = settings.model_context()
        self.params = params or settings.rolling
        self._pending: RollingParams | None = None
        self.phase = Phase.IDLE
        self.state = RollState()
        self.result = RunResult(status="running")
        self._on_sample, self._on_event, self._on_frame = on_sample, on_event, on_frame
        self._stop = asyncio.Event()
        self._t0 = 0.0
        self._task: asyncio.Task[RunResult] | None = None
        a = settings.axes
        self._axes = (a.phi2, a.phi3, a.phi4, a.phi5)
        self._m1, self._m2 = a.finger1_distal_matrix, a.finger2_distal_matrix
        self._last_seq: int | None = None
        self._estopping = False

    # --- control from outside ---------------------------------------------------------------

    def set_params(self, params: RollingParams) -> None:
        """Takes effect, whole, at the next iteration."""
        self._pending = params

    def request_stop(self) -> None:
        self._stop.set()

    async def emergency_stop(self) -> None:
        """SCHUNK's e-stop, ahead of anything queued on the joint line, from any phase.

        The run is marked e-stopped before its task is cancelled, so however the cancellation
        reaches it (mid-command, or as the link fails the queued commands), it ends e-stopped;
        the phase changes once the link has latched the stop, so no observer sees one without
        the other.
        """
        self._estopping = True
        self.result.status, self.result.message = "e-stopped", "emergency stop"
        self.result.strokes = self.state.strokes
        if self._task is not None and not self._task.done():
            self._task.cancel()
        try:
            await self.joints.emergency_stop()
        finally:
            self._set_phase(Phase.ESTOPPED)
            self._event("estop", {})

    # --- the run ----------------------------------------------------------------------------

    async def run(self) -> RunResult:
        self._task = asyncio.current_task()  # type: ignore[assignment]
        loop = asyncio.get_running_loop()
        self._t0 = loop.time()
        sub = self.tactile.subscribe({self._m1, self._m2}, self.settings.run.tactile_rate_hz)
        watch = self.tactile.subscribe(range(6), self.settings.run.watch_rate_hz)
        self.joints.start_polling()  # iterations take the newest angles, not a round trip
        try:
            self._set_phase(Phase.CONNECTING)
            self._event("start", {"params": self.params.model_dump()})
            await self._preshape(sub)
            if not self._stop.is_set():
                await self._grasp(sub)
            if not self._stop.is_set():
                await self._roll(sub)
            status = "stopped" if self._stop.is_set() else "completed"
            await self._release()
            self._finish(Phase.STOPPED if status == "stopped" else Phase.DONE, status)
        except RunFault as e:
            await self._halt()
            status = "dropped" if e.fault is Fault.DROPPED else "faulted"
            if e.fault is Fault.FORCE_CEILING:
                with contextlib.suppress(Exception):
                    await self._release()
            self._event("fault", {"fault": e.fault.value, "message": str(e)})
            self._finish(Phase.FAULTED, status, f"{e.fault.value}: {e}")
        except (JointLinkError, TactileError) as e:
            await self._halt()
            fault = Fault.JOINT_ERROR if isinstance(e, JointLinkError) else Fault.SENSOR_ERROR
            self._event("fault", {"fault": fault.value, "message": str(e)})
            self._finish(Phase.FAULTED, "faulted", f"{fault.value}: {e}")
        except asyncio.CancelledError:
            if not self._estopping:
                raise
        finally:
            self.joints.stop_polling()
            sub.close()
            watch.close()
        return self.result

    def _finish(self, phase: Phase, status: str, message: str = "") -> None:
        if self._estopping:  # nothing after an e-stop changes how the run ended
            return
        self.result.status, self.result.message = status, message
        self.result.strokes = self.state.strokes
        self._set_phase(phase)
        self._event("end", {"status": status, "message": message})

    async def _halt(self) -> None:
        """Hold where the hand is: stop every axis, targets = actual angles."""
        with contextlib.suppress(Exception):
            await self.joints.hold()

    def _contacts(self, frame: TactileFrame) -> tuple[ContactEstimate, ContactEstimate]:
        """The two distal contacts (Finger 1's, Finger 2's) of a frame."""
        m = frame.matrices
        return self.ctx.contact(m[self._m1]), self.ctx.contact(m[self._m2])

    def _ceiling_fault(self, F: float) -> RunFault | None:
        s = self.settings.safety
        if F > s.force_ceiling_factor * self.params.grasp_force:
            return RunFault(Fault.FORCE_CEILING, f"F = {F:.2f} above "
                            f"{s.force_ceiling_factor:g} × Fd")  # fmt: skip
        return None

    def _watch_ceiling(self, sub: Subscription) -> Callable[[], None]:
        """A move's check: the newest fresh frame's F must stay under the ceiling."""

        def check() -> None:
            frame = sub.latest
            stale = self.settings.safety.stale_frame_ms / 1000
            if frame is not None and frame.age() <= stale:
                fault = self._ceiling_fault(grip_force(*self._contacts(frame)))
                if fault is not None:
                    raise fault

        return check

    async def _to_preshape(self, check: Callable[[], None] | None) -> None:
        lim = self.settings.limits
        await move_to_preshape(self.joints, self.settings.run, (lim.min_deg, lim.max_deg),
                               self.settings.safety, check)  # fmt: skip

    async def _preshape(self, sub: Subscription) -> None:
        self._set_phase(Phase.PRESHAPE)
        await self._to_preshape(self._watch_ceiling(sub))

    async def _grasp(self, sub: Subscription) -> None:
        """Close both coupled fingers in a mirror pose, force-proportionally, until F ≥ Fd.

        The thesis (and SCHUNK's demo) close with a velocity command; the firmware would keep
        that velocity if this loop died. So every frame commands a pose increment instead — the
        closing speed × one frame period, at most ``safety.max_step_deg`` — and a lost loop
        leaves the fingers at most one increment further.
        """
        self._set_phase(Phase.GRASPING)
        run, fd, lim = self.settings.run, self.params.grasp_force, self.settings.limits
        max_step = self.settings.safety.max_step_deg
        period = 1.0 / run.tactile_rate_hz
        loop = asyncio.get_running_loop()
        deadline = loop.time() + run.grasp_timeout_s
        await self.joints.set_controller(ControllerMode.POSE)
        await self.joints.set_velocities([run.grasp_max_velocity_deg_s] * 7)
        await self.joints.set_accelerations(self.joints.acceleration_limits)
        law = GraspLaw(grasp_force=fd, gain_deg_s=run.grasp_gain_deg_s,
                       max_velocity_deg_s=run.grasp_max_velocity_deg_s,
                       min_velocity_deg_s=run.grasp_min_velocity_deg_s,
                       align_gain=run.grasp_align_gain, period_s=period,
                       max_step_deg=max_step)  # fmt: skip
        p2, p4 = self._axes[0], self._axes[2]
        settle_until: float | None = None
        while not self._stop.is_set():
            frame = await self._fresh(sub)
            c1, c2 = self._contacts(frame)
            F = grip_force(c1, c2)
            if (fault := self._ceiling_fault(F)) is not None:
                raise fault
            actual, _ = self._newest_angles()
            pose = HandPose(*(math.radians(actual[i]) for i in self._axes))
            g = grasp_step(pose, c1, c2, law, self.ctx)
            if F >= fd:  # held; the pads may still turn against their wedge for a while
                settle_until = settle_until or loop.time() + run.grasp_settle_s
                wedge_ok = g.wedge_deg is None or abs(g.wedge_deg) <= self.params.alpha_deg / 2
                if wedge_ok or law.align_gain == 0 or loop.time() >= settle_until:
                    self._event("grasped", {"F": F, "wedge_deg": g.wedge_deg})
                    return
            elif loop.time() > deadline:
                raise RunFault(Fault.NO_CONTACT, f"no grasp (F = {F:.2f} < Fd = {fd}) "
                               f"within {run.grasp_timeout_s:g} s")  # fmt: skip
            if max(actual[p2], actual[p4]) > run.grasp_max_close_deg:
                raise RunFault(Fault.NO_CONTACT, "fingers closed without touching anything")
            want = list(actual)
            for axis, inc in zip(self._axes, g.d_phi, strict=True):
                want[axis] = actual[axis] + inc
            await self.joints.set_targets(clamp_targets(want, actual, lim.min_deg, lim.max_deg,
                                                        max_step))  # fmt: skip
            await self.joints.move()

    async def _fresh(self, sub: Subscription) -> TactileFrame:
        """The next frame, newer than any used before; a silent or stale stream is a fault."""
        stale = self.settings.safety.stale_frame_ms / 1000
        try:
            frame = await sub.next_frame(timeout=stale)
        except (FrameTimeout, TimeoutError):
            raise RunFault(
                Fault.STALE_SENSOR, f"no tactile frame for {stale * 1000:.0f} ms"
            ) from None
        if frame.age() > stale:
            raise RunFault(Fault.STALE_SENSOR, f"tactile frame {frame.age() * 1000:.0f} ms old")
        return frame

    async def _roll(self, sub: Subscription) -> None:
        self._set_phase(Phase.ROLLING)
        await self.joints.set_controller(ControllerMode.POSE)
        # One small move per frame, each replanning the last from its current velocity: with
        # the firmware's default 100 °/s² the fingers could not follow a step per frame period,
        # so use the axes' own acceleration limits.
        await self.joints.set_velocities([self.settings.run.preshape_velocity_deg_s] * 7)
        await self.joints.set_accelerations(self.joints.acceleration_limits)
        loop = asyncio.get_running_loop()
        t_start = loop.time()
        try:
            await self._roll_loop(sub)
        finally:
            self.result.rolling_s = loop.time() - t_start

    async def _roll_loop(self, sub: Subscription) -> None:
        loop = asyncio.get_running_loop()
        safety, limits = self.settings.safety, self.settings.limits
        while not self._stop.is_set() and self.state.strokes < self.params.cycles:
            if self._pending is not None:
                self.params, self._pending = self._pending, None
                self._event("params", {"params": self.params.model_dump()})
            frame = await self._fresh(sub)
            if self._last_seq is not None:
                self.result.frames_skipped += max(0, frame.seq - self._last_seq - 1)
            self._last_seq = frame.seq
            actual, joint_age_ms = self._newest_angles()
            age_ms = (loop.time() - frame.arrival) * 1000
            pose = HandPose(*(math.radians(actual[i]) for i in self._axes))
            m1, m2 = frame.matrices[self._m1], frame.matrices[self._m2]
            r = step(self.state, pose, m1, m2, self.params, self.ctx)
            fault = self._supervise(r)
            if fault is not None:  # record what tripped it, command nothing
                latency_ms = (loop.time() - frame.arrival) * 1000
                self._record(r, pose, frame, age_ms, joint_age_ms, latency_ms)
                raise fault
            if r.targets is not None:
                want = list(actual)
                for axis, angle in zip(self._axes, (r.targets.phi2, r.targets.phi3, r.targets.phi4,
                                                    r.targets.phi5), strict=True):  # fmt: skip
                    want[axis] = math.degrees(angle)
                cmd = clamp_targets(want, actual, limits.min_deg, limits.max_deg,
                                    safety.max_step_deg)  # fmt: skip
                sent = await self.joints.send_targets(cmd)
                latency_ms = (sent - frame.arrival) * 1000  # the targets are on the line
                # Start the move and go on at once: the next iteration runs on the next fresh
                # frame with the angles the fingers have then. A move still running is replanned
                # by the firmware from its current velocity, so the fingers move continuously.
                await self.joints.move()
            else:
                latency_ms = (loop.time() - frame.arrival) * 1000
            self.state = r.state
            self._record(r, pose, frame, age_ms, joint_age_ms, latency_ms)

    def _newest_angles(self) -> tuple[tuple[float, ...], float]:
        """The newest joint angles and their age in ms; stale ones are a fault, as a stale frame."""
        reading = self.joints.take_reading()
        age_s = math.inf if reading is None else reading.age()
        if reading is None or age_s > self.settings.safety.stale_joint_ms / 1000:
            raise RunFault(Fault.JOINT_ERROR, f"joint angles {age_s * 1000:.0f} ms old")
        return reading.angles, age_s * 1000

    def _supervise(self, r: StepResult) -> RunFault | None:
        s = self.settings.safety
        c1, c2 = r.obs.contact1, r.obs.contact2
        if (fault := self._ceiling_fault(r.F)) is not None:
            return fault
        if not c1.present and not c2.present:
            return RunFault(Fault.DROPPED, "both contacts lost: the object is no longer held")
        if r.state.consecutive_reversals > s.max_consecutive_reversals:
            return RunFault(Fault.STUCK, f"{r.state.consecutive_reversals} reversals in a row "
                            f"(last: {r.reversal})")  # fmt: skip
        return None

    def _record(
        self,
        r: StepResult,
        pose: HandPose,
        frame: TactileFrame,
        age_ms: float,
        joint_age_ms: float,
        latency_ms: float,
    ) -> None:
        t = frame.arrival - self._t0
        res = self.result
        res.iterations += 1
        if res.lambda_initial_mm is None and r.obs.Lambda is not None:
            res.lambda_initial_mm = r.obs.Lambda
        res.forces.append(r.F)
        if r.obs.sigma is not None:
            res.sigmas.append(math.degrees(r.obs.sigma))
        res.latencies_ms.append(latency_ms)
        if r.reversal is not None:
            res.reversals.append({"iteration": r.state.iteration, "reason": r.reversal.value})
            self._event("reversal", {"reason": r.reversal.value, "stroke": r.state.strokes,
                                     "half_strokes": r.state.half_strokes},
                        r.state.iteration)  # fmt: skip
        sample = Sample.from_step(r, pose, t, age_ms, joint_age_ms, latency_ms)
        if self._on_sample:
            self._on_sample(sample)
        if self._on_frame:
            self._on_frame(t, frame)

    async def _release(self) -> None:
        """Open to the pre-shape pose; no force check: opening is the remedy for a high F."""
        self._set_phase(Phase.RELEASING)
        await self._to_preshape(None)

    def _set_phase(self, phase: Phase) -> None:
        if phase is not self.phase:
            self.phase = phase
            self._event("phase", {"phase": phase.value})

    def _event(self, kind: str, detail: dict[str, Any], iteration: int | None = None) -> None:
        if self._on_event:
            t = asyncio.get_running_loop().time() - self._t0
            self._on_event(t, iteration if iteration is not None else self.state.iteration, kind,
                           detail)  # fmt: skip
