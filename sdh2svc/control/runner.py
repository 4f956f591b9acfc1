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
import logging
import math
import statistics
from array import array
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

from sdh2svc.bus.joint import ControllerMode, JointLink, JointLinkError
from sdh2svc.bus.tactile import FrameTimeout, Subscription, TactileBus, TactileError, TactileFrame
from sdh2svc.control import safety
from sdh2svc.control.config import ControlConfig
from sdh2svc.control.grasp import GraspLaw, GraspWatch, Held, grasp_step
from sdh2svc.control.motion import move_to_preshape
from sdh2svc.control.observer import Event, EventKind, RunObserver
from sdh2svc.control.params import RollingParams
from sdh2svc.control.plan import grip_force
from sdh2svc.control.recognition import Recognition, Recognizer
from sdh2svc.control.rolling import RollState, StepResult, step
from sdh2svc.control.safety import Fault, clamp_targets
from sdh2svc.control.sample import Sample
from sdh2svc.model.contact import ContactEstimate
from sdh2svc.model.kinematics import Finger, HandPose
from sdh2svc.model.observe import ModelContext, Observation
from sdh2svc.protocol.sdh import NUM_AXES

log = logging.getLogger(__name__)

#: Makes a run's recognizer (the tests' doubles; by default :class:`Recognizer`).
RecognizerFactory = Callable[[ModelContext], Recognizer]


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
    """The supervisor stopped the run (:mod:`sdh2svc.control.safety`)."""

    def __init__(self, fault: Fault, message: str) -> None:
        super().__init__(message)
        self.fault = fault


def _raise(violation: safety.Violation | None) -> None:
    if violation is not None:
        raise RunFault(violation.fault, violation.message)


@dataclass
class RunResult:
    """What a run did; ``status`` is completed | stopped | faulted | dropped | e-stopped."""

    status: str
    message: str = ""
    strokes: int = 0
    iterations: int = 0
    # reversals by reason; each one's iteration is its event's and its sample's (a list here
    # made a 3 639-stroke run's summary 335 kB, in every row of the runs' list)
    reversals: Counter[str] = field(default_factory=Counter)
    lambda_initial_mm: float | None = None
    # one value an iteration, as C doubles (a Python float in a list costs 32 bytes: 3 of them
    # grew a 10 000-stroke run by ≈ 0.4 GB); the summary's statistics read them at the end
    forces: array[float] = field(default_factory=lambda: array("d"))
    sigmas: array[float] = field(default_factory=lambda: array("d"))
    latencies_ms: array[float] = field(default_factory=lambda: array("d"))
    rolling_s: float = 0.0
    frames_skipped: int = 0  # fresh frames no rolling iteration ran on
    recognition: dict[str, Any] | None = None  # Recognizer.summary(); None: no estimate

    def summary(self) -> dict[str, Any]:
        f, lat = self.forces, sorted(self.latencies_ms)

        def pct(q: float) -> float | None:
            return lat[min(len(lat) - 1, round(q * (len(lat) - 1)))] if lat else None

        return {
            "status": self.status, "message": self.message, "strokes": self.strokes,
            "iterations": self.iterations, "reversals": dict(sorted(self.reversals.items())),
            "lambda_initial_mm": self.lambda_initial_mm,
            "force": {
                "mean": statistics.fmean(f) if f else None,
                "sd": statistics.pstdev(f) if len(f) > 1 else None,
                "min": min(f, default=None), "max": max(f, default=None),
            },
            "sigma_range_deg": (max(self.sigmas) - min(self.sigmas)) if self.sigmas else None,
            "loop_hz": self.iterations / self.rolling_s if self.rolling_s > 0 else None,
            "latency_ms": {"p50": pct(0.5), "p99": pct(0.99)},
            "frames_skipped": self.frames_skipped, "recognition": self.recognition,
        }  # fmt: skip


