"""DSACON32m emulator: firmware behaviour on a virtual line, then a pyserial host on real links.

Unit tests drive the emulator directly with chosen ``now`` values, the way an endpoint does (one
whole packet at a time, each taking its 115200-baud line time), and decode everything it sends
with the codec. The end-to-end tests run SDHLibrary's open sequence and a push stream over a real
pty and a real TCP socket; there, timing assertions are lower bounds only.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
from collections import deque
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
import serial
import serial_asyncio

from sdh2svc.config import Settings
from sdh2svc.protocol.dsa import (
    BootNoise,
    ControllerInfo,
    DescriptorKind,
    DescriptorString,
    DsaError,
    ErrorReply,
    Event,
    Frame,
    MatrixInfo,
    MatrixMask,
    Packet,
    PacketId,
    PacketParser,
    SensitivityInfo,
    SensorInfo,
    ThresholdInfo,
    configure_acquisition,
    decode_frame_payload,
    encode_packet,
    get_sensitivity_info,
    get_threshold,
    loop,
    query_controller_info,
    query_controller_state,
    query_matrix_info,
    query_sensor_info,
    read_descriptor_string,
    read_matrix_mask,
    set_sensitivity,
    set_threshold,
)
from sdh2svc.sim.dsacon import BOOT_NOISE, DsaconEmulator, DsaconOptions
from sdh2svc.sim.endpoint import DEFAULT_BAUD, Device, PtyEndpoint, TcpEndpoint
from sdh2svc.sim.world import Pattern, ScriptedWorld

SHAPES = ((14, 6), (13, 6)) * 3
NB_CELLS = 486
BYTE_TIME = 10 / DEFAULT_BAUD
ACQ = PacketId.CONFIGURE_DATA_ACQUISITION
STOP = configure_acquisition(acquire=False, framerate=0)
PULL = configure_acquisition(acquire=True, framerate=0)


def push(rate: int = 30, rle: bool = True) -> bytes:
    return configure_acquisition(acquire=True, framerate=rate, rle=rle)


def stairs(now: float) -> np.ndarray:
    """Steps of 20 counts (runs of 20 cells) rising to 280 and repeating, at every instant."""
    return ((np.arange(NB_CELLS) % 300) // 20 * 20).astype(np.float64)


def emulator(pattern: Pattern | None = None, **options: Any) -> DsaconEmulator:
    return DsaconEmulator(ScriptedWorld(SHAPES, pattern), options=DsaconOptions(**options))


class Line:
    """A virtual serial line: asks the emulator for packets like an endpoint, on a fake clock."""

    def __init__(self, emu: DsaconEmulator, now: float = 0.0) -> None:
        self.emu = emu
        self.now = now
        self.parser = PacketParser()
        self.raw: list[tuple[float, bytes]] = []  # (start time, packet bytes)
        emu.connected(now)

    def send(self, *commands: bytes) -> None:
        self.emu.receive(b"".join(commands), self.now)

    def _take(self) -> list[tuple[float, Event]]:
        pkt = self.emu.next_packet(self.now)
        if pkt is None:
            return []
        start, self.now = self.now, self.now + len(pkt) * BYTE_TIME
        self.raw.append((start, pkt))
        events = self.parser.feed(pkt)
        assert events, f"{pkt!r} is not a whole packet"
        return [(start, e) for e in events]

    def drain(self) -> list[Packet]:
        """Every packet ready now and back to back after it."""
        out: list[Packet] = []
        while got := self._take():
            out += [e for _, e in got if isinstance(e, Packet)]
        return out

    def run(self, until: float) -> list[tuple[float, Event]]:
        """Serve the line up to ``until`` (packets started by then are included)."""
        out: list[tuple[float, Event]] = []
        while self.now <= until:
            if got := self._take():
                out += got
                continue
            wake = self.emu.next_wakeup(self.now)
            if wake is None or wake > until:
                break
            assert wake > self.now, "next_wakeup says now, but next_packet had nothing"
            self.now = wake
        self.now = max(self.now, until)
        return out

    def ask(self, *commands: bytes) -> list[Packet]:
        self.send(*commands)
        return self.drain()


def frames_of(events: list[tuple[float, Event]]) -> list[Frame]:
    return [
        decode_frame_payload(e.payload, NB_CELLS)
        for _, e in events
        if isinstance(e, Packet) and e.id == PacketId.FULL_FRAME
    ]


def pull_frame(line: Line) -> Frame:
    """Request one frame (pull mode): the ACK, then the frame."""
    ack, frame = line.ask(PULL)
    assert ack == Packet(ACQ, b"\x00\x00") and frame.id == PacketId.FULL_FRAME
    return decode_frame_payload(frame.payload, NB_CELLS)


def error_of(packet: Packet, pid: int) -> int:
    assert packet.id == pid and len(packet.payload) == 2
    return ErrorReply.decode(packet.payload).error_code


# -- identity and configuration ----------------------------------------------------------------


def test_is_a_device_and_validates_options() -> None:
    assert isinstance(emulator(), Device)
    bad: dict[str, Any]
    for bad in (
        {"max_fps": 0},
        {"boot_s": -1},
        {"factory_threshold": 5000},
        {"sw_version": 0x10000},
    ):
        with pytest.raises(ValueError):
            DsaconOptions(**bad)
    with pytest.raises(ValueError, match="static masks"):
        DsaconEmulator(ScriptedWorld(SHAPES), static_masks=[np.ones((13, 6))] * 6)


def test_controller_sensor_and_matrix_info() -> None:
    line = Line(emulator())
    ci, si, *mi = line.ask(
        query_controller_info(), query_sensor_info(), *map(query_matrix_info, range(6))
    )
    assert (ci.id, len(ci.payload), si.id, len(si.payload)) == (0x01, 18, 0x02, 12)
    info = ControllerInfo.decode(ci.payload)
    assert info.sw_version == 0x2900 and info.operable and not info.acquiring
    sensor = SensorInfo.decode(si.payload)
    assert sensor.nb_matrices == 6 and sensor.error_code == DsaError.E_SUCCESS
    for m, pkt in enumerate(mi):
        assert (pkt.id, len(pkt.payload)) == (0x0B, 52)
        mat = MatrixInfo.decode(pkt.payload)
        assert (mat.cells_y, mat.cells_x) == SHAPES[m]
        assert mat.texel_width == mat.texel_height == pytest.approx(3.4)
        assert mat.fullscale == 4095 and mat.feature_flags & 0x02
    assert len({MatrixInfo.decode(p.payload).uid for p in mi}) == 6
    custom = Line(emulator(texel_size_mm=3.0)).ask(query_matrix_info(5))
    assert MatrixInfo.decode(custom[0].payload).texel_width == pytest.approx(3.0)


def test_status_reports_acquisition_running() -> None:
    line = Line(emulator())
    line.ask(push())
    assert ControllerInfo.decode(line.ask(query_controller_info())[0].payload).acquiring
    line.ask(STOP)
    assert not ControllerInfo.decode(line.ask(query_controller_info())[0].payload).acquiring


@pytest.mark.parametrize(
    "command",
    [
        query_matrix_info(6),
        get_sensitivity_info(6),
        get_threshold(9),
        read_matrix_mask(6),
        read_descriptor_string(DescriptorKind.MATRIX, 7),
        set_sensitivity(6, 0.5),
        set_threshold(200, 10),
    ],
)
def test_matrix_index_out_of_range_is_rejected(command: bytes) -> None:
    (reply,) = Line(emulator()).ask(command)
    assert error_of(reply, command[3]) == DsaError.E_INDEX_OUT_OF_BOUNDS


# -- sensitivity and threshold -----------------------------------------------------------------


def sens_of(line: Line, m: int) -> SensitivityInfo:
    (reply,) = line.ask(get_sensitivity_info(m))
    assert (reply.id, len(reply.payload)) == (0x12, 11)
    return SensitivityInfo.decode(reply.payload)


def thr_of(line: Line, m: int) -> int:
    (reply,) = line.ask(get_threshold(m))
    assert (reply.id, len(reply.payload)) == (0x14, 4)
    return ThresholdInfo.decode(reply.payload).threshold


def test_sensitivity_get_set_all_and_reset() -> None:
    line = Line(emulator())
    info = sens_of(line, 0)
    assert (info.cur_sens, info.fact_sens, info.adjustable) == (0.5, 0.5, True)
    assert error_of(line.ask(set_sensitivity(2, 0.8))[0], 0x0F) == DsaError.E_SUCCESS
    assert sens_of(line, 2).cur_sens == pytest.approx(0.8)
    assert sens_of(line, 3).cur_sens == 0.5
    line.ask(set_sensitivity(0, 0.25, all_matrices=True))
    assert [sens_of(line, m).cur_sens for m in range(6)] == [0.25] * 6
    line.ask(set_sensitivity(4, 1.0, reset=True))
    assert [sens_of(line, m).cur_sens for m in range(6)] == [0.25] * 4 + [0.5, 0.25]


def test_threshold_get_set_all_and_reset() -> None:
    line = Line(emulator(factory_threshold=12))
    assert thr_of(line, 0) == 12
    assert error_of(line.ask(set_threshold(1, 4095))[0], 0x13) == DsaError.E_SUCCESS
    assert [thr_of(line, m) for m in range(3)] == [12, 4095, 12]
    line.ask(set_threshold(0, 150, all_matrices=True))
    assert line.emu.threshold == (150,) * 6
    line.ask(set_threshold(0, 0, all_matrices=True, reset=True))
    assert line.emu.threshold == (12,) * 6


@pytest.mark.parametrize(
    ("pid", "payload"),
    [
        (0x0F, struct.pack("<BBf", 0, 0, 1.5)),
        (0x0F, struct.pack("<BBf", 0, 0, -0.1)),
        (0x0F, struct.pack("<BBf", 2, 0, math.nan)),
        (0x13, struct.pack("<BBH", 0, 0, 4096)),
    ],
)
def test_out_of_range_values_are_rejected_and_ignored(pid: int, payload: bytes) -> None:
    line = Line(emulator())
    assert error_of(line.ask(encode_packet(pid, payload))[0], pid) == DsaError.E_RANGE_ERROR
    assert line.emu.sensitivity == (0.5,) * 6 and line.emu.threshold == (0,) * 6


def test_persistent_writes_get_no_reply_apply_and_survive_power_cycle() -> None:
    line = Line(emulator())
    replies = line.ask(
        set_sensitivity(1, 0.75, persistent=True),
        set_threshold(0, 300, all_matrices=True, persistent=True),
        set_threshold(0, 904, persistent=True),
        encode_packet(0x13, struct.pack("<BBH", 0x80, 1, 5000)),  # refused, and still silent
        get_threshold(1),
    )
    assert [r.id for r in replies] == [0x14]  # only the query is answered
    assert ThresholdInfo.decode(replies[0].payload).threshold == 300
    line.ask(set_sensitivity(1, 0.1), set_threshold(2, 7))  # temporary: until power cycle
    line.emu.power_on(line.now)
    assert sens_of(line, 1).cur_sens == pytest.approx(0.75)
    assert [thr_of(line, m) for m in range(3)] == [904, 300, 300]


def test_settings_survive_disconnect_and_a_push_stream_stops() -> None:
    line = Line(emulator())
    line.ask(set_sensitivity(3, 0.9), set_threshold(5, 99), push())
    line.run(0.2)
    line.emu.disconnected(line.now)
    line.emu.connected(line.now + 1.0)
    line.now += 1.0
    assert line.run(2.0) == []  # the stream ended with the host
    assert sens_of(line, 3).cur_sens == pytest.approx(0.9) and thr_of(line, 5) == 99


def test_stream_may_survive_disconnect_and_unsent_replies_are_dropped() -> None:
    line = Line(emulator(stream_survives_disconnect=True))
    line.ask(push())
    line.send(query_controller_info(), encode_packet(0x01)[:4])  # a reply pending, half a command
    line.emu.disconnected(line.now)
    line.emu.connected(line.now)
    line.send(query_sensor_info())
    events = line.run(line.now + 0.5)
    ids = [e.id for _, e in events if isinstance(e, Packet)]
    assert ids[0] == 0x02 and set(ids[1:]) == {0x00} and len(ids) >= 14


# -- matrix mask, descriptors, loop, state, errors ---------------------------------------------


def test_matrix_masks_static_from_layout_dynamic_all(cfg: Settings) -> None:
    layouts = [cfg.tactile.proximal, cfg.tactile.distal] * 3
    emu = DsaconEmulator(
        ScriptedWorld([(lay.rows, lay.cols) for lay in layouts], lambda now: np.full(486, 900.0)),
        static_masks=[lay.valid() for lay in layouts],
    )
    line = Line(emu)
    for m, lay in enumerate(layouts):
        for dynamic in (False, True):
            (reply,) = line.ask(read_matrix_mask(m, dynamic))
            mask = MatrixMask.decode(reply.payload, lay.cells)
            assert reply.id == 0x04 and mask.error_code == DsaError.E_SUCCESS
            expected = np.ones((lay.rows, lay.cols), bool) if dynamic else lay.valid()
            np.testing.assert_array_equal(mask.to_array(lay.cols, lay.rows), expected)
    assert not lay.valid().all()  # the distal pad really has absent cells
    present = np.concatenate([lay.valid().ravel() for lay in layouts])
    np.testing.assert_array_equal(pull_frame(line).texels, np.where(present, 900, 0))


def test_descriptor_loop_and_controller_state() -> None:
    line = Line(emulator(sensor_descriptor="unit 7"), now=2.5)
    asked_at = line.now  # 0x0A reports the clock when the command arrived
    sensor, matrix, bad, looped, state = line.ask(
        read_descriptor_string(DescriptorKind.SENSOR, 0),
        read_descriptor_string(DescriptorKind.MATRIX, 1),
        encode_packet(0x05, bytes([2, 0])),
        loop(),
        query_controller_state(),
    )
    assert DescriptorString.decode(sensor.payload).text == "unit 7"
    assert DescriptorString.decode(matrix.payload).text == "matrix 1 6x13"
    assert error_of(bad, 0x05) == DsaError.E_INVALID_PARAMETER
    assert error_of(looped, 0x06) == DsaError.E_SUCCESS
    assert state.id == 0x0A
    assert struct.unpack("<HBI", state.payload) == (0, 0x80, line.emu.clock_ms(asked_at))


@pytest.mark.parametrize(
    ("command", "code"),
    [
        (encode_packet(0x10), DsaError.E_CMD_UNKNOWN),
        (encode_packet(0x77, b"\x01\x02"), DsaError.E_CMD_UNKNOWN),
        (encode_packet(0x03, b"\x81\x00"), DsaError.E_CMD_NOT_ENOUGH_PARAMS),
        (encode_packet(0x0B, b"\x00\x00"), DsaError.E_CMD_FORMAT_ERROR),
        (encode_packet(0x01, b"\x00"), DsaError.E_CMD_FORMAT_ERROR),
    ],
)
def test_unknown_and_malformed_commands_get_an_error_under_their_id(
    command: bytes, code: DsaError
) -> None:
    line = Line(emulator())
    reply, info = line.ask(command, query_controller_info())
    assert error_of(reply, command[3]) == code
    assert info.id == 0x01  # and the link goes on
    unknown = code == DsaError.E_CMD_UNKNOWN  # decoded (as UnknownCommand), then refused
    assert line.emu.stats.errors == 1 and line.emu.stats.commands == 1 + unknown


@pytest.mark.parametrize("reply", [True, False])
def test_bad_host_crc_answered_or_ignored_as_configured(reply: bool) -> None:
    line = Line(emulator(crc_error_reply=reply))
    corrupt = bytearray(get_threshold(2))
    corrupt[-1] ^= 0x40
    replies = line.ask(bytes(corrupt), b"\x00\x17", query_controller_info())  # plus line noise
    expected = [(0x14, DsaError.E_CHECKSUM_ERROR)] if reply else []
    assert [(r.id, ErrorReply.decode(r.payload).error_code) for r in replies[:-1]] == expected
    assert replies[-1].id == 0x01
    assert line.emu.stats.crc_errors == 1


def test_commands_split_across_receives_and_garbage_are_handled() -> None:
    line = Line(emulator())
    data = b"\x55\xaa" + query_matrix_info(3) + query_controller_info()
    for i in range(len(data)):
        line.send(data[i : i + 1])
    assert [p.id for p in line.drain()] == [0x0B, 0x01]


# -- acquisition -------------------------------------------------------------------------------


def test_pull_is_ack_then_exactly_one_frame() -> None:
    line = Line(emulator())
    line.send(PULL)
    events = line.run(5.0)
    assert [e.id for _, e in events] == [ACQ, PacketId.FULL_FRAME]  # type: ignore[union-attr]
    assert error_of(events[0][1], ACQ) == DsaError.E_SUCCESS  # type: ignore[arg-type]
    assert line.emu.next_wakeup(line.now) is None


def test_push_streams_at_the_cap_and_stop_is_acked_mid_stream() -> None:
    line = Line(emulator())
    line.send(push(rate=1))  # any rate > 0 means "as fast as you can" (~30 fps)
    events = line.run(1.0)
    assert events[0][1] == Packet(ACQ, b"\x00\x00")
    stamps = [f.timestamp_ms for f in frames_of(events)]
    assert 29 <= len(stamps) <= 31
    assert min(np.diff(stamps)) >= 33
    due = line.emu.next_wakeup(line.now)
    assert due is not None
    frame = line.emu.next_packet(due)  # a frame goes on the line…
    assert frame is not None and frame[3] == PacketId.FULL_FRAME
    line.now = due + len(frame) * BYTE_TIME / 2
    line.send(STOP)  # arrives while that frame is still going out
    after = line.run(line.now + 2.0)
    assert [e for _, e in after] == [Packet(ACQ, b"\x00\x00")]
    assert not line.emu.streaming


@pytest.mark.parametrize(
    ("honour", "rate", "cap", "fps"),
    [(False, 1, 30, 30), (True, 10, 30, 10), (True, 100, 30, 30), (False, 30, 20, 20)],
)
def test_push_rate_follows_the_options(honour: bool, rate: int, cap: int, fps: int) -> None:
    line = Line(emulator(honour_framerate=honour, max_fps=cap))
    line.send(push(rate))
    stamps = [f.timestamp_ms for f in frames_of(line.run(2.0))]
    assert abs(len(stamps) - 2 * fps) <= 1
    assert min(np.diff(stamps)) >= math.floor(1000 / fps)


def test_rle_flag_is_honoured_per_request() -> None:
    line = Line(emulator(stairs))
    plain, packed = (
        line.ask(configure_acquisition(acquire=True, framerate=0, rle=rle))[1]
        for rle in (False, True)
    )
    assert len(plain.payload) == 5 + 2 * NB_CELLS and plain.payload[4] == 0
    assert packed.payload[4] == 1 and len(packed.payload) < len(plain.payload)
    a, b = (decode_frame_payload(p.payload, NB_CELLS) for p in (plain, packed))
    np.testing.assert_array_equal(a.texels, b.texels)
    line.send(push(rle=False))
    assert all(not f.rle for f in frames_of(line.run(line.now + 0.3)))


@pytest.mark.parametrize(("breaks", "words"), [("none", 33), ("matrix", 36), ("row", 81)])
def test_rle_run_breaks_option(breaks: str, words: int) -> None:
    line = Line(emulator(lambda now: np.zeros(NB_CELLS), rle_breaks=breaks))
    frame = line.ask(PULL)[1]
    assert len(frame.payload) == 5 + 2 * words


def test_frames_follow_the_moving_world() -> None:
    world = ScriptedWorld(SHAPES)
    emu = DsaconEmulator(world)
    line = Line(emu)
    texels = []
    for t in (0.0, 0.5, 1.0):
        line.run(t)
        line.send(PULL)
        _, (sampled_at, frame) = line.run(t + 0.1)  # ACK, then the frame sampled as it goes out
        assert isinstance(frame, Packet) and frame.id == PacketId.FULL_FRAME
        texels.append(decode_frame_payload(frame.payload, NB_CELLS).texels)
        expected = world.tactile_frame(sampled_at, (0.5,) * 6, (0,) * 6)
        np.testing.assert_array_equal(texels[-1], expected)
    assert all(t.any() for t in texels)
    assert not np.array_equal(texels[0], texels[1]) and not np.array_equal(texels[1], texels[2])


def test_threshold_zeroes_low_cells_and_sensitivity_scales() -> None:
    line = Line(emulator(stairs))
    line.ask(set_threshold(0, 150), set_sensitivity(1, 1.0))
    frame = pull_frame(line)
    raw = stairs(0.0).astype(np.int64)
    m0, m1, rest = frame.texels[:84], frame.texels[84:162], frame.texels[162:]
    np.testing.assert_array_equal(m0, np.where(raw[:84] < 150, 0, raw[:84]))
    np.testing.assert_array_equal(m1, 2 * raw[84:162])
    np.testing.assert_array_equal(rest, raw[162:])


def test_timestamps_are_controller_ms_and_never_zero() -> None:
    line = Line(emulator(), now=100.0)
    line.run(100.25)
    frame = pull_frame(line)
    assert frame.timestamp_ms == 1000 + 250
    zero = Line(emulator(clock_offset_ms=0), now=5.0)
    assert pull_frame(zero).timestamp_ms == 1
    wrap = emulator(clock_offset_ms=2**32 - 10)
    wrap.power_on(0.0)
    assert [wrap.clock_ms(t) for t in (0.005, 0.010, 0.020)] == [2**32 - 5, 1, 10]


# -- boot --------------------------------------------------------------------------------------


def test_boot_is_deaf_and_mute_except_three_terminal_queries() -> None:
    line = Line(emulator(boot_s=8.0))
    line.run(1.0)
    line.send(query_controller_info(), PULL)  # nobody is listening yet
    events = line.run(7.99)
    assert [e for _, e in events] == [BootNoise()] * 3
    starts = [t for t, _ in line.raw]
    assert starts == pytest.approx([7.0, 7.41, 7.82])
    assert starts[-1] - starts[0] <= 0.85
    assert all(pkt == BOOT_NOISE == b"\x1b\x5b\x35\x6e" for _, pkt in line.raw)
    assert line.emu.stats.deaf_bytes == len(query_controller_info()) + len(PULL)
    line.run(8.0)
    assert [p.id for p in line.ask(query_controller_info())] == [0x01]


def test_boot_noise_nobody_heard_is_not_sent_late() -> None:
    emu = emulator(boot_s=8.0)
    emu.power_on(0.0)
    assert emu.next_wakeup(0.0) == pytest.approx(7.0)
    assert emu.next_packet(9.0) is None and emu.next_wakeup(9.0) is None


def test_statistics_count_frames_bytes_commands_and_errors() -> None:
    line = Line(emulator())
    line.send(PULL, encode_packet(0x42))
    line.run(1.0)
    stats = line.emu.stats
    assert (stats.frames, stats.commands, stats.errors, stats.packets) == (1, 2, 1, 3)
    assert stats.bytes == sum(len(p) for _, p in line.raw)


# -- end to end: pyserial-asyncio host on a real pty and a real TCP socket ---------------------


class DsaHost:
    """Just enough of SDHLibrary's cDSA (protocols.md §1.6-1.7): requests skip stray frames."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.parser = PacketParser()
        self.pending: deque[Packet] = deque()
        self.skipped_frames = 0

    async def packet(self, timeout: float = 3.0) -> Packet:
        while not self.pending:
            data = await asyncio.wait_for(self.reader.read(4096), timeout)
            assert data, "link closed"
            self.pending.extend(e for e in self.parser.feed(data) if isinstance(e, Packet))
        return self.pending.popleft()

    async def request(self, command: bytes) -> bytes:
        self.writer.write(command)
        while (pkt := await self.packet()).id != command[3]:
            assert pkt.id == PacketId.FULL_FRAME, f"unexpected {pkt}"
            self.skipped_frames += 1
        return pkt.payload

    async def flush(self, first_s: float = 1.0, rest_s: float = 0.05) -> int:
        """Discard input until silence (SDHLibrary: 1 s for the first byte); bytes discarded."""
        dropped = self.parser.buffered + sum(len(p.payload) + 8 for p in self.pending)
        self.pending.clear()
        self.parser = PacketParser()
        timeout = first_s
        with contextlib.suppress(TimeoutError):
            while data := await asyncio.wait_for(self.reader.read(4096), timeout):
                dropped += len(data)
                timeout = rest_s
        return dropped


