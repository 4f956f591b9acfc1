"""SDH2 joint-controller firmware emulator, as a sans-I/O device.

:class:`Sdh2Emulator` implements :class:`~sdh2svc.sim.endpoint.Device`: an endpoint hands it the
host's bytes and asks for whole replies whenever the line is idle, always with the endpoint's
``now`` (seconds). It keeps no clock and starts no task, so the same ``now`` values give the same
bytes and the same calls into the world. Every byte goes through :mod:`sdh2svc.protocol.sdh`
(ASCII lines and binary frames on one line, detected per message; binary frames with or without
CRC, answered in the same form). Where the joints really are comes from a
:class:`~sdh2svc.sim.world.HandWorld` (protocols.md PART 2, PART 3, PART 4).

Servo model. Each axis has a *reference* angle that the firmware's controller computes and the
world's servo follows; ``pos`` reports what :meth:`HandWorld.move_joints` returns, ``vel`` its
finite difference. The reference advances on a fixed tick (``tick_s``, 5 ms, anchored at the
command that started the motion) while anything moves, plus once at every command's ``now`` and
exactly at the end of a coordinated move; :meth:`Sdh2Emulator.next_wakeup` asks for the next tick.

* Pose controller (``con=0``): ``m`` plans one normalised profile from the *actual* angles to the
  targets and every axis follows ``start + (goal − start)·s(t)``, so all axes start and arrive
  together on a straight line in joint space. The ramp time and duration are the smallest for
  which no axis exceeds its target velocity ``v`` or acceleration ``a`` (:class:`Profile`).
  ``vp=0`` shapes the ramps as sin² (velocity ∝ sin², peak acceleration π/2 × the mean), ``vp=1``
  as linear ramps (a trapezoid). ``M=`` and ``GET_DURATION=`` carry that duration.
  An ``m`` that arrives while a move still runs replans from where the references are, at the
  velocity they have ([U] in protocols.md; what a motion controller's ramp generator does, and
  what a host streaming one target per sensor frame needs): each axis's reference velocity ramps
  down to 0 within its acceleration (:class:`Carry`, the mirrored ramp shape, over at least the
  profile's ramp time, so that the two blend) while a coordinated
  profile, planned as above, covers the rest of the way to the new targets; the two superpose, so
  the reference velocity is continuous and every axis arrives at the end of the longer of the two.
  Where the carry would overshoot the new target (a reversal), carry and profile get half the
  axis's acceleration each. A new move from rest still starts from the actual angles.
* Velocity controllers: ``con=1`` takes each target velocity at once, ``con=2`` ramps the
  reference velocity towards it at ``a``. A reference that reaches ``p_min``/``p_max`` stops there
  (state 7, LIMITS_REACHED, while the target velocity pushes outwards).
* Blocked axis: when a moving axis's actual angle lags its reference by more than
  ``blocked_margin_deg``, the axis is blocked (state 4/5 by the direction it pushes) and its
  reference stops there, so the servo keeps pressing as hard as that lag makes it — a finger on a
  stiff object. In the pose controller the block lasts until the next ``m``/``selgrip``/``grip``,
  ``con`` or ``power`` change of that axis; in the velocity controllers also until a target
  velocity points away from the obstacle or the joint catches up to half the margin (the
  obstacle gave way).
* Power: an unpowered axis is limp (the world decides where it goes; its reference follows it).
  ``m``, ``selgrip`` and ``grip`` enable all axes, and a non-zero target velocity named by
  ``v``/``tvav`` in ``con=1|2`` enables that axis — SDHLibrary never sends ``power=1`` (PART 4
  item 5). Enabling an axis makes it hold where it is.

State (``state``): 4/5 blocked, else 6 unpowered, else in pose mode 1 while the axis takes part in
a running move (zero-distance axes read 0), in velocity modes 7 at a limit, 2 while the target or
reference velocity is non-zero (SDHLibrary's ``WaitAxis`` waits for 2 to clear), else 0. The state
is updated when the command is processed, so ``STATE`` reads 1 before the ``M=`` reply has even
left (PART 4 item 6). Device state, motion included, survives host disconnects; only the partial
input line and unsent replies are dropped.

Firmware behaviour the sources do not settle ([U] in protocols.md), our choice, and the
:class:`Sdh2Options` field that controls it:

* Identification strings: ``version`` ``0.0.3.3`` (SDHLibrary 0.0.2.10's recommended firmware,
  §2.1), ``version_date``, ``hand_id``, ``serial_number``, ``soc_version``, ``soc_date``.
* Number format of replies (§2.3): ``reply_fmt`` (``{:.3f}``); flags and states print as ints.
  Durations are rounded up to the millisecond, so a host that sleeps T finds the move done.
* Angle limits: ``min_angle_deg``/``max_angle_deg`` (axis 0: 0…90°, others ±90°, §2.2), the
  factory range; ``p_min=``/``p_max=`` may narrow it (values outside the factory range, or
  min > max, are refused) and targets are clipped into the new range. ``p_offset`` is stored and
  echoed only. Velocity limits ``velocity_limit`` (83, 140, 200, 140, 200, 140, 200 °/s, PY's
  fake ``VLIM``), acceleration limits ``acceleration_limit`` (5000, 400, 1500, … °/s², CPP's
  fallback), current limit ``max_current_a`` (1.0 A, the library's range).
* Refusals (open question 11): anything out of range — targets, velocities (pose mode 0…vlim,
  velocity modes ±vlim), accelerations (0…alim), currents, flags, ``con``/``vp``/``selgrip``
  values, ``grip`` arguments, non-finite binary values — answers ``range_error`` (E24
  RANGE_ERROR) and changes nothing; ``m``/``get_duration`` that would move an axis with zero
  ``v`` or ``a`` also answer it. ``m``/``selgrip``/``grip`` outside the pose controller answer
  ``wrong_mode_error`` (E17 CMD_FAILED). Values sent to read-only commands in binary answer
  NO_PARAMS_EXPECTED; binary codes other than the 11 of §2.6 answer CMD_UNKNOWN. Syntax errors
  use the codec's codes (E13 unknown, E14 format, E26 axis index, E11/E23 value count/type).
* Blank line (PART 4 item 4): silence; ``blank_line_error`` True answers E34 NO_COMMAND at once.
* ``stop`` reply text (open question 8): ``STOP=`` + ``stop_reply`` (empty). ``stop`` freezes the
  reference of an ``m`` move at once (no deceleration ramp) and, in velocity modes, sets every
  target and reference velocity to 0; it does not end ``selgrip``/``grip`` moves (§2.4).
* ``demo``/``user_errors``/``terminal``/``debug`` reply ``KEYWORD=<int>`` like every other
  command; any integer is stored.
* After ``con=0``: ``v`` = ``pose_velocity`` (40), ``a`` = ``pose_acceleration`` (100) and, with
  ``con_resets_targets`` (True, as CPP's ``SetController`` documents), targets 0° (clipped to the
  limits); after ``con=1|2``: ``v`` = 0, ``a`` kept. Any ``con=`` ends a running move; the
  references hold where they are. Power-on: controller ``initial_controller`` (0), axes powered
  if ``initially_powered`` (False), targets 0°, angles wherever the world has the joints.
* Blocked detection: ``blocked_margin_deg`` (1.0°); ``positive_is_cw`` (True) maps pushing
  towards positive angles to state 4 (CW), negative to 5 (CCW).
* Current limits ``ilim_a``/``igrip_a`` (1.0, 0.5, …; what old firmware printed while moving) and
  ``ihold_a`` (0.1, 0.2, …), ``kv``, ``pid``, ``temperatures_c`` (9 constant values): stored and
  echoed, no effect on motion.
* ``selgrip``/``grip`` (§2.4): ``grasps`` holds one open (close 0) and one closed (close 1) pose
  per grasp id; ``selgrip=<id>`` moves to the open pose at ``grasp_velocity`` (40 °/s, capped at
  vlim), ``grip=<close>,<velocity>`` to the interpolated pose at that velocity (0 <
  velocity ≤ ``grip_max_velocity``, 100 °/s). Both use the coordinated profile with the current
  ``vp`` and ``a``, leave the ``p`` targets alone and reply ``SELGRIP=<T>,<id>`` /
  ``GRIP=<T>,<close>``. Current-limit juggling is not modelled. ``pos_save=`` and ``ref=`` are
  checked (0/1, 0/1/2) and echoed at once; no reference move is made.
* Processing time (§2.7): a command is executed, and its reply built, ``ascii_latency_s`` or
  ``binary_latency_s`` after its last byte arrived (0 by default; the simulated hand takes them
  from ``config/sim.toml``, calibrated so that the vendor's benchmark loop runs at its published
  rate). The firmware takes one command at a time: one that arrives while another is processed
  waits its turn. A line, blank or not, is a command; line noise that frames nothing (garbage,
  answered by silence) takes no time: a burst of it would otherwise hold every later reply
  back by a command's time per stray byte. A command received before a host disconnect still
  takes effect; its reply is dropped.
* Its own clock: :meth:`Sdh2Emulator.attach_clock` hands the servo ticks to an outside clock
  (the simulated hand's, :mod:`sdh2svc.sim.lab`), so motion goes on while no host is connected;
  :meth:`~Sdh2Emulator.next_wakeup` then asks only for replies. A lazy outside clock
  (:meth:`~Sdh2Emulator.attach_lazy_clock`, fast mode) wakes for no tick: whoever reads the
  emulator or its world first calls :meth:`~Sdh2Emulator.observe`, which steps every tick and
  processes every command due by then at its own time — the same steps at the same times as a
  clock that wakes at each, without an event-loop wake-up per tick. Without one, an endpoint's
  wake-ups step the servo; a TCP endpoint stops asking while no host is connected and the servo
  catches up at the next call in at most ``max_catchup_steps`` (2000) evenly spaced steps.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final, TypeAlias

from sdh2svc.protocol.sdh import (
    BINARY_COMMANDS,
    COMMAND_SINCE,
    NUM_AXES,
    AsciiCommand,
    AxisState,
    BinaryRequest,
    BlankLine,
    ErrorSource,
    HostEvent,
    HostStreamParser,
    ProtocolErrorEvent,
    SdhError,
    encode_binary_reply,
    encode_error,
    encode_reply,
    firmware_release,
)
from sdh2svc.sim.world import HandWorld

__all__ = [
    "DEFAULT_GRASPS",
    "POSE",
    "PUBLISHED_LOOP_HZ",
    "VELOCITY",
    "VELOCITY_ACCELERATION",
    "Carry",
    "Grasp",
    "Profile",
    "Sdh2Emulator",
    "Sdh2Options",
    "Sdh2Stats",
]

Vec: TypeAlias = tuple[float, ...]

POSE, VELOCITY, VELOCITY_ACCELERATION = 0, 1, 2  # `con` values (§2.4)
_ALL: Final = tuple(range(NUM_AXES))
_EPS: Final = 1e-9  # deg: a shorter distance is no motion
_LIMIT_TOL: Final = 1e-6  # deg: float32 round-off of a value sent exactly at a limit
_PROPERTIES: Final = ("demo", "user_errors", "terminal", "debug")
#: SCHUNK's benchmark loop over RS-232 on a real SDH2, cycles per second (SDHLibrary-CPP release
#: notes 0.0.2.0, protocols.md §2.7): binary `pos` + `tvav`, ASCII `pos`, `v`, `vel`.
PUBLISHED_LOOP_HZ: Final = {"binary": 75.0, "ascii": 30.0}


@dataclass(frozen=True, slots=True)
class Grasp:
    """A ``selgrip`` grasp: the pose at close ratio 0 and at close ratio 1 (deg, 7 axes)."""

    open_deg: Vec
    closed_deg: Vec

    def __post_init__(self) -> None:
        if len(self.open_deg) != NUM_AXES or len(self.closed_deg) != NUM_AXES:
            raise ValueError(f"grasp poses need {NUM_AXES} angles")

    def pose(self, close: float) -> Vec:
        """The pose at close ratio ``close`` (0…1), linear in joint space."""
        pairs = zip(self.open_deg, self.closed_deg, strict=True)
        return tuple(o + close * (c - o) for o, c in pairs)


def _grasp(axis0: float, open_pd: tuple[float, float], closed_pd: tuple[float, float]) -> Grasp:
    return Grasp((axis0, *open_pd * 3), (axis0, *closed_pd * 3))


# Centrical, parallel, cylindrical, spherical (§2.4). Old firmware printed the grip vector
# 0, -66.8, 66.8, … for `grip=0.1` after `selgrip=1`, which these parallel poses reproduce.
DEFAULT_GRASPS: Final = (
    _grasp(60.0, (-75.0, 75.0), (7.0, -7.0)),
    _grasp(0.0, (-75.0, 75.0), (7.0, -7.0)),
    _grasp(0.0, (-60.0, 60.0), (30.0, 30.0)),
    _grasp(60.0, (-60.0, 60.0), (30.0, 30.0)),
)


def _release(version: str) -> tuple[int, ...]:
    """:func:`firmware_release`; a version string that is no release counts as the newest."""
    try:
        return firmware_release(version)
    except ValueError:
        return (1 << 30,)


def _seven(value: float) -> Vec:
    return (value,) * NUM_AXES


@dataclass(frozen=True, slots=True, kw_only=True)
class Sdh2Options:
    """Firmware choices where the sources are silent; see the module docstring for each."""

    version: str = "0.0.3.3"
    version_date: str = "2013-11-28"
    hand_id: str = "1"
    serial_number: str = "1"
    soc_version: str = "0.0.3.3"
    soc_date: str = "2013-11-28"
    reply_fmt: str = "{:.3f}"
    min_angle_deg: Vec = (0.0, -90.0, -90.0, -90.0, -90.0, -90.0, -90.0)
    max_angle_deg: Vec = (90.0,) * NUM_AXES
    velocity_limit: Vec = (83.0, 140.0, 200.0, 140.0, 200.0, 140.0, 200.0)
    acceleration_limit: Vec = (5000.0, 400.0, 1500.0, 400.0, 1500.0, 400.0, 1500.0)
    max_current_a: float = 1.0
    ilim_a: Vec = (1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5)
    igrip_a: Vec = (1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5)
    ihold_a: Vec = (0.1, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2)
    kv: Vec = (1.0,) * NUM_AXES
    pid: tuple[float, float, float] = (0.5, 0.0, 0.0)
    temperatures_c: tuple[float, ...] = (36.5, 37.0, 36.0, 37.0, 36.0, 37.0, 36.0, 45.0, 40.0)
    pose_velocity: float = 40.0
    pose_acceleration: float = 100.0
    con_resets_targets: bool = True
    initial_controller: int = POSE
    initially_powered: bool = False
    tick_s: float = 0.005
    blocked_margin_deg: float = 1.0
    positive_is_cw: bool = True
    stop_reply: str = ""
    blank_line_error: bool = False
    range_error: SdhError = SdhError.RANGE_ERROR
    wrong_mode_error: SdhError = SdhError.CMD_FAILED
    grasps: tuple[Grasp, ...] = DEFAULT_GRASPS
    grasp_velocity: float = 40.0
    grip_max_velocity: float = 100.0
    max_catchup_steps: int = 2000
    ascii_latency_s: float = 0.0
    binary_latency_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("min_angle_deg", "max_angle_deg", "velocity_limit", "acceleration_limit",
                     "ilim_a", "igrip_a", "ihold_a", "kv"):  # fmt: skip
            if len(getattr(self, name)) != NUM_AXES:
                raise ValueError(f"{name} needs {NUM_AXES} values")
        if len(self.temperatures_c) != 9:
            raise ValueError("temperatures_c needs 9 values (7 motors, FPGA, PCB)")
        if any(lo > hi for lo, hi in zip(self.min_angle_deg, self.max_angle_deg, strict=True)):
            raise ValueError("min_angle_deg must not exceed max_angle_deg")
        if min(self.velocity_limit) <= 0.0 or min(self.acceleration_limit) <= 0.0:
            raise ValueError("velocity and acceleration limits must be > 0")
        if not self.tick_s > 0.0:
            raise ValueError(f"tick_s must be > 0, got {self.tick_s!r}")
        if not self.blocked_margin_deg > 0.0:
            raise ValueError(f"blocked_margin_deg must be > 0, got {self.blocked_margin_deg!r}")
        if self.initial_controller not in (POSE, VELOCITY, VELOCITY_ACCELERATION):
            raise ValueError(f"initial_controller must be 0, 1 or 2, got {self.initial_controller}")
        if not self.grasps:
            raise ValueError("at least one grasp is needed")
        if self.max_catchup_steps < 1:
            raise ValueError("max_catchup_steps must be >= 1")
        if not min(self.ascii_latency_s, self.binary_latency_s) >= 0.0:
            raise ValueError("processing latencies must be >= 0")
        self.reply_fmt.format(1.0)  # fails early on a bad format


@dataclass(slots=True)
class Sdh2Stats:
    """Counters since construction."""

    commands: int = 0  # ASCII lines and binary frames that parsed
    binary: int = 0  # of which binary
    errors: int = 0  # replies that report an error (E<n> or a non-zero status)
    blank_lines: int = 0
    replies: int = 0  # packets handed out
    bytes: int = 0  # bytes of those packets


@dataclass(frozen=True, slots=True)
class Profile:
    """Normalised coordinated motion: a fraction going 0 → 1 over ``duration`` seconds.

    The unit velocity shape rises over ``ramp`` s (linear or sin²), stays at 1, and falls over the
    last ``ramp`` s; an axis covering ``d`` degrees moves at ``d / (duration − ramp)`` in between.
    """

    duration: float
    ramp: float
    sin2: bool

    @classmethod
    def plan(cls, distances: Sequence[float], velocities: Sequence[float],
             accelerations: Sequence[float], *, sin2: bool) -> Profile:  # fmt: skip
        """The fastest profile that keeps every axis within its velocity and acceleration.

        With cruise time ``c = duration − ramp``, axis i needs ``dᵢ/c ≤ vᵢ`` and a peak
        acceleration ``k·dᵢ/(c·ramp) ≤ aᵢ`` (k = 1 linear, π/2 sin²); ``duration = c + K/c`` with
        ``K = k·max(dᵢ/aᵢ)`` is smallest at ``c = max(√K, max dᵢ/vᵢ)``. Raises ValueError if an
        axis must move with zero velocity or acceleration.
        """
        # max dᵢ/aᵢ and max dᵢ/vᵢ over the moving axes, in one pass (as max() picks them)
        per_a: float | None = None
        per_v: float | None = None
        for d, v, a in zip(distances, velocities, accelerations, strict=True):
            d = abs(d)
            if d > _EPS:
                if v <= 0.0 or a <= 0.0:
                    raise ValueError("an axis must move with zero velocity or acceleration")
                if per_a is None or d / a > per_a:
                    per_a = d / a
                if per_v is None or d / v > per_v:
                    per_v = d / v
        if per_a is None or per_v is None:  # nothing moves
            return cls(0.0, 0.0, sin2)
        k = (math.pi / 2 if sin2 else 1.0) * per_a
        cruise = max(math.sqrt(k), per_v)
        ramp = k / cruise
        return cls(cruise + ramp, ramp, sin2)

    def fraction(self, t: float) -> float:
        """Share of the distance covered ``t`` s after the start."""
        return self.at(t)[0]

    def rate(self, t: float) -> float:
        """d fraction / dt at ``t`` (1/s)."""
        return self.at(t)[1]

    def at(self, t: float) -> tuple[float, float]:
        """:meth:`fraction` and :meth:`rate` at ``t`` in one go (asked at every servo tick)."""
        total, ramp = self.duration, self.ramp
        if t >= total:
            return 1.0, 0.0
        if t <= 0.0:
            return 0.0, 0.0
        cruise = total - ramp
        if t < ramp:
            area, speed = self._ramp(t)
        elif t <= cruise:
            area, speed = ramp / 2 + (t - ramp), 1.0
        else:
            area, speed = self._ramp(total - t)
            area = cruise - area
        return area / cruise, speed / cruise

    def _ramp(self, t: float) -> tuple[float, float]:
        """Distance and speed ``t`` s into a ramp up (the unit velocity shape)."""
        r = self.ramp
        if self.sin2:
            area = t / 2 - r / (2 * math.pi) * math.sin(math.pi * t / r)
            return area, math.sin(math.pi * t / (2 * r)) ** 2
        return t * t / (2 * r), t / r


@dataclass(frozen=True, slots=True)
class Carry:
    """An axis's velocity at a replan, ramped down to 0 at the axis's acceleration.

    The velocity falls from ``v0`` to 0 over ``time`` s with the move's ramp shape (linear, or
    cos² for ``vp=0``, i.e. the mirror of a sin² ramp); ``distance`` = v0·time/2 is how far the
    axis coasts meanwhile. ``accel`` is the deceleration allowed to this ramp (deg/s²).
    """

    v0: float
    time: float
    sin2: bool

    @classmethod
    def plan(cls, v0: float, accel: float, *, sin2: bool, at_least: float = 0.0) -> Carry:
        """Ramp down within ``accel``, and over no less than ``at_least`` s."""
        v0, time = _carry(v0, accel, sin2, at_least)
        if v0 == 0.0:
            return _STILL[sin2] if cls is Carry else cls(0.0, 0.0, sin2)
        return cls(v0, time, sin2)

    @property
    def distance(self) -> float:
        return self.v0 * self.time / 2

    def offset(self, t: float) -> float:
        """Distance coasted ``t`` s after the replan."""
        if self.time <= 0.0 or t <= 0.0:
            return 0.0
        if t >= self.time:
            return self.distance
        tau = self.time
        if self.sin2:
            return self.v0 * (t / 2 + tau / (2 * math.pi) * math.sin(math.pi * t / tau))
        return self.v0 * (t - t * t / (2 * tau))

    def velocity(self, t: float) -> float:
        if self.time <= 0.0 or t < 0.0 or t >= self.time:
            return 0.0
        if self.sin2:
            return self.v0 * math.cos(math.pi * t / (2 * self.time)) ** 2
        return self.v0 * (1.0 - t / self.time)


def _carry(v0: float, accel: float, sin2: bool, at_least: float) -> tuple[float, float]:
    """:meth:`Carry.plan`'s ``(v0, time)``, without building the Carry (planning tries several)."""
    if v0 == 0.0 or accel <= 0.0:
        return 0.0, 0.0
    return v0, max((math.pi / 2 if sin2 else 1.0) * abs(v0) / accel, at_least)