class Runner:
    """One run on open links; its ``observer`` receives everything worth recording."""

    def __init__(
        self,
        config: ControlConfig,
        joints: JointLink,
        tactile: TactileBus,
        *,
        params: RollingParams | None = None,
        observer: RunObserver | None = None,
        recognizer: RecognizerFactory = Recognizer,
    ) -> None:
        self.config, self.joints, self.tactile = config, joints, tactile
        self.ctx = config.ctx
        self.params = params or config.rolling
        self._pending: RollingParams | None = None
        self.phase = Phase.IDLE
        self.state = RollState()
        self.result = RunResult(status="running")
        self.observer = observer
        self._stop = asyncio.Event()
        self._stop_reason = ""  # the first stop's: the stopped run's message
        self._t0 = 0.0
        self._task: asyncio.Task[RunResult] | None = None
        self._axes = config.axes  # wire ↔ model (AxisMap.pose, .wire_targets, .wire_steps)
        self._m1, self._m2 = self._axes.finger1_distal_matrix, self._axes.finger2_distal_matrix
        self._last_seq: int | None = None
        self._estopping = False
        self._estopped = asyncio.Event()  # the e-stop has latched and been reported
        # run() has returned: the run's end is its own (an e-stop then stops the hand alone;
        # the task that ran it may still be recording that end, and must not be cancelled)
        self._returned = False
        self._make_recognizer = recognizer
        # the run's recognition; None once it failed (the rolling goes on without an estimate)
        self._recognizer: Recognizer | None = None
        # the summary of a recognition that failed: the one made before, with where and why
        self._recognition_failed: dict[str, Any] | None = None

    # --- control from outside ---------------------------------------------------------------

    def set_params(self, params: RollingParams) -> None:
        """Takes effect, whole, at the next frame of the grasp or iteration of the rolling."""
        self._pending = params

    def _adopt_pending(self) -> bool:
        """The parameters :meth:`set_params` gave, in force from here (and said so); False if
        none came."""
        if self._pending is None:
            return False
        self.params, self._pending = self._pending, None
        self._event(EventKind.PARAMS, {"params": self.params.model_dump()})
        return True

    def request_stop(self, reason: str = "") -> None:
        """Stop the run: it releases the object and ends ``stopped`` with ``reason`` (who
        stopped it, in the caller's words) as its message; a later stop keeps the first's."""
        if not self._stop.is_set():
            self._stop_reason = reason
        self._stop.set()

    def begin_emergency_stop(self) -> bool:
        """The e-stop's first half, synchronous with the joint link's latch: from here on the run
        ends e-stopped, whatever it meets before its task is cancelled — a command the latch
        refuses, a fault (the service latches the link at once and stops the run a loop
        iteration later, when the run's next command may already have been refused). Its phase
        says so from here on too: on a silent joint line the power-off waits through the
        attempt in flight, seconds in which the status said ``rolling`` beside the link's latch.
        False if the run had ended on its own: it keeps that end."""
        if self._returned and not self._estopping:
            return False
        if not self._estopping:
            self._estopping = True
            after = self.result.message  # a fault the run was already answering (a force ceiling)
            self.result.status = "e-stopped"
            self.result.message = f"emergency stop (after {after})" if after else "emergency stop"
            self.result.strokes = self.state.strokes
            self._set_phase(Phase.ESTOPPED)
        return True

    async def emergency_stop(self) -> None:
        """SCHUNK's e-stop, ahead of anything queued on the joint line, from any phase (a run
        that had already ended keeps its end, and says nothing of the hand's e-stop).

        The run is marked e-stopped (:meth:`begin_emergency_stop`) first, so however the stop
        reaches its task (a command refused by the latch, or the cancellation), it ends
        e-stopped. The link stops the hand before the task is cancelled: the command in flight
        finishes, and the power-off follows it at once. Cancelled first, the task abandoned
        that command mid-reply, and the power-off waited for the line to resynchronise (≈ 90
        instead of ≈ 5 ms). The phase changed as the link latched (:meth:`begin_emergency_stop`),
        so no observer sees one without the other; the e-stop's events follow once the hand has
        been told.
        """
        if not self.begin_emergency_stop():  # the run has ended as it ended: the hand alone
            await self.joints.emergency_stop()
            return
        try:
            await self.joints.emergency_stop()
        finally:
            task = self._task
            if not self._returned and task is not None and not task.done():
                task.cancel()  # (once run() has returned, the task is its recording's: left alone)
            if not self._estopped.is_set():  # said once, however many e-stops came
                self._event(EventKind.ESTOP, {})
                rec = self.result.recognition  # the run ends here: _finish said nothing
                end = {"status": "e-stopped", "message": self.result.message, "recognition": rec}
                self._event(EventKind.END, end)
                self._estopped.set()

    async def estop_reported(self) -> None:
        """Once an e-stop's events are out (a recording waits for them before it closes: the
        run's task may end, refused by the latch, before the e-stop has said so)."""
        if self._estopping:
            await self._estopped.wait()

    # --- the run ----------------------------------------------------------------------------

    async def run(self) -> RunResult:
        self._task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        self._t0 = loop.time()
        sub = self.tactile.subscribe({self._m1, self._m2}, self.config.run.tactile_rate_hz)
        self.joints.start_polling()  # iterations take the newest angles, not a round trip
        self._recognizer = self._new_recognizer()
        self._recognition_failed = None
        try:
            self._set_phase(Phase.CONNECTING)
            self._event(EventKind.START, {"params": self.params.model_dump()})
            await self._preshape(sub)
            if not self._stop.is_set():
                await self._grasp(sub)
            if not self._stop.is_set():
                await self._roll(sub)
            status = "stopped" if self._stop.is_set() else "completed"
            await self._release()
            stopped = status == "stopped"
            self._finish(Phase.STOPPED if stopped else Phase.DONE, status,
                         self._stop_reason if stopped else "")  # fmt: skip
        except RunFault as e:
            self._say_fault(e.fault, str(e))
            await self._halt()
            if e.fault is Fault.FORCE_CEILING:
                with contextlib.suppress(Exception):
                    await self._release()
            status = "dropped" if e.fault is Fault.DROPPED else "faulted"
            self._finish(Phase.FAULTED, status, f"{e.fault.value}: {e}")
        except (JointLinkError, safety.OutsideLimits, TactileError) as e:
            fault = Fault.SENSOR_ERROR if isinstance(e, TactileError) else Fault.JOINT_ERROR
            self._say_fault(fault, str(e))
            await self._halt()
            self._finish(Phase.FAULTED, "faulted", f"{fault.value}: {e}")
        except Exception as e:  # a bug: the hand held and the run ended as any fault ends it
            log.exception("the run failed unexpectedly")
            message = f"{type(e).__name__}: {e}"
            self._say_fault(Fault.INTERNAL, message)
            await self._halt()
            self._finish(Phase.FAULTED, "faulted", f"{Fault.INTERNAL.value}: {message}")
        except asyncio.CancelledError:
            if not self._estopping:
                raise
        finally:
            self.joints.stop_polling()
            sub.close()
            self._returned = True
        return self.result

    def _finish(self, phase: Phase, status: str, message: str = "") -> None:
        if self._estopping:  # nothing after an e-stop changes how the run ended
            return
        self.result.status, self.result.message = status, message
        self.result.strokes = self.state.strokes
        self._set_phase(phase)
        rec = self.result.recognition
        self._event(EventKind.END, {"status": status, "message": message, "recognition": rec})

    def _say_fault(self, fault: Fault, message: str) -> None:
        """The fault in the status and the record at once, before the halt and any opening: on
        a silent joint line the halt takes a reply's timeout per command (seconds, the run
        showing its phase meanwhile), and an e-stop during the halt or opening keeps why. After
        an e-stop nothing is a fault of the run (its latch refuses commands)."""
        if self._estopping:
            return
        self._event(EventKind.FAULT, {"fault": fault.value, "message": message})
        self.result.message = f"{fault.value}: {message}"

    async def _halt(self) -> None:
        """Hold where the hand is: stop every axis, targets = actual angles."""
        with contextlib.suppress(Exception):
            await self.joints.hold()

    def _contacts(self, frame: TactileFrame) -> tuple[ContactEstimate, ContactEstimate]:
        """The two distal contacts (Finger 1's, Finger 2's) of a frame."""
        m = frame.matrices
        return self.ctx.contact(m[self._m1]), self.ctx.contact(m[self._m2])

    def _watch_ceiling(self, sub: Subscription) -> Callable[[], None]:
        """A move's check: the newest frame is fresh and its F under the ceiling. A stale or
        silent stream is a fault as in the grasp: the move would go on with the ceiling unseen
        (the first frame has :func:`safety.stale_s` from the move's start to come)."""
        loop = asyncio.get_running_loop()
        started = loop.time()

        def check() -> None:
            frame, s = sub.latest, self.config.safety
            if frame is None:
                if loop.time() - started > safety.stale_s(s):
                    _raise(safety.frame_age(None, s))
                return
            _raise(safety.frame_age(frame.age(), s))
            c1, c2 = self._contacts(frame)
            _raise(safety.force_ceiling(c1.force, c2.force, self.params.grasp_force, s))

        return check

    async def _to_preshape(self, check: Callable[[], None] | None) -> None:
        lim = self.config.limits
        limits = (lim.min_deg, lim.max_deg)
        await move_to_preshape(self.joints, self.config.run, limits, self.config.safety, check)

    def _clamp(self, want: Sequence[float], actual: Sequence[float]) -> tuple[float, ...]:
        """The supervisor's bound on a command: within the joint limits, ≤ max_step_deg away."""
        lim, max_step = self.config.limits, self.config.safety.max_step_deg
        return clamp_targets(want, actual, lim.min_deg, lim.max_deg, max_step)

    async def _preshape(self, sub: Subscription) -> None:
        self._set_phase(Phase.PRESHAPE)
        await self._to_preshape(self._watch_ceiling(sub))

    async def _grasp(self, sub: Subscription) -> None:
        """Close both coupled fingers in a mirror pose, force-proportionally, until F ≥ Fd.

        The thesis (and SCHUNK's demo) close with a velocity command; the firmware would keep
        that velocity if this loop died. So every frame commands a pose increment instead, and
        a lost loop leaves the fingers at most ``safety.max_step_deg`` from their angles.

        A finger whose pad reads nothing steps from its previous target, by the approach speed
        × the time since the last frame: its newest angles are a reading old, and the servo
        (replanning each frame) followed only part of a step taken from them, so the fingers
        closed at ≈ 0.63 × the speed commanded, and slower lines or a loop held up (a busy
        computer) slowed them below half, until the grasp timed out untouched. Once its pad
        reads a contact a finger steps from its newest angles again, one frame period of the
        force law: the force then sets how far the target leads, not the servo's lag.
        """
        self._set_phase(Phase.GRASPING)
        run, fd = self.config.run, self.params.grasp_force
        period = 1.0 / run.tactile_rate_hz
        loop = asyncio.get_running_loop()
        started = loop.time()
        await self.joints.set_controller(ControllerMode.POSE)
        await self.joints.set_velocities([run.grasp_max_velocity_deg_s] * NUM_AXES)
        await self.joints.set_accelerations(self.joints.acceleration_limits)
        law = GraspLaw(
            grasp_force=fd,
            gain_deg_s=run.grasp_gain_deg_s,
            max_velocity_deg_s=run.grasp_max_velocity_deg_s,
            min_velocity_deg_s=run.grasp_min_velocity_deg_s,
            approach_velocity_deg_s=run.grasp_approach_velocity_deg_s,
            align_gain=run.grasp_align_gain,
            period_s=period,
            max_step_deg=self.config.safety.max_step_deg,
        )
        watch = GraspWatch(
            run=run, axes=self._axes, geom=self.ctx.geom,
            contact_force_min=self.params.contact_force_min, alpha_deg=self.params.alpha_deg,
            align=law.align_gain != 0, approach_deg_s=law.approach_velocity_deg_s,
            started=started,
        )  # fmt: skip
        aim: tuple[float, ...] | None = None  # the targets commanded last
        last: float | None = None  # when the previous frame was taken
        while not self._stop.is_set():
            if self._adopt_pending():  # a new Fd: the grasp closes towards it from this frame
                fd = self.params.grasp_force
                law = replace(law, grasp_force=fd)
            frame = await self._fresh(sub)
            c1, c2 = self._contacts(frame)
            _raise(safety.force_ceiling(c1.force, c2.force, fd, self.config.safety))
            actual, _ = self._newest_angles()
            pose = self._axes.pose(actual)
            now = loop.time()
            g = grasp_step(pose, c1, c2, law, self.ctx, None if last is None else now - last)
            last = now
            verdict = watch.observe(now, c1, c2, fd, actual, pose, g.wedge_deg)
            if isinstance(verdict, Held):
                self._event(EventKind.GRASPED, {"F": grip_force(c1, c2), "wedge_deg": g.wedge_deg})
                return
            _raise(verdict)
            base = self._step_base(actual, aim, (c1.present, c2.present))
            aim = self._clamp(self._axes.wire_steps(g.d_phi, base), actual)
            await self.joints.set_targets(aim)
            await self.joints.move()

    def _step_base(self, actual: tuple[float, ...], aim: tuple[float, ...] | None,
                   present: tuple[bool, bool]) -> list[float]:  # fmt: skip
        """Where a grasp frame's increments start: a finger's previous targets while its pad
        reads nothing (the ``_clamp`` bounds their lead over the angles), else its angles."""
        base = list(actual)
        if aim is not None:
            for finger, touching in zip((Finger.ONE, Finger.TWO), present, strict=True):
                if not touching:
                    for axis in self._axes.finger_axes(finger):
                        base[axis] = aim[axis]
        return base

    async def _fresh(self, sub: Subscription) -> TactileFrame:
        """The next frame, newer than any used before; a silent or stale stream is a fault."""
        s = self.config.safety
        frame: TactileFrame | None
        try:
            frame = await sub.next_frame(timeout=safety.stale_s(s))
        except (FrameTimeout, TimeoutError):
            frame = None
        _raise(safety.frame_age(None if frame is None else frame.age(), s))
        assert frame is not None  # no frame is always a violation
        return frame

    async def _roll(self, sub: Subscription) -> None:
        self._set_phase(Phase.ROLLING)
        await self.joints.set_controller(ControllerMode.POSE)
        # One small move per frame, each replanning the last from its current velocity: with
        # the firmware's default 100 °/s² the fingers could not follow a step per frame period,
        # so use the axes' own acceleration limits.
        await self.joints.set_velocities([self.config.run.preshape_velocity_deg_s] * NUM_AXES)
        await self.joints.set_accelerations(self.joints.acceleration_limits)
        loop = asyncio.get_running_loop()
        t_start = loop.time()
        try:
            await self._roll_loop(sub)
        finally:
            self.result.rolling_s = loop.time() - t_start
            self.result.recognition = self._recognition_summary()

    async def _roll_loop(self, sub: Subscription) -> None:
        loop = asyncio.get_running_loop()
        while not self._stop.is_set() and self.state.strokes < self.params.cycles:
            self._adopt_pending()
            frame = await self._fresh(sub)
            if self._last_seq is not None:
                self.result.frames_skipped += max(0, frame.seq - self._last_seq - 1)
            self._last_seq = frame.seq
            actual, joint_age_ms = self._newest_angles()
            age_ms = (loop.time() - frame.arrival) * 1000
            pose = self._axes.pose(actual)
            m1, m2 = frame.matrices[self._m1], frame.matrices[self._m2]
            r = step(self.state, pose, m1, m2, self.params, self.ctx)
            v = safety.rolling_step(r, self.params.grasp_force, self.config.safety)
            if v is not None:  # record what tripped it, command nothing
                latency_ms = (loop.time() - frame.arrival) * 1000
                self._record(r, pose, frame, age_ms, joint_age_ms, latency_ms)
                self.state = r.state  # the fault is this iteration's, as its sample and events
                _raise(v)
            commanded = None
            if r.targets is not None:
                want = self._clamp(self._axes.wire_targets(r.targets, actual), actual)
                commanded = self._axes.pose(want)  # recorded as sent, within the step limit
                sent = await self.joints.send_targets(want)
                latency_ms = (sent - frame.arrival) * 1000  # the targets are on the line
                # Start the move and go on at once: the next iteration runs on the next fresh
                # frame with the angles the fingers have then. A move still running is replanned
                # by the firmware from its current velocity, so the fingers move continuously.
                await self.joints.move()
            else:
                latency_ms = (loop.time() - frame.arrival) * 1000
            self.state = r.state
            self._record(r, pose, frame, age_ms, joint_age_ms, latency_ms, commanded)

    def _new_recognizer(self) -> Recognizer | None:
        try:
            return self._make_recognizer(self.ctx)
        except Exception:
            log.exception("recognition could not start: the run goes on without an estimate")
            return None

    def _recognize(self, obs: Observation, frame: TactileFrame) -> Recognition | None:
        """This iteration's recognition; its failure must never stop the rolling: logged, told
        as an event, and the run goes on without an estimate (its summary keeps the one made
        before, with the failure)."""
        if self._recognizer is None:
            return None
        m = frame.matrices
        try:
            return self._recognizer.update(obs, m[self._m1], m[self._m2])
        except Exception as exc:
            log.exception("recognition failed: the run goes on without an estimate")
            why = f"{type(exc).__name__}: {exc}"
            failed = {"iteration": self.result.iterations, "message": why}
            self._recognition_failed = {**(self._recognition_summary() or {}), "failed": failed}
            self._recognizer = None
            self._event(EventKind.RECOGNITION_FAILED, {"message": why})
            return None

    def _recognition_summary(self) -> dict[str, Any] | None:
        """The recognition's summary; after a failure, the one it made before, and ``failed``."""
        if self._recognizer is None:
            return self._recognition_failed
        try:
            return self._recognizer.summary()
        except Exception:
            log.exception("recognition's summary failed: the run's summary has none")
            return None

    def _newest_angles(self) -> tuple[tuple[float, ...], float]:
        """The newest joint angles and their age in ms; stale ones are a fault, as a stale frame."""
        reading = self.joints.take_reading()
        age_s = None if reading is None else reading.age()
        _raise(safety.joint_age(age_s, self.config.safety))
        assert reading is not None and age_s is not None
        return reading.angles, age_s * 1000

    def _record(
        self,
        r: StepResult,
        pose: HandPose,
        frame: TactileFrame,
        age_ms: float,
        joint_age_ms: float,
        latency_ms: float,
        commanded: HandPose | None = None,
    ) -> None:
        t = frame.arrival - self._t0
        res = self.result
        res.iterations += 1
        rec = self._recognize(r.obs, frame)
        if res.lambda_initial_mm is None and r.obs.Lambda is not None:
            res.lambda_initial_mm = r.obs.Lambda
        res.forces.append(r.F)
        if r.obs.sigma is not None:
            res.sigmas.append(math.degrees(r.obs.sigma))
        res.latencies_ms.append(latency_ms)
        if r.reversal is not None:
            res.reversals[r.reversal.value] += 1
            st, why = r.state, r.reversal.value
            detail = {"reason": why, "stroke": st.strokes, "half_strokes": st.half_strokes}
            self._event(EventKind.REVERSAL, detail, st.iteration)
        if self.observer is not None:
            sample = Sample.from_step(r, pose, t, age_ms, joint_age_ms, latency_ms, rec,
                                      commanded)  # fmt: skip
            self.observer.sample(sample)
            self.observer.frame(t, sample.iteration, frame)

    async def _release(self) -> None:
        """Open to the pre-shape pose; no force check: opening is the remedy for a high F."""
        self._set_phase(Phase.RELEASING)
        await self._to_preshape(None)

    def _set_phase(self, phase: Phase) -> None:
        if self._estopping and phase is not Phase.ESTOPPED:  # the e-stop ended the run: what
            return  # its task meets until it is cancelled (a refused command, a fault) says nothing
        if phase is not self.phase:
            self.phase = phase
            self._event(EventKind.PHASE, {"phase": phase.value})

    def _event(self, kind: EventKind, detail: dict[str, Any], iteration: int | None = None) -> None:
        if self.observer is not None:
            t = asyncio.get_running_loop().time() - self._t0
            i = iteration if iteration is not None else self.state.iteration
            self.observer.event(Event(t, i, kind, detail))