@contextlib.asynccontextmanager
async def dsa_host(url: str) -> AsyncIterator[DsaHost]:
    reader, writer = await serial_asyncio.open_serial_connection(url=url, baudrate=DEFAULT_BAUD)
    try:
        yield DsaHost(reader, writer)
    finally:
        writer.close()
        with contextlib.suppress(serial.SerialException, ConnectionError):
            await writer.wait_closed()


async def open_sequence(host: DsaHost) -> int:
    """SDHLibrary's Open(): stop + ACK, flush, 0x01, 0x02, 0x0B per matrix; returns nb_cells."""
    assert ErrorReply.decode(await host.request(STOP)).ok
    assert await host.flush() == 0  # nothing follows the stop's ACK
    info = ControllerInfo.decode(await host.request(query_controller_info()))
    assert info.sw_version >= 0x1000 and not info.acquiring
    sensor = SensorInfo.decode(await host.request(query_sensor_info()))
    mats = [
        MatrixInfo.decode(await host.request(query_matrix_info(m)))
        for m in range(sensor.nb_matrices)
    ]
    return sum(m.nb_cells for m in mats)


@pytest.mark.parametrize("kind", ["pty", "tcp"])
async def test_sdhlibrary_open_push_and_stop_over_real_transports(kind: str) -> None:
    # The first host is killed mid-stream (no stop); the stream goes on, as on the real line.
    emu = DsaconEmulator(
        ScriptedWorld(SHAPES), options=DsaconOptions(stream_survives_disconnect=True)
    )
    endpoint = PtyEndpoint(emu) if kind == "pty" else TcpEndpoint(emu)
    loop_ = asyncio.get_running_loop()
    async with endpoint:
        async with dsa_host(endpoint.url) as killed:
            assert ErrorReply.decode(await killed.request(push(30))).ok
            assert (await killed.packet()).id == PacketId.FULL_FRAME

        async with dsa_host(endpoint.url) as host:
            await asyncio.sleep(0.2)  # let stale frames pile up before the open
            assert await open_sequence(host) == NB_CELLS
            assert host.skipped_frames >= 1

            assert ErrorReply.decode(await host.request(push(30))).ok
            frames: list[Frame] = []
            t_end = loop_.time() + 1.0
            while loop_.time() < t_end:
                pkt = await host.packet()
                assert pkt.id == PacketId.FULL_FRAME
                frames.append(decode_frame_payload(pkt.payload, NB_CELLS))
            assert len(frames) >= 15  # ~30 expected; lower bound only
            stamps = [f.timestamp_ms for f in frames]
            assert min(np.diff(stamps)) >= 33  # never above 30 fps by the controller's clock
            assert any(not np.array_equal(frames[0].texels, f.texels) for f in frames)

            assert ErrorReply.decode(await host.request(STOP)).ok
            assert await host.flush(first_s=0.3) == 0  # no frame after the stop's ACK
    assert emu.stats.errors == 0 and not emu.streaming