_NO_CARRY: Final = Carry(0.0, 0.0, False)
_STILL: Final = {False: _NO_CARRY, True: Carry(0.0, 0.0, True)}  # Carry.plan of v0 = 0


@dataclass(frozen=True, slots=True)
class _Move:
    start: Vec
    goal: Vec
    profile: Profile
    t0: float
    stoppable: bool  # `stop` ends `m` moves, not selgrip/grip (§2.4)
    carry: tuple[Carry, ...] = (_NO_CARRY,) * NUM_AXES  # per axis: a replan's inherited velocity
    # asked at every servo tick: computed once
    duration: float = field(init=False, repr=False, compare=False)
    end: float = field(init=False, repr=False, compare=False)  # t0 + duration
    # the axes without a carry: (axis, start + 0.0, span)
    plain: tuple[tuple[int, float, float], ...] = field(init=False, repr=False, compare=False)
    # the axes with one (carry time > 0), by carry shape
    coast: tuple[_Coast, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        duration = max(self.profile.duration, max(c.time for c in self.carry))
        object.__setattr__(self, "duration", duration)
        object.__setattr__(self, "end", self.t0 + duration)
        goal, start, carry = self.goal, self.start, self.carry
        plain: list[tuple[int, float, float]] = []
        coast: dict[tuple[float, bool], _Coast] = {}
        for i in _ALL:
            s, c = start[i], carry[i]
            distance = c.distance
            span = goal[i] - s - distance
            if c.time > 0.0:
                key = (c.time, c.sin2)
                if (group := coast.get(key)) is None:
                    coast[key] = group = _Coast(*key)
                group.axes.append((i, s, span, c))
                group.after.append((i, s + distance, span))
            else:  # the carry's offset is 0.0
                plain.append((i, s + 0.0, span))
        object.__setattr__(self, "plain", tuple(plain))
        object.__setattr__(self, "coast", tuple(coast.values()))

    def span(self, i: int) -> float:
        """What the coordinated profile covers on axis i (the rest is the carry's)."""
        return self.goal[i] - self.start[i] - self.carry[i].distance


class _Coast:
    """A move's axes whose carries ramp down alike (same time and shape): the carry's shape at a
    tick is computed once for all of them (:meth:`Carry.offset`, :meth:`Carry.velocity`)."""

    __slots__ = ("after", "axes", "k", "sin2", "time", "twice")

    def __init__(self, time: float, sin2: bool) -> None:
        self.time, self.sin2 = time, sin2
        self.k = time / (2 * math.pi)
        self.twice = 2 * time
        # filled as the move is built, never changed once it runs
        self.axes: list[tuple[int, float, float, Carry]] = []  # (axis, start, span, carry)
        self.after: list[tuple[int, float, float]] = []  # (axis, start + carry distance, span)

    def follow(self, tau: float, frac: float, rate: float, ax: _Axes) -> None:
        """References ``tau`` s into the move: the carry's offset and velocity plus the profile's
        ``frac`` and ``rate`` of the span (the same operations as Carry.offset/velocity)."""
        in_move, blocked, ref, rvel = ax.in_move, ax.blocked, ax.ref, ax.rvel
        ctime = self.time
        if tau >= ctime:  # coasted all the way: Carry.offset is its distance, the velocity 0.0
            for i, base, span in self.after:
                if in_move[i] and not blocked[i]:
                    ref[i] = base + span * frac
                    rvel[i] = 0.0 + span * rate
            return
        if not 0.0 < tau:  # not ramping yet (or not a number): per axis
            for i, start, span, c in self.axes:
                if in_move[i] and not blocked[i]:
                    ref[i] = start + c.offset(tau) + span * frac
                    rvel[i] = c.velocity(tau) + span * rate
            return
        if self.sin2:  # per unit v0
            pt = math.pi * tau
            offset = tau / 2 + self.k * math.sin(pt / ctime)
            velocity = math.cos(pt / self.twice) ** 2
        else:
            offset = tau - tau * tau / self.twice
            velocity = 1.0 - tau / ctime
        for i, start, span, c in self.axes:
            if in_move[i] and not blocked[i]:
                ref[i] = start + c.v0 * offset + span * frac
                rvel[i] = c.v0 * velocity + span * rate


class _Reject(Exception):
    """The firmware refuses a command with this error code (E<n> or binary status)."""

    def __init__(self, code: SdhError) -> None:
        super().__init__(code.name)
        self.code = code


Writer: TypeAlias = Callable[[Vec, Sequence[int]], None]


@dataclass(frozen=True, slots=True)
class _Vector:
    """A 7-vector command: what it reads, and for settable ones the vector a per-axis set
    completes and the writer (which validates everything before changing anything)."""

    read: Callable[[], Vec]
    base: Callable[[], Vec] | None = None
    write: Writer | None = None


@dataclass(slots=True)
class _Axes:
    """Per-axis controller state (lists of 7)."""

    target: list[float]
    velocity: list[float]  # target velocity `v`
    accel: list[float]
    ref: list[float]
    rvel: list[float]
    actual: list[float]
    actual_vel: list[float]
    powered: list[bool]
    blocked: list[int]  # 0, or the direction (+1/-1) the axis is pushing
    in_move: list[bool] = field(default_factory=lambda: [False] * NUM_AXES)


class Sdh2Emulator:
    """An SDH2 joint controller moving ``world``'s joints; implements the endpoint's ``Device``."""

    def __init__(self, world: HandWorld, *, options: Sdh2Options | None = None) -> None:
        self.options = o = options or Sdh2Options()
        self._release = _release(o.version)
        self.stats = Sdh2Stats()
        self._world = world
        self._parser = HostStreamParser()
        self._outbox: deque[bytes] = deque()
        # received commands being processed: (ready time, event, link generation), in order
        self._inbox: deque[tuple[float, HostEvent, int]] = deque()
        self._busy_until = -math.inf  # when the firmware finishes the last command it took
        self._generation = 0  # bumped at every (dis)connect: replies for a gone host are dropped
        self._wake: Callable[[], None] | None = None  # the outside clock, if any
        self._clock_now: Callable[[], float] | None = None  # a lazy outside clock's time
        self._t: float | None = None  # time the servo model has advanced to
        self._next_tick = -math.inf
        self._move: _Move | None = None
        self._con = o.initial_controller
        self._vp = 0
        self._grasp = 0
        self._pmin = list(o.min_angle_deg)
        self._pmax = list(o.max_angle_deg)
        self._poffset = [0.0] * NUM_AXES
        self._currents = {"ilim": list(o.ilim_a), "igrip": list(o.igrip_a),
                          "ihold": list(o.ihold_a)}  # fmt: skip
        self._kv = list(o.kv)
        self._pid = [o.pid] * NUM_AXES
        self._pos_save = [0] * NUM_AXES
        self._ref_mode = [0] * NUM_AXES
        self._props = dict.fromkeys(_PROPERTIES, 0)
        zeros = [0.0] * NUM_AXES
        self._ax = _Axes(
            target=self._clip([0.0] * NUM_AXES),
            velocity=list(_seven(o.pose_velocity)) if self._con == POSE else list(zeros),
            accel=list(_seven(o.pose_acceleration)),
            ref=list(zeros), rvel=list(zeros), actual=list(zeros), actual_vel=list(zeros),
            powered=[False] * NUM_AXES, blocked=[0] * NUM_AXES,
        )  # fmt: skip
        self._vectors = self._vector_table()

    # -- inspection ------------------------------------------------------------------------------

    @property
    def controller(self) -> int:
        """Current controller (0 pose, 1 velocity, 2 velocity with acceleration ramp)."""
        self.observe()
        return self._con

    @property
    def actual_deg(self) -> Vec:
        """Joint angles as the world last reported them."""
        self.observe()
        return tuple(self._ax.actual)

    @property
    def reference_deg(self) -> Vec:
        """The servo references the world was last asked to follow."""
        self.observe()
        return tuple(self._ax.ref)

    @property
    def target_deg(self) -> Vec:
        self.observe()
        return tuple(self._ax.target)

    @property
    def powered(self) -> tuple[bool, ...]:
        self.observe()
        return tuple(self._ax.powered)

    @property
    def moving(self) -> bool:
        """Whether the servo model needs ticks (a move runs or a velocity is non-zero)."""
        self.observe()
        return self._active()

    # -- Device protocol -------------------------------------------------------------------------

    def connected(self, now: float) -> None:
        self._process(now)
        self._advance(now)
        self._reset_link()

    def disconnected(self, now: float) -> None:
        self._process(now)
        self._advance(now)
        self._reset_link()
        if self._inbox and self._wake is not None:
            self._wake()  # commands still in process: no host is left to ask for them

    def receive(self, data: bytes, now: float) -> None:
        self._process(now)
        self._advance(now)
        o = self.options
        for event in self._parser.feed(data):
            if isinstance(event, ProtocolErrorEvent) and event.source is ErrorSource.GARBAGE:
                self.stats.errors += 1  # line noise: nothing to execute or answer, no time taken
                continue
            binary = isinstance(event, BinaryRequest)
            latency = o.binary_latency_s if binary else o.ascii_latency_s
            ready = max(now, self._busy_until) + latency
            self._busy_until = ready
            self._inbox.append((ready, event, self._generation))
        self._process(now)

    def next_packet(self, now: float) -> bytes | None:
        self._process(now)
        self._advance(now)
        if not self._outbox:
            return None
        packet = self._outbox.popleft()
        self.stats.replies += 1
        self.stats.bytes += len(packet)
        return packet

    def next_wakeup(self, now: float) -> float | None:
        self._process(now)
        self._advance(now)
        if self._outbox:
            return now
        ready = self._inbox[0][0] if self._inbox else None
        clocked = self._wake is not None or self._clock_now is not None
        due = None if clocked else self._due()
        if ready is None or due is None:
            return due if ready is None else ready
        return min(ready, due)

    # -- the outside clock -----------------------------------------------------------------------

    def attach_clock(self, wake: Callable[[], None]) -> None:
        """From now on an outside clock steps the servo (:meth:`step`); ``wake`` is called
        whenever a command may have brought the next step forward (e.g. started a motion)."""
        self._wake = wake

    def attach_lazy_clock(self, now: Callable[[], float]) -> None:
        """From now on the servo steps on an outside clock that tells the time (``now``) but
        does not wake at every tick: whoever reads the emulator or its world first calls
        :meth:`observe`, which steps every tick and processes every command due by then, each
        at its own time — what a clock that woke at each of those moments would have done."""
        self._wake = None  # nothing to wake: it catches up when observed
        self._clock_now = now

    def observe(self) -> None:
        """With a lazy clock: catch up with it (:meth:`catch_up`); else nothing."""
        if self._clock_now is not None:
            self.catch_up(self._clock_now())

    def catch_up(self, now: float) -> None:
        """Process the commands whose processing ends by ``now`` and step the servo ticks due
        by then, each at its own time; unlike :meth:`step`, no step at ``now`` itself (an
        observer between ticks sees the last one, as with a clock that wakes at each)."""
        if self._t is None:
            return  # not powered on yet: the clock's first step does that
        self._process(now)
        self._ticks(now)

    def step(self, now: float) -> float | None:
        """Bring the servo model and the world to ``now``; when the servo must next step on its
        own or a command's processing ends (None: not before a command)."""
        self._process(now)
        self._advance(now)
        due = self._due()
        if self._inbox:
            ready = self._inbox[0][0]
            return ready if due is None else min(due, ready)
        return due

    def _process(self, now: float) -> None:
        """Execute the commands whose processing time is over, each at its own ready time."""
        inbox = self._inbox
        while inbox and inbox[0][0] <= now:
            ready, event, generation = inbox.popleft()
            self._advance(ready)
            wake = self._wake
            due = self._due() if wake is not None else None
            reply = self._handle(event)
            if reply and generation == self._generation:
                self._outbox.append(reply)
            new = self._due() if wake is not None else None
            if wake is not None and new is not None and (due is None or new < due):
                wake()  # a motion started, or its next step came forward

    # -- event dispatch --------------------------------------------------------------------------

    def _handle(self, event: HostEvent) -> bytes:
        match event:
            case AsciiCommand():
                self.stats.commands += 1
                return self._ascii(event)
            case BinaryRequest():
                self.stats.commands += 1
                self.stats.binary += 1
                return self._binary(event)
            case BlankLine():
                self.stats.blank_lines += 1
                return encode_error(SdhError.NO_COMMAND) if self.options.blank_line_error else b""
            case ProtocolErrorEvent():
                self.stats.errors += 1
                return event.suggested_reply()  # garbage gets none (PART 4 item 11)

    def _ascii(self, cmd: AsciiCommand) -> bytes:
        try:
            if (since := COMMAND_SINCE.get(cmd.keyword)) is not None and self._release < since:
                raise _Reject(SdhError.CMD_UNKNOWN)  # older firmware lacks it (COMMAND_SINCE)
            if cmd.keyword in self._vectors:
                return self._ascii_vector(cmd)
            return self._ascii_other(cmd)
        except _Reject as exc:
            self.stats.errors += 1
            return encode_error(exc.code)

    def _ascii_vector(self, cmd: AsciiCommand) -> bytes:
        vec = self._vectors[cmd.keyword]
        if cmd.values is not None:
            if vec.write is None or vec.base is None:  # the codec already refuses these
                raise _Reject(SdhError.NO_PARAMS_EXPECTED)
            if cmd.axis is None:
                vec.write(cmd.values, _ALL)
            else:
                row = list(vec.base())
                row[cmd.axis] = cmd.values[0]
                vec.write(tuple(row), (cmd.axis,))
        values = vec.read()
        if cmd.axis is None:
            return self._reply(cmd.keyword, values)
        return self._reply(cmd.keyword, values[cmd.axis], axis=cmd.axis)

    def _ascii_other(self, cmd: AsciiCommand) -> bytes:
        kw, values, o = cmd.keyword, cmd.values, self.options
        text = {"ver": o.version, "ver_date": o.version_date, "id": o.hand_id,
                "sn": o.serial_number, "soc": o.soc_version, "soc_date": o.soc_date}  # fmt: skip
        if kw in text:
            return encode_reply(kw, text[kw])
        match kw:
            case "m":
                return self._reply(kw, self._round_up(self._start_m()))
            case "get_duration":
                return self._reply(kw, self._round_up(self._duration(self._ax.target)))
            case "stop":
                self._stop()
                return encode_reply(kw, o.stop_reply)
            case "temp":
                return self._reply(kw, o.temperatures_c)
            case "numaxis":
                return self._reply(kw, NUM_AXES)
            case "vp":
                if values is not None:
                    self._set_vp(int(values[0]))
                return self._reply(kw, self._vp)
            case "con":
                if values is not None:
                    self._set_controller(int(values[0]))
                return self._reply(kw, self._con)
            case "selgrip":
                assert values is not None  # the codec refuses a bare selgrip
                gid = int(values[0])
                return self._reply(kw, (self._round_up(self._selgrip(gid)), gid))
            case "grip":
                assert values is not None
                return self._reply(kw, (self._round_up(self._grip(*values)), values[0]))
            case "kv" | "pid":
                assert cmd.axis is not None  # axis-only commands (§2.4)
                return self._reply(kw, self._gains(kw, cmd.axis, values), axis=cmd.axis)
            case _:  # demo, user_errors, terminal, debug
                if values is not None:
                    self._props[kw] = int(values[0])
                return self._reply(kw, self._props[kw])

    def _binary(self, req: BinaryRequest) -> bytes:
        kw = req.cmd.keyword
        try:
            if kw not in BINARY_COMMANDS:
                raise _Reject(SdhError.CMD_UNKNOWN)
            vec = self._vectors[kw]
            if req.values is not None:
                if vec.write is None:
                    raise _Reject(SdhError.NO_PARAMS_EXPECTED)
                if not all(math.isfinite(v) for v in req.values):
                    raise _Reject(self.options.range_error)
                vec.write(req.values, _ALL)
            return encode_binary_reply(req.cmd, SdhError.SUCCESS, vec.read(),
                                       with_crc=req.with_crc)  # fmt: skip
        except _Reject as exc:
            self.stats.errors += 1
            return encode_binary_reply(req.cmd, exc.code, with_crc=req.with_crc)

    def _reply(self, kw: str, values: float | Sequence[float], *, axis: int | None = None) -> bytes:
        return encode_reply(kw, values, axis=axis, fmt=self.options.reply_fmt)

    @staticmethod
    def _round_up(duration: float) -> float:
        # Hosts may sleep T instead of polling (PART 4 item 6): never announce less than T.
        return math.ceil(duration * 1000.0 - 1e-6) / 1000.0

    def _reset_link(self) -> None:
        self._parser.reset()
        self._outbox.clear()
        self._generation += 1

    # -- vector commands -------------------------------------------------------------------------

    def _vector_table(self) -> dict[str, _Vector]:
        ax, o = self._ax, self.options

        def get(values: list[float]) -> Callable[[], Vec]:
            return lambda: tuple(values)

        def current(name: str) -> _Vector:
            values = self._currents[name]
            return _Vector(get(values), get(values), self._current_writer(values))

        def power() -> Vec:
            return tuple(int(p) for p in ax.powered)

        return {
            "p": _Vector(get(ax.target), get(ax.target), self._set_targets),
            "tpap": _Vector(get(ax.actual), get(ax.target), self._set_targets),
            "pos": _Vector(get(ax.actual)),
            "v": _Vector(get(ax.velocity), get(ax.velocity), self._set_velocities),
            "tvav": _Vector(get(ax.actual_vel), get(ax.velocity), self._set_velocities),
            "vel": _Vector(get(ax.actual_vel)),
            "rvel": _Vector(get(ax.rvel)),
            "a": _Vector(get(ax.accel), get(ax.accel), self._set_accelerations),
            "state": _Vector(lambda: tuple(self._state(i) for i in _ALL)),
            "power": _Vector(power, power, self._set_power),
            "vlim": _Vector(lambda: o.velocity_limit),
            "alim": _Vector(lambda: o.acceleration_limit),
            "p_min": _Vector(get(self._pmin), get(self._pmin), self._limit_writer(upper=False)),
            "p_max": _Vector(get(self._pmax), get(self._pmax), self._limit_writer(upper=True)),
            "p_offset": _Vector(get(self._poffset), get(self._poffset), self._set_offsets),
            "ilim": current("ilim"),
            "igrip": current("igrip"),
            "ihold": current("ihold"),
            "pos_save": self._flag_vector(self._pos_save, (0, 1)),
            "ref": self._flag_vector(self._ref_mode, (0, 1, 2)),
        }

    def _require(self, ok: bool) -> None:
        if not ok:
            raise _Reject(self.options.range_error)

    def _set_targets(self, values: Vec, axes: Sequence[int]) -> None:
        self._require(all(self._pmin[i] - _LIMIT_TOL <= v <= self._pmax[i] + _LIMIT_TOL
                          for i, v in enumerate(values)))  # fmt: skip
        self._ax.target[:] = self._clip(values)

    def _set_velocities(self, values: Vec, axes: Sequence[int]) -> None:
        vlim, ax = self.options.velocity_limit, self._ax
        low = 0.0 if self._con == POSE else -1.0  # pose: magnitudes (CPP AdjustLimits)
        self._require(all(low * vlim[i] <= v <= vlim[i] for i, v in enumerate(values)))
        ax.velocity[:] = values
        if self._con == POSE:
            return
        for i in axes:
            if values[i] != 0.0:
                self._enable(i)  # implicit enable (PART 4 item 5)
            if ax.blocked[i] * values[i] < 0.0:
                ax.blocked[i] = 0  # pulling away from the obstacle
        if self._con == VELOCITY:  # no ramp: the reference velocity jumps to the target
            for i in _ALL:
                free = ax.powered[i] and not ax.blocked[i] and not self._pinned(i)
                ax.rvel[i] = values[i] if free else 0.0

    def _set_accelerations(self, values: Vec, axes: Sequence[int]) -> None:
        alim = self.options.acceleration_limit
        self._require(all(0.0 <= v <= alim[i] for i, v in enumerate(values)))
        self._ax.accel[:] = values

    def _set_power(self, values: Vec, axes: Sequence[int]) -> None:
        self._require(all(v in (0.0, 1.0) for v in values))
        ax = self._ax
        for i, flag in enumerate(values):
            if flag and not ax.powered[i]:
                self._enable(i)
            elif not flag and ax.powered[i]:
                ax.powered[i], ax.blocked[i], ax.rvel[i] = False, 0, 0.0
                ax.in_move[i] = False
                ax.ref[i] = ax.actual[i]
                if self._con != POSE:  # its target velocity too: powered on, it holds still
                    ax.velocity[i] = 0.0
        if self._move is not None and not any(ax.in_move):
            self._move = None

    def _limit_writer(self, *, upper: bool) -> Writer:
        def write(values: Vec, axes: Sequence[int]) -> None:
            o = self.options
            lo = self._pmin if upper else list(values)
            hi = list(values) if upper else self._pmax
            self._require(all(
                o.min_angle_deg[i] <= lo[i] <= hi[i] <= o.max_angle_deg[i] for i in _ALL
            ))  # fmt: skip
            (self._pmax if upper else self._pmin)[:] = values
            self._ax.target[:] = self._clip(self._ax.target)

        return write

    def _set_offsets(self, values: Vec, axes: Sequence[int]) -> None:
        self._poffset[:] = values

    def _current_writer(self, store: list[float]) -> Writer:
        def write(values: Vec, axes: Sequence[int]) -> None:
            self._require(all(0.0 <= v <= self.options.max_current_a for v in values))
            store[:] = values

        return write

    def _flag_vector(self, store: list[int], allowed: tuple[int, ...]) -> _Vector:
        def write(values: Vec, axes: Sequence[int]) -> None:
            self._require(all(v in allowed for v in values))
            store[:] = [int(v) for v in values]

        def read() -> Vec:
            return tuple(store)

        return _Vector(read, read, write)

    def _clip(self, values: Sequence[float]) -> list[float]:
        out = []
        for v, lo, hi in zip(values, self._pmin, self._pmax, strict=True):
            v = lo if lo > v else v  # max(v, lo) and min(…, hi), as those pick
            out.append(hi if hi < v else v)
        return out

    # -- other commands --------------------------------------------------------------------------

    def _set_vp(self, profile: int) -> None:
        self._require(profile in (0, 1))
        self._vp = profile

    def _set_controller(self, con: int) -> None:
        self._require(con in (POSE, VELOCITY, VELOCITY_ACCELERATION))
        ax, o = self._ax, self.options
        self._move = None
        self._con = con
        ax.in_move[:] = [False] * NUM_AXES
        ax.rvel[:] = [0.0] * NUM_AXES
        ax.blocked[:] = [0] * NUM_AXES
        if con == POSE:
            ax.velocity[:] = _seven(o.pose_velocity)
            ax.accel[:] = _seven(o.pose_acceleration)
            if o.con_resets_targets:
                ax.target[:] = self._clip([0.0] * NUM_AXES)
        else:
            ax.velocity[:] = [0.0] * NUM_AXES

    def _stop(self) -> None:
        ax = self._ax
        if self._move is not None and self._move.stoppable:
            self._move = None
            ax.in_move[:] = [False] * NUM_AXES
            ax.rvel[:] = [0.0] * NUM_AXES
        if self._con != POSE:
            ax.velocity[:] = [0.0] * NUM_AXES
            ax.rvel[:] = [0.0] * NUM_AXES

    def _gains(self, kw: str, axis: int, values: Vec | None) -> float | Vec:
        if values is not None:
            self._require(all(v >= 0.0 for v in values))
            if kw == "kv":
                self._kv[axis] = values[0]
            else:
                p, i, d = values
                self._pid[axis] = (p, i, d)
        return self._kv[axis] if kw == "kv" else self._pid[axis]

    def _selgrip(self, gid: int) -> float:
        self._require(0 <= gid < len(self.options.grasps))
        self._grasp = gid
        return self._grasp_move(0.0, self.options.grasp_velocity)

    def _grip(self, close: float, velocity: float) -> float:
        self._require(0.0 <= close <= 1.0 and 0.0 < velocity <= self.options.grip_max_velocity)
        return self._grasp_move(close, velocity)

    def _grasp_move(self, close: float, velocity: float) -> float:
        goal = self._clip(self.options.grasps[self._grasp].pose(close))
        speeds = [min(velocity, lim) for lim in self.options.velocity_limit]
        return self._start_move(goal, speeds, stoppable=False)

    # -- motion ----------------------------------------------------------------------------------

    def _plan(self, goal: Sequence[float], speeds: Sequence[float] | None = None
              ) -> tuple[Vec, Profile, tuple[Carry, ...]]:  # fmt: skip
        """Where a move to ``goal`` starts, its coordinated profile, and each axis's carry.

        From rest: from the actual angles, no carry. Mid-move (any axis's reference still
        moving): from the references (a blocked axis: from its actual angle), each axis keeping
        its reference velocity, which ramps down
        at the axis's acceleration while the coordinated profile covers the rest of the way — so
        the reference velocity is continuous across the replan. An axis whose carry overshoots
        its goal (a reversal) shares its acceleration half and half between the two, so the sum
        stays within ``a``."""
        ax, sin2 = self._ax, self._vp == 0
        speeds = ax.velocity if speeds is None else speeds
        accels = list(ax.accel)
        moving = self._move is not None and any(v != 0.0 for v in ax.rvel)
        free = [moving and ax.powered[i] and not ax.blocked[i] for i in _ALL]
        # a blocked axis starts afresh from where it is, as from rest
        start = tuple(ax.ref[i] if free[i] else ax.actual[i] for i in _ALL)
        v0 = [ax.rvel[i] if free[i] else 0.0 for i in _ALL]
        halved = [False] * NUM_AXES

        def carries(at_least: float) -> list[tuple[float, float]]:  # (v0, time) of each
            out = []
            for i in _ALL:
                c = _carry(v0[i], accels[i], sin2, at_least)
                if not halved[i] and (goal[i] - start[i] - c[0] * c[1] / 2) * v0[i] < 0.0:
                    halved[i] = True  # a reversal: carry and profile share the acceleration
                    accels[i] /= 2
                    c = _carry(v0[i], accels[i], sin2, at_least)
                out.append(c)
            return out

        carry = carries(0.0)
        try:
            for _ in range(3):  # the carry ramps down while the profile ramps up: same length
                dist = [g - s - v * t / 2 for g, s, (v, t) in zip(goal, start, carry, strict=True)]
                profile = Profile.plan(dist, speeds, accels, sin2=sin2)
                if not moving or all(t >= profile.ramp - 1e-9 for v, t in carry if v):
                    break
                carry = carries(profile.ramp)
        except ValueError:
            raise _Reject(self.options.range_error) from None
        return start, profile, tuple(Carry(v, t, sin2) if v else _STILL[sin2] for v, t in carry)

    def _duration(self, goal: Sequence[float]) -> float:
        _, profile, carry = self._plan(goal)
        return max(profile.duration, max(c.time for c in carry))

    def _start_m(self) -> float:
        return self._start_move(self._ax.target, self._ax.velocity, stoppable=True)

    def _start_move(self, goal: Sequence[float], speeds: Sequence[float], *,
                    stoppable: bool) -> float:  # fmt: skip
        """Start a coordinated move (from rest: from the actual angles; mid-move: from the
        references and their velocities, see :meth:`_plan`); returns its duration."""
        if self._con != POSE:
            raise _Reject(self.options.wrong_mode_error)
        start, profile, carry = self._plan(goal, speeds)
        assert self._t is not None
        ax = self._ax
        ax.powered[:] = [True] * NUM_AXES  # "Enabling all axis" (§2.4, PART 4 item 5)
        ax.blocked[:] = [0] * NUM_AXES
        ax.ref[:] = start
        ax.rvel[:] = [c.v0 for c in carry]
        ax.in_move[:] = [abs(g - s) > _EPS or c.v0 != 0.0
                         for g, s, c in zip(goal, start, carry, strict=True)]  # fmt: skip
        move = _Move(start, tuple(goal), profile, self._t, stoppable, carry)
        self._move = move if move.duration > 0.0 else None
        if self._move is None:
            ax.in_move[:] = [False] * NUM_AXES
        return move.duration

    def _enable(self, i: int) -> None:
        ax = self._ax
        if not ax.powered[i]:
            ax.powered[i], ax.blocked[i], ax.rvel[i] = True, 0, 0.0
            ax.ref[i] = ax.actual[i]  # hold where it is

    def _pinned(self, i: int) -> bool:
        """In a velocity controller, the reference sits at a limit the target pushes past."""
        ax = self._ax
        v = ax.velocity[i]
        return (ax.ref[i] >= self._pmax[i] and v > 0.0) or (ax.ref[i] <= self._pmin[i] and v < 0.0)

    def _velocity_active(self, i: int) -> bool:
        ax = self._ax
        return (ax.powered[i] and not ax.blocked[i] and not self._pinned(i)
                and (ax.velocity[i] != 0.0 or ax.rvel[i] != 0.0))  # fmt: skip

    def _active(self) -> bool:
        if self._move is not None:
            return True
        return self._con != POSE and any(self._velocity_active(i) for i in _ALL)

    def _state(self, i: int) -> int:
        ax = self._ax
        if ax.blocked[i]:
            cw = (ax.blocked[i] > 0) == self.options.positive_is_cw
            return AxisState.CW_BLOCKED if cw else AxisState.CCW_BLOCKED
        if not ax.powered[i]:
            return AxisState.DISABLED
        if self._con == POSE:
            return AxisState.POSITIONING if self._move and ax.in_move[i] else AxisState.IDLE
        if self._pinned(i):
            return AxisState.LIMITS_REACHED
        moving = ax.velocity[i] != 0.0 or ax.rvel[i] != 0.0
        return AxisState.SPEED_MODE if moving else AxisState.IDLE

    def _due(self) -> float | None:
        """When the servo model must next step on its own (None: only at the next command)."""
        move = self._move
        if move is None and not self._active():
            return None
        t = self._t
        assert t is not None
        if self._next_tick <= t:  # motion (re)started: the tick grid starts now
            self._next_tick = t + self.options.tick_s
        due = self._next_tick
        if move is None:
            return due
        return move.end if move.end < due else due  # min(due, end)

    def _advance(self, now: float) -> None:
        """Bring the servo model and the world to ``now``: every tick due, then ``now`` itself."""
        if self._t is None:
            self._power_on(now)
            return
        if now <= self._t:
            return
        self._ticks(now)
        if now > self._t:
            self._step(now)

    def _ticks(self, now: float) -> None:
        """Step every tick (and a move's end) due by ``now``. A lazy clock's ticks keep their
        grid however long the gap; otherwise a long one is crossed in at most
        ``max_catchup_steps`` evenly spaced steps."""
        assert self._t is not None
        tick = self.options.tick_s
        if self._clock_now is None:
            tick = max(tick, (now - self._t) / self.options.max_catchup_steps)
        while (due := self._due()) is not None and due <= now:
            self._step(due)
            next_tick = self._next_tick
            while next_tick <= due:
                next_tick += tick
            self._next_tick = next_tick

    def _power_on(self, now: float) -> None:
        ax = self._ax
        # Unpowered joints stay where they are: this only asks the world where that is.
        actual = self._world.move_joints(now, tuple(ax.ref), (False,) * NUM_AXES)
        ax.actual[:] = [float(a) for a in actual]
        ax.ref[:] = ax.actual
        ax.powered[:] = [self.options.initially_powered] * NUM_AXES
        self._t = now

    def _step(self, t: float) -> None:
        assert self._t is not None
        dt = t - self._t
        move, ax = self._move, self._ax  # (neither the world nor _observe changes the move)
        if move is not None:
            self._follow(t)
        elif self._con != POSE:
            self._integrate(dt)
        actual = self._world.move_joints(t, tuple(ax.ref), tuple(ax.powered))
        self._observe(list(map(float, actual)), dt)
        if move is not None and t >= move.end:
            self._move = None
            ax.in_move[:] = [False] * NUM_AXES
            ax.rvel[:] = [0.0] * NUM_AXES
        self._t = t

    def _follow(self, t: float) -> None:
        """Pose controller: references along the coordinated profile."""
        move, ax = self._move, self._ax
        assert move is not None
        tau = t - move.t0
        in_move, blocked, ref, rvel = ax.in_move, ax.blocked, ax.ref, ax.rvel
        if tau >= move.duration:  # done
            for i in _ALL:
                if in_move[i] and not blocked[i]:
                    ref[i], rvel[i] = move.goal[i], 0.0
            return
        frac, rate = move.profile.at(tau)
        for i, base, span in move.plain:  # no carry: its offset and velocity are 0.0
            if in_move[i] and not blocked[i]:
                ref[i] = base + span * frac
                rvel[i] = 0.0 + span * rate
        for group in move.coast:
            group.follow(tau, frac, rate, ax)

    def _integrate(self, dt: float) -> None:
        """Velocity controllers: advance each reference by its (ramped) velocity over ``dt``."""
        ax = self._ax
        for i in _ALL:
            if not ax.powered[i] or ax.blocked[i]:
                ax.rvel[i] = 0.0
                continue
            r0, goal = ax.rvel[i], ax.velocity[i]
            if self._con == VELOCITY:
                r1, dist = goal, goal * dt
            else:
                r1, dist = _ramp(r0, goal, ax.accel[i], dt)
            new = ax.ref[i] + dist
            if dist > 0.0 and new >= self._pmax[i]:
                new, r1 = max(self._pmax[i], ax.ref[i]), 0.0
            elif dist < 0.0 and new <= self._pmin[i]:
                new, r1 = min(self._pmin[i], ax.ref[i]), 0.0
            ax.ref[i], ax.rvel[i] = new, r1

    def _observe(self, actual: list[float], dt: float) -> None:
        """Take the world's angles; detect blocked axes and release velocity-mode blocks."""
        ax, margin = self._ax, self.options.blocked_margin_deg
        was, vel, powered, ref = ax.actual, ax.actual_vel, ax.powered, ax.ref
        blocked, rvel = ax.blocked, ax.rvel
        for i in _ALL:
            a = actual[i]
            if dt > 0.0:
                vel[i] = (a - was[i]) / dt
            was[i] = a
            if not powered[i]:
                ref[i], rvel[i] = a, 0.0  # limp: the reference follows the joint
                continue
            lag = ref[i] - a
            if blocked[i]:
                if self._con != POSE and abs(lag) <= margin / 2:
                    blocked[i] = 0  # the obstacle gave way
            elif abs(lag) > margin and self._axis_moving(i):
                blocked[i] = 1 if lag > 0.0 else -1
                rvel[i] = 0.0

    def _axis_moving(self, i: int) -> bool:
        if self._con == POSE:
            return self._move is not None and self._ax.in_move[i]
        return self._ax.rvel[i] != 0.0 or self._ax.velocity[i] != 0.0


def _ramp(r0: float, goal: float, accel: float, dt: float) -> tuple[float, float]:
    """Reference velocity after ``dt`` ramping from ``r0`` towards ``goal`` at ``accel``, and the
    distance covered meanwhile (exact for the piecewise-linear velocity)."""
    if accel <= 0.0 or r0 == goal:
        return r0, r0 * dt
    reach = abs(goal - r0) / accel
    if dt <= reach:
        r1 = r0 + math.copysign(accel * dt, goal - r0)
        return r1, (r0 + r1) / 2 * dt
    return goal, (r0 + goal) / 2 * reach + goal * (dt - reach)
