"""SDH2 joint-controller emulator: commands, servo model, binary frames, and real transports.

Unit tests drive the sans-I/O emulator directly with fake ``now`` values and decode its output
with the codec's :class:`ReplyParser`; end-to-end tests put it behind a real pty and a real TCP
port and talk to it with pyserial-asyncio as SDHLibrary would. Wall-clock assertions are lower
bounds only.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator, Sequence

import numpy as np
import pytest
import serial
import serial_asyncio

from sdh2svc.protocol.sdh import (
    ASCII_COMMANDS,
    BINARY_COMMANDS,
    NUM_AXES,
    AxisState,
    BinaryCommand,
    BinaryReply,
    ErrorLine,
    Reply,
    ReplyParser,
    SdhError,
    binary_reply_size,
    encode_binary_request,
)
from sdh2svc.sim.endpoint import DEFAULT_BAUD, Device, PtyEndpoint, TcpEndpoint
from sdh2svc.sim.sdh2 import DEFAULT_GRASPS, Grasp, Profile, Sdh2Emulator, Sdh2Options
from sdh2svc.sim.world import ScriptedWorld

SHAPES = ((14, 6), (13, 6)) * 3
TICK = 0.005
ZEROS = (0.0,) * NUM_AXES


def vec(values: Sequence[float]) -> str:
    return ",".join(f"{v:f}" for v in values)


class ObstacleWorld:
    """Joints follow their reference, except that ``axis`` cannot leave ``lo…hi`` (a stiff
    object); unpowered joints stay put. Records the time of every call."""

    matrix_shapes = SHAPES

    def __init__(self, axis: int = 1, lo: float = -math.inf, hi: float = math.inf) -> None:
        self.axis, self.lo, self.hi = axis, lo, hi
        self.angles = [0.0] * NUM_AXES
        self.calls: list[float] = []

    def move_joints(self, now: float, reference_deg: Sequence[float],
                    powered: Sequence[bool]) -> tuple[float, ...]:  # fmt: skip
        self.calls.append(now)
        for i, (ref, on) in enumerate(zip(reference_deg, powered, strict=True)):
            if on:
                self.angles[i] = min(max(ref, self.lo), self.hi) if i == self.axis else ref
        return tuple(self.angles)

    def tactile_frame(self, now: float, sensitivity: Sequence[float],
                      threshold: Sequence[int]) -> np.ndarray:  # fmt: skip
        return np.zeros(sum(r * c for r, c in SHAPES), dtype=np.uint16)


class Host:
    """Drives an emulator the way an endpoint does, on a fake clock starting at ``now``."""

    def __init__(self, emu: Sdh2Emulator | None = None, now: float = 10.0) -> None:
        self.emu = emu or Sdh2Emulator(ScriptedWorld(SHAPES))
        self.now = now
        self.emu.connected(now)

    def send(self, data: bytes) -> bytes:
        self.emu.receive(data, self.now)
        out = b""
        while (packet := self.emu.next_packet(self.now)) is not None:
            out += packet
        return out

    def ask(self, line: str) -> Reply | ErrorLine:
        raw = self.send(line.encode("ascii") + b"\r\n")
        assert raw.endswith(b"\r\n") and raw.count(b"\n") == 1, raw  # exactly one line
        (event,) = ReplyParser().feed(raw)
        assert isinstance(event, Reply | ErrorLine), event
        return event

    def values(self, line: str) -> tuple[float, ...]:
        reply = self.ask(line)
        assert isinstance(reply, Reply), reply
        return reply.values

    def error(self, line: str) -> int:
        reply = self.ask(line)
        assert isinstance(reply, ErrorLine), reply
        return reply.code

    def binary(self, cmd: BinaryCommand, values: Sequence[float] | None = None, *,
               crc: bool = True) -> BinaryReply:  # fmt: skip
        raw = self.send(encode_binary_request(cmd, values, with_crc=crc))
        assert len(raw) == binary_reply_size(crc)
        reply = BinaryReply.decode(raw, crc=crc)  # checks the CRC
        assert reply.cmd == cmd
        return reply

    def run(self, until: float) -> list[tuple[float, tuple[float, ...]]]:
        """Wake the emulator whenever it asks until ``until``; (time, actual angles) per wake."""
        trace = []
        while (wake := self.emu.next_wakeup(self.now)) is not None and wake <= until:
            assert wake > self.now or wake == self.now == until
            self.now = wake
            assert self.emu.next_packet(wake) is None
            trace.append((wake, self.emu.actual_deg))
        self.now = until
        self.emu.next_packet(until)
        return trace

    def later(self, dt: float) -> list[tuple[float, tuple[float, ...]]]:
        return self.run(self.now + dt)


def targets_move(
    host: Host,
    targets: Sequence[float],
    *,
    vp: int = 0,
    v: Sequence[float] | None = None,
    a: Sequence[float] | None = None,
) -> float:
    """con=0, vp, v, a, p, then m; returns T."""
    assert host.values("con=0") == (0,)
    assert host.values(f"vp={vp}") == (vp,)
    if v is not None:
        host.ask(f"v={vec(v)}")
    if a is not None:
        host.ask(f"a={vec(a)}")
    assert host.values(f"p={vec(targets)}") == pytest.approx(targets, abs=1e-3)
    (duration,) = host.values("m")
    return duration


# -- every command -----------------------------------------------------------------------------

SEVEN = vec((10.0, -20.0, 30.0, -40.0, 50.0, -60.0, 70.0))
ONES = "1,1,1,1,1,1,1"
CASES = [
    # request, reply keyword, value count (None: a text body)
    ("power", "POWER", 7), ("power=0,0,0,0,0,0,0", "POWER", 7),
    ("p", "P", 7), (f"p={SEVEN}", "P", 7), ("m", "M", 1), ("get_duration", "GET_DURATION", 1),
    ("stop", "STOP", 0), ("pos", "POS", 7), ("vel", "VEL", 7), ("rvel", "RVEL", 7),
    ("state", "STATE", 7), ("v", "V", 7), ("v=10,20,30,40,50,60,70", "V", 7), ("a", "A", 7),
    ("a=50,50,50,50,50,50,50", "A", 7), ("tpap", "TPAP", 7), (f"tpap={SEVEN}", "TPAP", 7),
    ("tvav", "TVAV", 7), ("tvav=1,2,3,4,5,6,7", "TVAV", 7), ("vlim", "VLIM", 7),
    ("alim", "ALIM", 7), ("p_min", "P_MIN", 7), ("p_min=0,-80,-80,-80,-80,-80,-80", "P_MIN", 7),
    ("p_max", "P_MAX", 7), ("p_max=80,80,80,80,80,80,80", "P_MAX", 7),
    ("p_offset", "P_OFFSET", 7), ("p_offset=1,2,3,4,5,6,7", "P_OFFSET", 7), ("vp", "VP", 1),
    ("vp=1", "VP", 1), ("con", "CON", 1), ("con=0", "CON", 1), ("ilim", "ILIM", 7),
    ("ilim=0.5,0.5,0.5,0.5,0.5,0.5,0.5", "ILIM", 7), ("igrip", "IGRIP", 7),
    ("igrip=1,1,1,1,1,1,1", "IGRIP", 7), ("ihold", "IHOLD", 7),
    ("ihold=0.1,0.1,0.1,0.1,0.1,0.1,0.1", "IHOLD", 7), ("kv(2)", "KV", 1), ("kv(2)=1.5", "KV", 1),
    ("pid(1)", "PID", 3), ("pid(1)=1,0.1,0", "PID", 3), ("temp", "TEMP", 9),
    ("ver", "VER", None), ("ver_date", "VER_DATE", None), ("id", "ID", None),
    ("sn", "SN", None), ("soc", "SOC", None), ("soc_date", "SOC_DATE", None),
    ("numaxis", "NUMAXIS", 1), ("selgrip=1", "SELGRIP", 2), ("grip=0.5,40", "GRIP", 2),
    ("pos_save", "POS_SAVE", 7), (f"pos_save={ONES}", "POS_SAVE", 7), ("ref", "REF", 7),
    ("ref=0,1,2,0,1,2,0", "REF", 7), ("demo", "DEMO", 1), ("demo=1", "DEMO", 1),
    ("user_errors", "USER_ERRORS", 1), ("user_errors=2", "USER_ERRORS", 1),
    ("terminal", "TERMINAL", 1), ("terminal=1", "TERMINAL", 1), ("debug", "DEBUG", 1),
    ("debug=3", "DEBUG", 1),
]  # fmt: skip


@pytest.mark.parametrize(("line", "keyword", "count"), CASES)
def test_every_command_replies_with_its_keyword_and_value_count(
    line: str, keyword: str, count: int | None
) -> None:
    host = Host()
    if line.startswith("tvav="):
        host.ask("con=1")  # velocities may be signed and move only in a velocity controller
    reply = host.ask(line)
    assert isinstance(reply, Reply), reply
    axis = int(line.split("(")[1].split(")")[0]) if "(" in line else None
    assert (reply.keyword, reply.axis) == (keyword, axis)
    if count is None:
        assert reply.text  # an identification string
    else:
        assert len(reply.values) == count, reply


def test_every_command_of_the_table_is_exercised() -> None:
    covered = {line.split("=")[0].split("(")[0] for line, _, _ in CASES}
    assert covered == set(ASCII_COMMANDS)


def test_emulator_is_a_device_and_answers_the_basics() -> None:
    host = Host()
    assert isinstance(host.emu, Device)
    assert host.ask("ver").text == "0.0.3.3"
    assert host.values("vlim") == (83, 140, 200, 140, 200, 140, 200)
    assert host.values("alim") == (5000, 400, 1500, 400, 1500, 400, 1500)
    assert host.values("numaxis") == (7,)
    assert host.values("con") == (0,)
    assert host.values("v") == (40,) * 7 and host.values("a") == (100,) * 7
    assert host.values("state") == (AxisState.DISABLED,) * 7  # nothing powered after power-on
    assert host.send(b"stop\r\n") == b"STOP=\r\n"
    assert host.send(b"power\r\n") == b"POWER=0,0,0,0,0,0,0\r\n"
    custom = Host(
        Sdh2Emulator(
            ScriptedWorld(SHAPES),
            options=Sdh2Options(
                version="0.0.2.15", reply_fmt="{:.1f}", stop_reply="OK", initially_powered=True
            ),
        )
    )
    assert custom.send(b"ver\r\n") == b"VER=0.0.2.15\r\n"
    assert custom.send(b"p(1)\r\n") == b"P(1)=0.0\r\n"
    assert custom.send(b"stop\r\n") == b"STOP=OK\r\n"
    assert custom.values("state") == (0,) * 7


def test_per_axis_forms() -> None:
    host = Host()
    assert host.send(b"p(3)=     -45.000\r\n") == b"P(3)=-45.000\r\n"  # C++ %12.3f padding
    reply = host.ask("p(3)")
    assert (reply.keyword, reply.axis, reply.values) == ("P", 3, (-45.0,))
    assert host.values("p") == (0, 0, 0, -45, 0, 0, 0)
    assert host.ask("vlim(0)").values == (83,)
    assert host.ask("pos(3)").axis == 3
    assert host.send(b"state(2)\r\n") == b"STATE(2)=6\r\n"
    assert host.send(b"power(2)=1\r\n") == b"POWER(2)=1\r\n"
    assert host.values("power") == (0, 0, 1, 0, 0, 0, 0)
    assert host.ask("v(6)=12.5").values == (12.5,)
    assert host.values("v")[6] == 12.5 and host.values("v")[5] == 40
    assert host.ask("pid(4)=1,2,3").values == (1, 2, 3)
    assert host.ask("pid(4)").values == (1, 2, 3) and host.ask("pid(3)").values != (1, 2, 3)
    assert host.ask("kv(0)=2").values == (2,)
    assert host.ask("con=1").values == (1,)
    reply = host.ask("tvav(5)=-10")
    assert (reply.keyword, reply.axis, reply.values) == ("TVAV", 5, (0.0,))  # actual, at rest
    assert host.values("v")[5] == -10


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("frobnicate", SdhError.CMD_UNKNOWN),
        ("p=1,2,x,4,5,6,7", SdhError.CMD_FORMAT_ERROR),
        ("p(9)", SdhError.INDEX_OUT_OF_BOUNDS),
        ("p=1,2", SdhError.NOT_ENOUGH_PARAMS),
        ("p(0)=-5", SdhError.RANGE_ERROR),  # axis 0 is 0…90
        ("p=0,0,0,0,0,0,95", SdhError.RANGE_ERROR),
        ("tpap=0,0,0,-91,0,0,0", SdhError.RANGE_ERROR),
        ("v=0,0,0,0,0,0,201", SdhError.RANGE_ERROR),
        ("v(1)=-5", SdhError.RANGE_ERROR),  # pose velocities are magnitudes
        ("a(1)=401", SdhError.RANGE_ERROR),
        ("a=-1,0,0,0,0,0,0", SdhError.RANGE_ERROR),
        ("power=2,0,0,0,0,0,0", SdhError.RANGE_ERROR),
        ("power=0.5,0,0,0,0,0,0", SdhError.INVALID_PARAMETER),
        ("con=3", SdhError.RANGE_ERROR),
        ("vp=2", SdhError.RANGE_ERROR),
        ("selgrip=4", SdhError.RANGE_ERROR),
        ("grip=1.5,40", SdhError.RANGE_ERROR),
        ("grip=0.5,0", SdhError.RANGE_ERROR),
        ("grip=0.5,101", SdhError.RANGE_ERROR),
        ("ilim=0,0,0,0,0,0,1.5", SdhError.RANGE_ERROR),
        ("ref=0,0,0,3,0,0,0", SdhError.RANGE_ERROR),
        ("p_min=-1,0,0,0,0,0,0", SdhError.RANGE_ERROR),  # below the factory range
        ("p_max(1)=-95", SdhError.RANGE_ERROR),
        ("kv(1)=-1", SdhError.RANGE_ERROR),
        ("pos=1,2,3,4,5,6,7", SdhError.NO_PARAMS_EXPECTED),
    ],
)
def test_errors_answer_e_n_and_change_nothing(line: str, code: SdhError) -> None:
    host = Host()
    host.ask("p=10,20,30,40,50,60,70")
    before = {
        kw: host.ask(kw).text
        for kw in (
            "p",
            "v",
            "a",
            "power",
            "con",
            "vp",
            "ilim",
            "ref",
            "p_min",
            "p_max",
            "kv(1)",
            "state",
        )
    }
    assert host.send(line.encode() + b"\r\n") == f"E{int(code)}\r\n".encode()
    after = {kw: host.ask(kw).text for kw in before}
    assert after == before
    assert host.emu.stats.errors == 1


def test_wrong_controller_and_impossible_moves_are_refused() -> None:
    host = Host()
    host.ask("con=1")
    for line in ("m", "selgrip=0", "grip=0.5,40"):
        assert host.error(line) == SdhError.CMD_FAILED
    host.ask("con=0")
    host.ask("p(2)=30")
    host.ask("v(2)=0")  # must move, cannot
    assert host.error("m") == SdhError.RANGE_ERROR
    assert host.error("get_duration") == SdhError.RANGE_ERROR
    host.ask("v(2)=40")
    host.ask("a(2)=0")
    assert host.error("m") == SdhError.RANGE_ERROR
    host.ask("p(2)=0")  # nothing to move: zero v/a no longer matter
    assert host.values("m") == (0.0,)
    assert host.values("state") == (0,) * 7  # m enabled every axis


def test_blank_line_is_silent_and_ver_answers_at_once() -> None:
    host = Host()
    assert host.send(b" \r\n") == b""
    assert host.emu.next_wakeup(host.now) is None  # nothing pending, nothing moving
    assert host.send(b"ver\r\n") == b"VER=0.0.3.3\r\n"
    assert host.emu.stats.blank_lines == 1
    loud = Host(Sdh2Emulator(ScriptedWorld(SHAPES), options=Sdh2Options(blank_line_error=True)))
    assert loud.send(b" \r\n") == b"E34\r\n"


def test_one_reply_per_command_in_order_across_chunks() -> None:
    host = Host()
    assert host.send(b"ver\r\nnumaxis\r\n\r\ncon\nfoo\r\n") == (
        b"VER=0.0.3.3\r\nNUMAXIS=7\r\nCON=0\r\nE13\r\n"  # bare \n accepted, blank silent
    )
    out = b"".join(host.send(bytes([b])) for b in b"p(1)=12.5\r\n")
    assert out == b"P(1)=12.500\r\n"
    assert host.send(b"\x83\x03") == b""  # half a binary frame: wait for the rest
    assert len(host.send(b"\x00\xdc\x1e")) == 34
    assert host.send(b"\xff") == b""  # garbage gets no reply (PART 4 item 11)


# -- coordinated motion ------------------------------------------------------------------------


def test_profile_is_smooth_and_hits_the_limits() -> None:
    for sin2 in (False, True):
        prof = Profile.plan([40.0, 10.0], [40.0, 40.0], [100.0, 100.0], sin2=sin2)
        ts = np.linspace(0.0, prof.duration, 2001)
        frac = np.array([prof.fraction(t) for t in ts])
        rate = np.array([prof.rate(t) for t in ts])
        assert frac[0] == 0.0 and frac[-1] == 1.0 and np.all(np.diff(frac) >= 0.0)
        assert np.trapezoid(rate, ts) == pytest.approx(1.0, abs=1e-5)
        assert 40.0 * rate.max() == pytest.approx(40.0)  # the leading axis cruises at v
        accel = np.diff(40.0 * rate) / np.diff(ts)
        assert np.abs(accel).max() == pytest.approx(100.0, rel=1e-3)  # … and ramps at a
    assert Profile.plan([40.0], [40.0], [100.0], sin2=False).duration == pytest.approx(1.4)
    assert Profile.plan([40.0], [40.0], [100.0], sin2=True).duration == pytest.approx(
        1.0 + math.pi / 2 * 0.4
    )
    assert Profile.plan([4.0], [40.0], [100.0], sin2=False).duration == pytest.approx(0.4)
    assert Profile.plan([0.0], [0.0], [0.0], sin2=True).duration == 0.0


@pytest.mark.parametrize("vp", [0, 1])
def test_m_moves_all_axes_together_within_their_limits(vp: int) -> None:
    host = Host()
    start = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    goal = (30.0, -40.0, 10.0, 0.0, 25.0, 0.0, -5.0)
    v = (40.0, 40.0, 10.0, 40.0, 60.0, 40.0, 40.0)
    a = (100.0, 150.0, 30.0, 100.0, 100.0, 100.0, 100.0)
    duration = targets_move(host, goal, vp=vp, v=v, a=a)
    dist = [g - s for g, s in zip(goal, start, strict=True)]
    planned = Profile.plan(dist, v, a, sin2=vp == 0).duration
    assert duration == pytest.approx(planned, abs=1e-3) and duration >= planned
    assert host.values("get_duration") == pytest.approx((duration,))
    # STATE reads 1 for the moving axes as soon as M= is out (PART 4 item 6).
    assert host.values("state") == (1, 1, 1, 0, 1, 0, 1)
    assert host.binary(BinaryCommand.STATE).values == (1, 1, 1, 0, 1, 0, 1)
    t0 = host.now
    trace = [(t0, start), *host.run(t0 + duration + 0.5)]
    times = np.array([t for t, _ in trace])
    pos = np.array([p for _, p in trace])
    assert np.all(np.diff(times) <= TICK + 1e-12)  # ticks while moving
    assert times[-1] == pytest.approx(t0 + planned)  # the last step lands exactly on T
    vel = np.diff(pos, axis=0) / np.diff(times)[:, None]
    acc = np.diff(vel, axis=0) / ((times[2:] - times[:-2]) / 2)[:, None]
    for i in range(NUM_AXES):
        steps = np.diff(pos[:, i]) * np.sign(dist[i])
        assert np.all(steps >= -1e-12), f"axis {i} not monotonic"
        assert np.abs(vel[:, i]).max() <= v[i] * (1 + 1e-6)
        assert np.abs(acc[:, i]).max() <= a[i] * 1.01
        # straight line in joint space: every axis covers the same share at the same time
        if dist[i]:
            share = (pos[:, i] - start[i]) / dist[i]
            assert share == pytest.approx((pos[:, 1] - start[1]) / dist[1], abs=1e-9)
    assert pos[-1] == pytest.approx(goal)
    assert host.values("pos") == pytest.approx(goal, abs=1e-3)
    assert host.values("state") == (0,) * 7
    assert host.values("vel") == (0,) * 7 and host.values("rvel") == (0,) * 7
    assert host.emu.next_wakeup(host.now) is None


def test_m_plans_from_the_actual_angles_and_cruises_at_v() -> None:
    host = Host()
    duration = targets_move(host, (0, 20, 0, 0, 0, 0, 0), vp=1)
    host.later(duration)
    duration = targets_move(host, (0, 20, 0, -20, 0, 0, 0), vp=1)  # axis 1 is there already
    assert duration == pytest.approx(Profile.plan([20], [40], [100], sin2=False).duration, 1e-3)
    assert host.values("state") == (0, 0, 0, 1, 0, 0, 0)
    host.later(duration / 2)
    pos = host.values("pos")
    assert pos[1] == pytest.approx(20.0, abs=1e-3) and pos[3] == pytest.approx(-10.0, abs=1e-3)
    assert host.ask("rvel(3)").values == pytest.approx((-40.0,))  # cruising at v


def _stream(host: Host, step: float, n: int, period: float, *, vp: int) -> np.ndarray:
    """A host streaming targets: every ``period`` s a new target ``step`` beyond the actual
    angle of axis 1, with ``p`` and ``m`` (as the rolling loop does). Returns (t, pos, rvel)."""
    targets_move(host, host.values("pos"), vp=vp, a=(400.0,) * 7)
    rows = []
    for _ in range(n):
        pos = host.values("pos")
        goal = list(pos)
        goal[1] += step
        host.ask(f"p={vec(goal)}")
        host.values("m")
        # the scripted world's joints follow their references exactly
        rows += [(t, p[1], p[1]) for t, p in host.later(period)]
    return np.array(rows)


@pytest.mark.parametrize("vp", [0, 1])
def test_m_mid_move_replans_from_the_current_velocity(vp: int) -> None:
    """One target per 33 ms frame, each 0.25° ahead: the axis keeps moving instead of starting
    every move from rest (which took ≈63 ms per 0.25° step at 400 °/s²)."""
    host = Host()
    period, step, n = 1 / 30, 0.25, 40
    rows = _stream(host, step, n, period, vp=vp)
    t, ref = rows[:, 0], rows[:, 2]
    assert np.all(np.diff(ref) >= -1e-9)  # never backs off
    vel = np.diff(ref) / np.diff(t)
    acc = np.diff(vel) / ((t[2:] - t[:-2]) / 2)
    assert np.abs(acc).max() <= 400.0 * 1.05  # within a (finite differences straddle replans)
    # steady state: the reference velocity never drops to 0 between commands
    late = vel[len(vel) // 2 :]
    assert late.min() > 0.3 * late.mean() > 0.0
    assert late.mean() > 0.5 * step / period  # most of one step per period
    assert host.values("state")[1] == 1  # still positioning: the last move runs
    (rest,) = host.values("get_duration")
    host.later(rest + 0.05)
    assert host.values("state") == (0,) * 7 and host.values("rvel") == (0,) * 7


def test_m_mid_move_reversal_stays_within_the_acceleration() -> None:
    host = Host()
    duration = targets_move(host, (0, 20, 0, 0, 0, 0, 0), vp=1, a=(100.0,) * 7)
    host.later(duration / 2)  # cruising at +40 °/s
    assert host.ask("rvel(1)").values == pytest.approx((40.0,))
    here = host.values("pos")[1]
    host.ask(f"p={vec((0, here - 5, 0, 0, 0, 0, 0))}")
    (back,) = host.values("m")
    t0 = host.now
    t, ref = np.array([(t0, here), *((tt, p[1]) for tt, p in host.later(back + 0.1))]).T
    keep = np.concatenate([[True], np.diff(t) > 1e-9])
    t, ref = t[keep], ref[keep]
    vel = np.diff(ref) / np.diff(t)
    assert vel[0] == pytest.approx(40.0, rel=0.05)  # continuous across the replan
    assert np.abs(np.diff(vel) / ((t[2:] - t[:-2]) / 2)).max() <= 100.0 * 1.02
    assert ref.max() > here + 2.0  # it had to brake first: overshoot, then come back
    assert ref[-1] == pytest.approx(here - 5.0, abs=1e-6)
    assert host.values("state") == (0,) * 7


def test_stop_halts_the_move_where_it_is() -> None:
    host = Host()
    duration = targets_move(host, (0, 60, 0, 0, 0, 0, 0))
    host.later(duration / 2)
    assert host.send(b"stop\r\n") == b"STOP=\r\n"
    halted = host.values("pos")
    assert 10.0 < halted[1] < 50.0
    assert host.values("state") == (0,) * 7
    assert host.emu.next_wakeup(host.now) is None
    host.later(2.0)
    assert host.values("pos") == halted
    (rest,) = host.values("m")  # the targets are still set: m finishes the move
    assert 0.0 < rest < duration
    host.later(rest)
    assert host.values("pos")[1] == pytest.approx(60.0, abs=1e-3)


def test_selgrip_and_grip_move_to_the_grasp_and_ignore_stop() -> None:
    host = Host()
    reply = host.ask("selgrip=1")
    duration, gid = reply.values
    assert gid == 1 and duration > 0.0
    assert host.values("state")[1] == 1
    host.send(b"stop\r\n")  # does not interrupt selgrip/grip (§2.4)
    assert host.values("state")[1] == 1
    host.later(duration)
    assert host.values("pos") == pytest.approx(DEFAULT_GRASPS[1].pose(0.0), abs=1e-3)
    duration, close = host.values("grip=0.1,20")
    assert close == pytest.approx(0.1)
    host.later(duration)
    # old firmware's grip vector for grip=0.1 after selgrip=1: 0, -66.8, 66.8, …
    assert host.values("pos") == pytest.approx((0, -66.8, 66.8, -66.8, 66.8, -66.8, 66.8), abs=1e-3)
    assert host.values("p") == (0,) * 7  # targets untouched


# -- velocity controllers ----------------------------------------------------------------------


def test_con1_moves_at_the_target_velocity_even_after_power_off() -> None:
    host = Host()
    assert host.values("con=1") == (1,)
    assert host.values("v") == (0,) * 7
    host.ask("power=0,0,0,0,0,0,0")
    host.ask("v=0,10,0,-20,0,0,0")  # the host never sends power=1 (PART 4 item 5)
    assert host.values("state") == (6, 2, 6, 2, 6, 6, 6)
    assert host.values("power") == (0, 1, 0, 1, 0, 0, 0)
    assert host.values("rvel") == (0, 10, 0, -20, 0, 0, 0)
    host.later(1.0)
    pos = host.values("pos")
    assert pos[1] == pytest.approx(10.0, abs=1e-3) and pos[3] == pytest.approx(-20.0, abs=1e-3)
    assert host.values("vel")[1] == pytest.approx(10.0, abs=1e-6)
    host.ask("v=0,0,0,0,0,0,0")
    assert host.values("state") == (6, 0, 6, 0, 6, 6, 6)
    assert host.emu.next_wakeup(host.now) is None
    host.later(1.0)
    assert host.values("pos")[1] == pytest.approx(10.0, abs=1e-3)


def test_an_axis_powered_off_and_on_in_a_velocity_mode_holds_still() -> None:
    """`power=0` then `power=1` (a host's e-stop and release) does not drive the axis off at
    the velocity it had before: enabling an axis makes it hold where it is."""
    host = Host()
    host.ask("con=1")
    host.ask("v=0,0,0,0,0,0,30")
    host.later(0.5)
    host.ask("power=0,0,0,0,0,0,0")
    assert host.values("v")[6] == 0.0
    host.ask("power=1,1,1,1,1,1,1")
    held = host.values("pos")[6]
    assert held == pytest.approx(15.0, abs=0.5)
    host.later(1.0)
    assert host.values("pos")[6] == pytest.approx(held, abs=1e-3)
    assert host.values("state")[6] == 0


def test_con2_ramps_with_the_acceleration() -> None:
    host = Host()
    host.ask("con=2")
    host.ask("a(1)=20")
    host.ask("v(1)=10")
    assert host.values("state")[1] == AxisState.SPEED_MODE
    host.later(0.25)
    assert host.values("rvel")[1] == pytest.approx(5.0, abs=1e-6)
    assert host.values("pos")[1] == pytest.approx(0.625, abs=1e-3)
    host.later(0.75)
    assert host.values("rvel")[1] == pytest.approx(10.0)
    assert host.values("pos")[1] == pytest.approx(2.5 + 5.0, abs=1e-3)
    host.ask("v(1)=0")  # ramps down over 0.5 s, still speed mode meanwhile
    host.later(0.25)
    assert host.values("state")[1] == AxisState.SPEED_MODE
    host.later(0.5)
    assert host.values("state")[1] == AxisState.IDLE
    assert host.values("pos")[1] == pytest.approx(7.5 + 2.5, abs=1e-3)


def test_velocity_mode_stops_at_the_angle_limit() -> None:
    host = Host()
    host.ask("con=1")
    host.ask("v(1)=140")
    host.later(1.0)
    assert host.values("pos")[1] == pytest.approx(90.0)
    assert host.values("state")[1] == AxisState.LIMITS_REACHED
    assert host.emu.next_wakeup(host.now) is None
    host.ask("v(1)=-140")  # back out
    assert host.values("state")[1] == AxisState.SPEED_MODE


def test_tpap_and_tvav_set_targets_and_return_actuals() -> None:
    host = Host()
    assert host.values(f"tpap={SEVEN}") == (0,) * 7  # actual angles, not the targets
    assert host.values("p") == (10, -20, 30, -40, 50, -60, 70)
    host.later(host.values("m")[0])
    assert host.values("tpap=0,0,0,0,0,0,0") == pytest.approx((10, -20, 30, -40, 50, -60, 70))
    host.ask("con=1")
    assert host.values("tvav=0,5,0,0,0,0,-5") == (0,) * 7  # actual velocities: still at rest
    host.later(0.1)
    assert host.values("tvav=0,5,0,0,0,0,-5") == pytest.approx((0, 5, 0, 0, 0, 0, -5))
    assert host.values("v") == (0, 5, 0, 0, 0, 0, -5)


# -- binary ------------------------------------------------------------------------------------


@pytest.mark.parametrize("crc", [True, False])
@pytest.mark.parametrize("keyword", sorted(BINARY_COMMANDS))
def test_binary_get_matches_ascii(keyword: str, crc: bool) -> None:
    host = Host()
    host.ask(f"p={SEVEN}")
    host.later(host.values("m")[0] / 3)
    reply = host.binary(BINARY_COMMANDS[keyword], crc=crc)
    assert reply.ok and reply.with_crc == crc
    assert reply.values == pytest.approx(host.values(keyword), abs=1e-3)


def test_binary_sets_and_errors() -> None:
    host = Host()
    # The worked example of §2.6: get actual angles 83 03 00 DC 1E → 34 bytes 83 20 07 00 ….
    raw = host.send(bytes.fromhex("830300dc1e"))
    assert len(raw) == 34 and raw[:4] == bytes.fromhex("83200700")
    targets = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    assert host.send(encode_binary_request(BinaryCommand.P, targets))[:4] == bytes.fromhex(
        "85200700"
    )
    assert host.values("p") == targets
    assert host.binary(BinaryCommand.V, (20.0,) * 7, crc=False).values == (20.0,) * 7
    bad = host.binary(BinaryCommand.P, (0, 0, 0, 0, 0, 0, 95.0))
    assert bad.status == SdhError.RANGE_ERROR and bad.values == ZEROS
    assert host.binary(BinaryCommand.P, (math.nan,) * 7).status == SdhError.RANGE_ERROR
    assert host.values("p") == targets  # unchanged
    assert host.binary(BinaryCommand.POS, ZEROS).status == SdhError.NO_PARAMS_EXPECTED
    assert host.binary(BinaryCommand.VER).status == SdhError.CMD_UNKNOWN  # not one of the 11
    host.values("m")
    assert host.binary(BinaryCommand.POWER, ZEROS).values == ZEROS  # how SDHLibrary closes
    assert host.binary(BinaryCommand.STATE).values == (6,) * 7
    assert host.emu.stats.binary == 9 and host.emu.stats.errors == 4


def test_binary_request_with_a_bad_crc_gets_a_crc_error_status() -> None:
    host = Host()
    frame = bytearray(encode_binary_request(BinaryCommand.P, (0, 45, 0, 0, 0, 0, 0)))
    frame[-1] ^= 0xFF
    raw = host.send(bytes(frame))
    reply = BinaryReply.decode(raw, crc=True)
    assert len(raw) == 34 and reply.status == SdhError.CRC_ERROR
    assert host.values("p") == (0,) * 7  # the frame was dropped
    assert host.binary(BinaryCommand.POS).ok  # and the line is still in step


# -- blocked axes, power -----------------------------------------------------------------------


@pytest.mark.parametrize(("sign", "cw", "state"), [(1, True, 4), (-1, True, 5), (1, False, 5)])
def test_an_axis_pressing_an_obstacle_is_blocked_and_its_reference_stops(
    sign: int, cw: bool, state: int
) -> None:
    world = ObstacleWorld(axis=1, lo=-20.0, hi=20.0)
    host = Host(Sdh2Emulator(world, options=Sdh2Options(positive_is_cw=cw)))
    duration = targets_move(host, (0, 40 * sign, 0, 30, 0, 0, 0), vp=1)
    host.later(duration * 0.9)
    states = host.values("state")
    assert states[1] == state and states[3] == AxisState.POSITIONING
    assert host.values("pos")[1] == pytest.approx(20.0 * sign)
    (reference,) = host.ask("rvel(1)").values
    assert reference == 0.0
    stalled = host.emu.reference_deg[1]
    assert 1.0 < abs(stalled) - 20.0 < 1.5  # one margin plus at most one tick of motion
    host.later(duration)
    assert host.emu.reference_deg[1] == stalled  # still pressing, no further
    assert host.values("state") == (0, state, 0, 0, 0, 0, 0)
    assert host.values("pos")[3] == pytest.approx(30.0)
    world.hi, world.lo = math.inf, -math.inf  # the obstacle goes away: the block stays latched
    host.later(0.5)
    assert host.values("state")[1] == state
    host.later(host.values("m")[0])  # until the next m
    assert host.values("pos")[1] == pytest.approx(40.0 * sign)


def test_velocity_mode_block_holds_without_creeping_and_releases_on_reversal() -> None:
    world = ObstacleWorld(axis=1, hi=10.0)
    host = Host(Sdh2Emulator(world))
    host.ask("con=1")
    host.ask("v(1)=20")
    host.later(1.0)
    assert host.values("state")[1] == AxisState.CW_BLOCKED
    assert host.emu.next_wakeup(host.now) is None  # nothing moves
    stalled = host.emu.reference_deg[1]
    host.ask("v(1)=20")  # the same push again must not creep the reference forwards
    host.later(0.5)
    assert host.emu.reference_deg[1] == stalled
    host.ask("v(1)=-20")  # pulling away releases it
    assert host.values("state")[1] == AxisState.SPEED_MODE
    host.later(0.5)
    assert host.values("pos")[1] == pytest.approx(stalled - 10.0, abs=1e-3)
    host.ask("v(1)=20")
    host.later(1.0)
    assert host.values("state")[1] == AxisState.CW_BLOCKED
    world.hi = math.inf  # the obstacle gives way: the joint catches up and moves on
    host.later(0.01)
    assert host.values("state")[1] == AxisState.SPEED_MODE
    host.later(0.5)
    assert host.values("pos")[1] > 15.0


def test_power_off_reads_disabled_and_m_still_moves() -> None:
    host = Host(Sdh2Emulator(ScriptedWorld(SHAPES), options=Sdh2Options(initially_powered=True)))
    assert host.values("state") == (0,) * 7
    host.ask("power=0,0,0,0,0,0,0")
    assert host.values("state") == (6,) * 7
    host.ask("p=0,30,0,0,0,0,0")
    (duration,) = host.values("m")
    assert duration > 0.0
    assert host.values("state") == (0, 1, 0, 0, 0, 0, 0)
    assert host.values("power") == (1,) * 7
    host.later(duration)
    assert host.values("pos")[1] == pytest.approx(30.0)
    host.ask("power(1)=0")  # limp: the joint stays where the world leaves it
    host.later(1.0)
    assert host.values("pos")[1] == pytest.approx(30.0)
    assert host.values("state")[1] == AxisState.DISABLED


def test_con_resets_and_limits_narrow() -> None:
    host = Host()
    host.ask("v=10,10,10,10,10,10,10")
    host.ask("a=50,50,50,50,50,50,50")
    host.ask(f"p={SEVEN}")
    host.ask("con=0")
    assert host.values("v") == (40,) * 7 and host.values("a") == (100,) * 7
    assert host.values("p") == (0,) * 7  # CPP SetController: targets 0 after con=0
    host.ask(f"p={SEVEN}")
    assert host.values("p_max=80,80,15,80,80,80,80") == (80, 80, 15, 80, 80, 80, 80)
    assert host.values("p") == (10, -20, 15, -40, 50, -60, 70)  # clipped into the new range
    assert host.error("p(2)=16") == SdhError.RANGE_ERROR
    assert host.error("p_min(2)=20") == SdhError.RANGE_ERROR  # min above max


# -- connections, determinism, options ---------------------------------------------------------


def test_state_and_motion_survive_a_disconnect() -> None:
    host = Host()
    duration = targets_move(host, (0, 45, 0, 0, 0, 0, 0))
    host.send(b"ve")  # half a command, then the host goes away
    host.emu.disconnected(host.now + 0.1)
    host.now += duration + 1.0
    host.emu.connected(host.now)
    assert host.send(b"r\r\n") == b"E13\r\n"  # the partial line was dropped: "r" alone
    assert host.values("pos")[1] == pytest.approx(45.0)  # it kept moving meanwhile
    assert host.values("state") == (0,) * 7 and host.values("con") == (0,)


def test_long_silence_is_caught_up_in_bounded_steps() -> None:
    world = ObstacleWorld()
    emu = Sdh2Emulator(world, options=Sdh2Options(max_catchup_steps=100))
    host = Host(emu)
    host.ask("con=1")
    host.ask("v(1)=0.01")  # 3 h to the limit
    calls = len(world.calls)
    assert host.values("pos") == (0,) * 7  # same now: no new world step
    host.now += 3600.0
    assert host.values("pos")[1] == pytest.approx(36.0)
    assert len(world.calls) - calls <= 102
    assert world.calls == sorted(world.calls)


def test_the_same_inputs_give_the_same_bytes_and_world_calls() -> None:
    def script() -> tuple[bytes, list[float]]:
        world = ObstacleWorld(axis=3, lo=-25.0)
        host = Host(Sdh2Emulator(world))
        out = b""
        for line in (b"p=20,30,10,-40,5,0,0\r\n", b"m\r\n", b"con=2\r\n", b"v(2)=30\r\n"):
            out += host.send(line)
            host.later(0.37)
            out += host.send(b"pos\r\nstate\r\n" + encode_binary_request(BinaryCommand.VEL))
        return out, world.calls

    assert script() == script()


def test_options_are_validated() -> None:
    with pytest.raises(ValueError):
        Sdh2Options(min_angle_deg=(0.0,) * 6)
    with pytest.raises(ValueError):
        Sdh2Options(tick_s=0.0)
    with pytest.raises(ValueError):
        Sdh2Options(temperatures_c=(1.0,) * 7)
    with pytest.raises(ValueError):
        Sdh2Options(min_angle_deg=(10.0,) * 7, max_angle_deg=(0.0,) * 7)
    with pytest.raises(ValueError):
        Grasp((0.0,) * 7, (0.0,) * 6)


# -- end to end --------------------------------------------------------------------------------

Conn = tuple[asyncio.StreamReader, asyncio.StreamWriter]


@contextlib.asynccontextmanager
async def connect(url: str) -> AsyncIterator[Conn]:
    reader, writer = await serial_asyncio.open_serial_connection(url=url, baudrate=DEFAULT_BAUD)
    try:
        yield reader, writer
    finally:
        writer.close()
        with contextlib.suppress(serial.SerialException, ConnectionError):
            await writer.wait_closed()


async def command(conn: Conn, line: str) -> Reply:
    reader, writer = conn
    writer.write(line.encode("ascii") + b"\r\n")
    raw = await asyncio.wait_for(reader.readline(), 5.0)
    (reply,) = ReplyParser().feed(raw)
    assert isinstance(reply, Reply), (line, reply)
    return reply


async def binary(conn: Conn, cmd: BinaryCommand, crc: bool,
                 values: Sequence[float] | None = None) -> BinaryReply:  # fmt: skip
    reader, writer = conn
    writer.write(encode_binary_request(cmd, values, with_crc=crc))
    raw = await asyncio.wait_for(reader.readexactly(binary_reply_size(crc)), 5.0)
    reply = BinaryReply.decode(raw, crc=crc)
    assert reply.ok and reply.cmd == cmd
    return reply


async def sdhlibrary_open(conn: Conn) -> None:
    """SDHLibrary's open sequence (§2.8 step 1)."""
    reader, writer = conn
    writer.write(b" \r\n")
    with contextlib.suppress(TimeoutError):
        stray = await asyncio.wait_for(reader.read(256), 0.1)
        pytest.fail(f"reply to the blank line: {stray!r}")
    assert (await command(conn, "ver")).text == "0.0.3.3"
    assert (await command(conn, "ver")).text == "0.0.3.3"
    assert len((await command(conn, "vlim")).values) == 7
    assert len((await command(conn, "alim")).values) == 7
    assert (await command(conn, "con")).values == (0,)


async def move_and_wait(conn: Conn, crc: bool, goal: Sequence[float]) -> float:
    """con=0, binary v and p, m, then WaitAxis-style polling; returns T after checking it."""
    loop = asyncio.get_running_loop()
    await command(conn, "con=0")
    await binary(conn, BinaryCommand.V, crc, (80.0,) * 7)
    await binary(conn, BinaryCommand.P, crc, goal)
    started = loop.time()
    (duration,) = (await command(conn, "m")).values
    polls = 0
    while AxisState.POSITIONING in (await binary(conn, BinaryCommand.STATE, crc)).values:
        polls += 1
    assert polls > 0  # STATE read 1 right after M= (PART 4 item 6)
    assert loop.time() - started >= duration - 0.02  # lower bound only
    pos = (await binary(conn, BinaryCommand.POS, crc)).values
    assert pos == pytest.approx(goal, abs=1e-3)
    return duration


async def test_sdhlibrary_session_over_a_pty() -> None:
    async with PtyEndpoint(Sdh2Emulator(ScriptedWorld(SHAPES))) as ep, connect(ep.url) as conn:
        await sdhlibrary_open(conn)
        await move_and_wait(conn, True, (20.0, -15.0, 10.0, 0.0, 5.0, -10.0, 0.0))
        for _ in range(20):  # binary get-pos round trips stay in step
            await binary(conn, BinaryCommand.POS, True)
        assert (await command(conn, "state")).values == (0,) * 7
        await binary(conn, BinaryCommand.POWER, True, ZEROS)  # how the C++ host closes
        assert (await command(conn, "state")).values == (6,) * 7


async def test_sdhlibrary_sessions_over_tcp_keep_the_hand_moving() -> None:
    emu = Sdh2Emulator(ScriptedWorld(SHAPES))
    goal = (0.0, 30.0, 0.0, -30.0, 0.0, 0.0, 0.0)
    async with TcpEndpoint(emu) as ep:
        async with connect(ep.url) as conn:
            await sdhlibrary_open(conn)
            await move_and_wait(conn, False, (10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            for _ in range(20):  # TCP: binary frames without CRC, 32-byte replies
                await binary(conn, BinaryCommand.POS, False)
            await binary(conn, BinaryCommand.P, False, goal)
            loop = asyncio.get_running_loop()
            started = loop.time()
            (duration,) = (await command(conn, "m")).values
        async with connect(ep.url) as conn:  # the next program run, while the hand moves
            await sdhlibrary_open(conn)
            states = (await binary(conn, BinaryCommand.STATE, False)).values
            assert states == (1, 1, 0, 1, 0, 0, 0)  # axis 0 returns from 10°
            while AxisState.POSITIONING in (await binary(conn, BinaryCommand.STATE, False)).values:
                pass
            assert loop.time() - started >= duration - 0.02  # lower bound only
            assert (await binary(conn, BinaryCommand.POS, False)).values == pytest.approx(
                goal, abs=1e-3
            )
    assert ep.stats.connections == 2
