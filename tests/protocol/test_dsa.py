"""Tests for the DSACON32m codec: golden bytes (protocols.md §1.2.2), layouts (§1.4), frames and
RLE (§1.5), geometry (§1.8), the packet parser (§1.2, §1.7), and property tests."""

from __future__ import annotations

import itertools
import math
import struct
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sdh2svc.protocol import dsa
from sdh2svc.protocol.crc import crc16
from sdh2svc.protocol.dsa import (
    SDH2_MATRIX_SHAPES,
    SDH2_NB_CELLS,
    BadCrc,
    BootNoise,
    ConfigureAcquisition,
    ControllerInfo,
    DescriptorKind,
    DescriptorString,
    DsaError,
    ErrorReply,
    Frame,
    FrameError,
    GarbageSkipped,
    GetSensitivityInfo,
    GetThreshold,
    Loop,
    MatrixInfo,
    MatrixMask,
    MatrixShape,
    Oversized,
    Packet,
    PacketId,
    PacketParser,
    ProtocolError,
    QueryControllerInfo,
    QueryControllerState,
    QueryMatrixInfo,
    QuerySensorInfo,
    ReadDescriptorString,
    ReadMatrixMask,
    SensitivityInfo,
    SensorInfo,
    SetSensitivity,
    SetThreshold,
    ThresholdInfo,
    UnknownCommand,
)

PROPERTY = settings(max_examples=150, deadline=None, derandomize=True, database=None)


def hx(text: str) -> bytes:
    return bytes.fromhex(text)


def parse_all(data: bytes, parser: PacketParser | None = None) -> list[dsa.Event]:
    return (parser or PacketParser()).feed(data)


def packets_of(events: list[dsa.Event]) -> list[Packet]:
    return [e for e in events if isinstance(e, Packet)]


# ---------------------------------------------------------------------------------------------
# Golden bytes, protocols.md §1.2.2 — every row, both directions
# ---------------------------------------------------------------------------------------------

# (encoder, golden bytes, id, payload, decoded command)
GOLDEN_COMMANDS = [
    pytest.param(
        dsa.query_controller_info, "AA AA AA 01 00 00", 0x01, b"", QueryControllerInfo(),
        id="query-controller",
    ),
    pytest.param(
        dsa.query_sensor_info, "AA AA AA 02 00 00", 0x02, b"", QuerySensorInfo(),
        id="query-sensor",
    ),
    *[
        pytest.param(
            lambda m=m: dsa.query_matrix_info(m), f"AA AA AA 0B 01 00 {m:02X} {crc}", 0x0B,
            bytes([m]), QueryMatrixInfo(m), id=f"query-matrix-{m}",
        )
        for m, crc in enumerate(["CB FB", "EA EB", "89 DB", "A8 CB", "4F BB", "6E AB"])
    ],
    pytest.param(
        lambda: dsa.configure_acquisition(acquire=False, framerate=0),
        "AA AA AA 03 03 00 01 00 00 2F 6A", 0x03, hx("01 00 00"),
        ConfigureAcquisition(acquire=False, framerate=0, rle=True, flags=0x01),
        id="stop",
    ),
    pytest.param(
        lambda: dsa.configure_acquisition(acquire=True, framerate=0),
        "AA AA AA 03 03 00 81 00 00 2F 68", 0x03, hx("81 00 00"),
        ConfigureAcquisition(acquire=True, framerate=0, rle=True, flags=0x81),
        id="pull-one-frame",
    ),
    pytest.param(
        lambda: dsa.configure_acquisition(acquire=True, framerate=1),
        "AA AA AA 03 03 00 81 01 00 7C 5C", 0x03, hx("81 01 00"),
        ConfigureAcquisition(acquire=True, framerate=1, rle=True, flags=0x81),
        id="push-rate-1",
    ),
    pytest.param(
        lambda: dsa.get_threshold(0), "AA AA AA 14 01 00 00 03 C1", 0x14, b"\x00",
        GetThreshold(0), id="get-threshold-0",
    ),
    pytest.param(
        lambda: dsa.get_sensitivity_info(0), "AA AA AA 12 01 00 00 8F DB", 0x12, b"\x00",
        GetSensitivityInfo(0), id="get-sensitivity-0",
    ),
    pytest.param(
        lambda: dsa.set_sensitivity(0, 0.5),
        "AA AA AA 0F 06 00 00 00 00 00 00 3F B0 B3", 0x0F, hx("00 00 00 00 00 3F"),
        SetSensitivity(0, 0.5), id="set-sensitivity-0.5",
    ),
    pytest.param(
        lambda: dsa.set_threshold(0, 150, all_matrices=True),
        "AA AA AA 13 04 00 02 00 96 00 05 C7", 0x13, hx("02 00 96 00"),
        SetThreshold(0, 150, all_matrices=True), id="set-threshold-150-all",
    ),
]  # fmt: skip


@pytest.mark.parametrize(("encoder", "golden", "pid", "payload", "command"), GOLDEN_COMMANDS)
def test_golden_command_encode_parse_decode(
    encoder: Callable[[], bytes], golden: str, pid: int, payload: bytes, command: dsa.Command
) -> None:
    wire = hx(golden)
    assert encoder() == wire
    events = parse_all(wire)
    assert events == [Packet(pid, payload)]
    assert dsa.decode_command(events[0]) == command
    assert dsa.encode_command(command) == wire


def test_golden_ack() -> None:
    wire = hx("AA AA AA 03 02 00 00 00 4B B9")
    assert dsa.encode_response(PacketId.CONFIGURE_DATA_ACQUISITION, ErrorReply()) == wire
    [pkt] = parse_all(wire)
    assert pkt == Packet(PacketId.CONFIGURE_DATA_ACQUISITION, b"\x00\x00")
    reply = ErrorReply.decode(pkt.payload)
    assert reply.ok and reply.error_code is DsaError.E_SUCCESS


GOLDEN_FRAME = hx("AA AA AA 00 47 00 34 12 00 00 01" + " 00 F0" * 32 + " 00 60 02 2A")


def test_golden_all_zero_rle_frame() -> None:
    assert len(GOLDEN_FRAME) == 79
    zeros = np.zeros(SDH2_NB_CELLS, dtype=np.uint16)
    payload = dsa.encode_frame_payload(0x1234, zeros, rle=True)
    assert dsa.encode_packet(PacketId.FULL_FRAME, payload) == GOLDEN_FRAME
    frame_obj = Frame(0x1234, True, zeros)
    assert dsa.encode_response(PacketId.FULL_FRAME, frame_obj) == GOLDEN_FRAME

    [pkt] = parse_all(GOLDEN_FRAME)
    assert pkt.id == PacketId.FULL_FRAME and len(pkt.payload) == 0x47
    frame = dsa.decode_frame_payload(pkt.payload, SDH2_NB_CELLS)
    assert frame.timestamp_ms == 0x1234 and frame.rle
    assert frame.texels.dtype == np.uint16 and frame.texels.shape == (SDH2_NB_CELLS,)
    assert not frame.texels.any()


def test_crc_check_value_and_remembered_crcs() -> None:
    """Short byte strings' CRCs are remembered: the same value by any path, also after the
    memory was cleared for being full."""
    from sdh2svc.protocol import crc

    assert crc16(b"123456789") == crc16(b"123456789") == 0x6EB4
    assert crc16(bytearray(b"123456789")) == crc16(memoryview(b"123456789")) == 0x6EB4
    assert crc16(b"6789", crc16(b"12345")) == 0x6EB4  # chained: not from the memory
    frames = [bytes([k & 0xFF, k >> 8, 7]) for k in range(crc._SEEN_MAX + 10)]
    assert [crc16(f) for f in frames] == [crc16(bytearray(f)) for f in frames]
    assert len(crc._SEEN) <= crc._SEEN_MAX
    assert crc16(b"123456789") == 0x6EB4


def test_crc_covers_id_length_payload_not_preamble() -> None:
    wire = dsa.query_matrix_info(5)
    assert int.from_bytes(wire[-2:], "little") == crc16(wire[3:-2])


# ---------------------------------------------------------------------------------------------
# Framing
# ---------------------------------------------------------------------------------------------


def test_encode_packet_crc_presence() -> None:
    assert dsa.encode_packet(0x06) == hx("AA AA AA 06 00 00")
    with_crc = dsa.encode_packet(0x06, crc_when_empty=True)
    assert with_crc[:6] == hx("AA AA AA 06 00 00") and len(with_crc) == 8
    assert int.from_bytes(with_crc[6:], "little") == crc16(hx("06 00 00"))


@pytest.mark.parametrize("pid", [-1, 0xAA, 0x100])
def test_encode_packet_rejects_bad_ids(pid: int) -> None:
    with pytest.raises(ValueError, match="packet id"):
        dsa.encode_packet(pid, b"x")


def test_encode_packet_rejects_oversized_payload() -> None:
    dsa.encode_packet(0, bytes(0xFFFF))  # the largest representable length is fine
    with pytest.raises(ValueError, match="u16"):
        dsa.encode_packet(0, bytes(0x10000))


# ---------------------------------------------------------------------------------------------
# Host-command encoders: validation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "call",
    [
        lambda: dsa.query_matrix_info(-1),
        lambda: dsa.query_matrix_info(256),
        lambda: dsa.get_threshold(300),
        lambda: dsa.get_sensitivity_info(-5),
        lambda: dsa.read_matrix_mask(256),
        lambda: dsa.read_descriptor_string(DescriptorKind.MATRIX, 999),
        lambda: dsa.read_descriptor_string(2, 0),
        lambda: dsa.set_sensitivity(0, 1.01),
        lambda: dsa.set_sensitivity(0, -0.1),
        lambda: dsa.set_sensitivity(0, math.nan),
        lambda: dsa.set_sensitivity(256, 0.5),
        lambda: dsa.set_threshold(0, 4096),
        lambda: dsa.set_threshold(0, -1),
        lambda: dsa.set_threshold(-1, 10),
        lambda: dsa.configure_acquisition(acquire=True, framerate=65536),
        lambda: dsa.configure_acquisition(acquire=True, framerate=-1),
        lambda: dsa.configure_acquisition(acquire=True, framerate=1, extra_flags=0x80),
        lambda: dsa.configure_acquisition(acquire=True, framerate=1, extra_flags=0x01),
    ],
)
def test_command_argument_validation(call: Callable[[], bytes]) -> None:
    with pytest.raises(ValueError, match=r"must"):
        call()


def test_command_argument_types() -> None:
    with pytest.raises(TypeError):
        dsa.query_matrix_info(1.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        dsa.set_threshold(0, True)


def test_command_range_edges_accepted() -> None:
    assert dsa.query_matrix_info(255)[6] == 255
    assert dsa.set_threshold(0, 4095)[8:10] == b"\xff\x0f"
    assert struct.unpack("<f", dsa.set_sensitivity(0, 1.0)[8:12]) == (1.0,)
    assert dsa.configure_acquisition(acquire=True, framerate=65535)[7:9] == b"\xff\xff"
    assert dsa.query_matrix_info(np.uint8(3)) == dsa.query_matrix_info(3)


def test_configure_acquisition_flags() -> None:
    def flags(**kw: object) -> int:
        return dsa.configure_acquisition(**kw)[6]  # type: ignore[arg-type]

    assert flags(acquire=False, framerate=0, rle=False) == 0x00
    assert flags(acquire=True, framerate=30, rle=False) == 0x80
    # RobWork's push start: acquisition + internal trigger (+ RLE) = 0xA1 (§1.6)
    assert flags(acquire=True, framerate=5, extra_flags=dsa.AcqFlag.INTERNAL_TRIGGER) == 0xA1
    cmd = dsa.decode_command(parse_all(dsa.configure_acquisition(acquire=True, framerate=30))[0])
    assert isinstance(cmd, ConfigureAcquisition) and cmd.push and not cmd.pull


def test_adjust_flags_bits() -> None:
    wire = dsa.set_sensitivity(2, 0.25, all_matrices=True, persistent=True, reset=True)
    assert wire[6] == 0x83 and wire[7] == 2
    cmd = dsa.decode_command(parse_all(wire)[0])
    assert cmd == SetSensitivity(2, 0.25, all_matrices=True, persistent=True, reset=True)
    assert isinstance(cmd, SetSensitivity) and not cmd.expects_reply
    thr = dsa.decode_command(parse_all(dsa.set_threshold(1, 7, persistent=True))[0])
    assert isinstance(thr, SetThreshold) and thr.persistent and not thr.expects_reply
    assert SetThreshold(1, 7).expects_reply


def test_rarely_used_commands_round_trip() -> None:
    cases: list[tuple[bytes, dsa.Command]] = [
        (dsa.read_matrix_mask(3), ReadMatrixMask(3, dynamic=False)),
        (dsa.read_matrix_mask(4, dynamic=True), ReadMatrixMask(4, dynamic=True)),
        (dsa.read_descriptor_string(DescriptorKind.SENSOR, 0), ReadDescriptorString(0, 0)),
        (dsa.read_descriptor_string(1, 5), ReadDescriptorString(DescriptorKind.MATRIX, 5)),
        (dsa.loop(), Loop()),
        (dsa.query_controller_state(), QueryControllerState()),
    ]
    for wire, expected in cases:
        [pkt] = parse_all(wire)
        assert dsa.decode_command(pkt) == expected
    assert dsa.read_matrix_mask(4, dynamic=True)[6:8] == b"\x01\x04"
    assert dsa.loop() == hx("AA AA AA 06 00 00")
    assert dsa.query_controller_state() == hx("AA AA AA 0A 00 00")


# ---------------------------------------------------------------------------------------------
# decode_command: payload sizes, unknown IDs
# ---------------------------------------------------------------------------------------------

REQUEST_SIZES = {
    PacketId.QUERY_CONTROLLER_CONFIGURATION: 0,
    PacketId.QUERY_SENSOR_CONFIGURATION: 0,
    PacketId.CONFIGURE_DATA_ACQUISITION: 3,
    PacketId.READ_MATRIX_MASK: 2,
    PacketId.READ_DESCRIPTOR_STRING: 2,
    PacketId.LOOP: 0,
    PacketId.QUERY_CONTROLLER_STATE: 0,
    PacketId.QUERY_MATRIX_CONFIGURATION: 1,
    PacketId.ADJUST_MATRIX_SENSITIVITY: 6,
    PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO: 1,
    PacketId.SET_MATRIX_THRESHOLD: 4,
    PacketId.GET_MATRIX_THRESHOLD: 1,
}


@pytest.mark.parametrize(("pid", "size"), REQUEST_SIZES.items())
def test_decode_command_payload_size(pid: PacketId, size: int) -> None:
    dsa.decode_command(Packet(pid, bytes(size)))  # exact size decodes
    with pytest.raises(ProtocolError) as long:
        dsa.decode_command(Packet(pid, bytes(size + 1)))
    assert long.value.code is DsaError.E_CMD_FORMAT_ERROR and long.value.packet_id == pid
    if size:
        with pytest.raises(ProtocolError) as short:
            dsa.decode_command(Packet(pid, bytes(size - 1)))
        assert short.value.code is DsaError.E_CMD_NOT_ENOUGH_PARAMS
    assert isinstance(long.value, ValueError)


@pytest.mark.parametrize("pid", [0x00, 0x07, 0x0C, 0x0D, 0x0E, 0x10, 0xAB, 0xFF])
def test_decode_command_unknown(pid: int) -> None:
    assert dsa.decode_command(Packet(pid, b"\x01\x02")) == UnknownCommand(pid, b"\x01\x02")
    wire = dsa.encode_packet(pid, b"\x01\x02")
    assert dsa.encode_command(UnknownCommand(pid, b"\x01\x02")) == wire


# ---------------------------------------------------------------------------------------------
# Response payloads (§1.4): layouts at the documented offsets, exact sizes
# ---------------------------------------------------------------------------------------------


def test_controller_info_offsets() -> None:
    raw = bytearray(18)
    struct.pack_into("<H", raw, 0, 0)
    struct.pack_into("<I", raw, 2, 0xDEADBEEF)
    raw[6] = 0x21
    struct.pack_into("<H", raw, 7, 0x2900)
    raw[9], raw[10], raw[11], raw[12] = 0xC0, 0x70, 1, 0
    struct.pack_into("<I", raw, 13, 1_000_000)
    raw[17] = 0x42
    info = ControllerInfo.decode(bytes(raw))
    assert info == ControllerInfo(
        serial_no=0xDEADBEEF, hw_version=0x21, sw_version=0x2900, status_flags=0xC0,
        feature_flags=0x70, senscon_type=1, active_interface=0, can_baudrate=1_000_000,
        can_id=0x42,
    )  # fmt: skip
    assert info.operable and info.acquiring
    assert info.encode() == bytes(raw)


def test_controller_info_can_id_is_one_byte() -> None:
    assert len(ControllerInfo(can_id=255).encode()) == 18
    with pytest.raises(ValueError, match="out of range"):
        ControllerInfo(can_id=256).encode()


def test_sensor_info_offsets() -> None:
    raw = struct.pack("<HHHBIB", 0, 6, 0x0123, 7, 0x01020304, 1)
    assert len(raw) == 12
    info = SensorInfo.decode(raw)
    assert (info.nb_matrices, info.generated_by, info.hw_revision) == (6, 0x0123, 7)
    assert (info.serial_no, info.feature_flags) == (0x01020304, 1)
    assert SensorInfo().encode()[2:4] == b"\x06\x00"


def test_matrix_info_offsets_and_u32_fullscale() -> None:
    info = MatrixInfo(
        texel_width=3.5, texel_height=4.0, cells_x=6, cells_y=13, uid=b"ABCDEF",
        hw_revision=9, center=(1.0, 2.0, 3.0), theta=(0.5, 0.25, -1.0), feature_flags=3,
    )  # fmt: skip
    raw = info.encode()
    assert len(raw) == 52
    assert struct.unpack_from("<ff", raw, 2) == (3.5, 4.0)
    assert struct.unpack_from("<HH", raw, 10) == (6, 13)
    assert raw[14:20] == b"ABCDEF" and raw[20:22] == b"\x00\x00" and raw[22] == 9
    assert struct.unpack_from("<3f", raw, 23) == (1.0, 2.0, 3.0)
    assert struct.unpack_from("<3f", raw, 35) == (0.5, 0.25, -1.0)
    assert struct.unpack_from("<I", raw, 47) == (4095,)
    assert raw[51] == 3
    assert MatrixInfo.decode(raw) == info
    assert (info.nb_cells, info.shape) == (78, (13, 6))


def test_matrix_info_field_validation() -> None:
    with pytest.raises(ValueError, match="uid"):
        MatrixInfo(cells_x=6, cells_y=14, uid=b"short").encode()
    with pytest.raises(ValueError, match="3 components"):
        MatrixInfo(cells_x=6, cells_y=14, center=(1.0, 2.0)).encode()  # type: ignore[arg-type]


def test_sensitivity_and_threshold_info() -> None:
    raw = SensitivityInfo(cur_sens=0.75).encode()
    assert raw == struct.pack("<HBff", 0, 2, 0.75, 0.5) and len(raw) == 11
    decoded = SensitivityInfo.decode(raw)
    assert decoded.adjustable and decoded.cur_sens == 0.75 and decoded.fact_sens == 0.5
    assert ThresholdInfo(threshold=150).encode() == hx("00 00 96 00")
    assert ThresholdInfo.decode(hx("00 00 96 00")).threshold == 150


def test_error_reply_codes() -> None:
    bad = ErrorReply.decode(struct.pack("<H", 13))
    assert bad.error_code is DsaError.E_CMD_UNKNOWN and not bad.ok
    odd = ErrorReply.decode(struct.pack("<H", 999))  # not in §1.3: kept as a plain int
    assert odd.error_code == 999 and not isinstance(odd.error_code, DsaError)
    assert [e.value for e in DsaError] == list(range(28))


FIXED_SIZE_RESPONSES: list[tuple[type, int]] = [
    (ControllerInfo, 18),
    (SensorInfo, 12),
    (MatrixInfo, 52),
    (SensitivityInfo, 11),
    (ThresholdInfo, 4),
    (ErrorReply, 2),
]


@pytest.mark.parametrize(("cls", "size"), FIXED_SIZE_RESPONSES)
def test_response_exact_size(cls: type, size: int) -> None:
    decoded = cls.decode(bytes(size))
    assert decoded.encode() == bytes(size)
    for wrong in (size - 1, size + 1):
        with pytest.raises(ProtocolError, match=f"exactly {size} bytes"):
            cls.decode(bytes(wrong))


def test_matrix_mask_exact_size_and_bit_order() -> None:
    mask = np.zeros((14, 6), dtype=bool)
    mask[0, 1] = True  # (x=1, y=0) → bit 1 of byte 0
    mask[1, 0] = True  # (x=0, y=1) → cell 6 → bit 6 of byte 0
    mask[13, 5] = True  # last cell 83 → bit 3 of byte 10
    reply = MatrixMask.from_array(mask)
    raw = reply.encode()
    assert len(raw) == 2 + 11 and raw[:2] == b"\x00\x00"
    assert raw[2] == 0x42 and raw[12] == 0x08 and not any(raw[3:12])
    decoded = MatrixMask.decode(raw, 84)
    assert np.array_equal(decoded.to_array(6, 14), mask)
    for wrong in (len(raw) - 1, len(raw) + 1):
        with pytest.raises(ProtocolError, match="exactly 13 bytes"):
            MatrixMask.decode(bytes(wrong), 84)
    with pytest.raises(ProtocolError, match="do not fit"):
        decoded.to_array(6, 13 * 2)


def test_descriptor_string() -> None:
    raw = DescriptorString(text="DSA 9205").encode()
    assert raw == b"\x00\x00DSA 9205"
    assert DescriptorString.decode(raw).text == "DSA 9205"
    assert DescriptorString.decode(b"\x00\x00").text == ""
    with pytest.raises(ProtocolError, match="at least 2"):
        DescriptorString.decode(b"\x00")


def test_encode_response_type_guard() -> None:
    with pytest.raises(TypeError, match="ControllerInfo"):
        dsa.encode_response(PacketId.QUERY_CONTROLLER_CONFIGURATION, SensorInfo())
    with pytest.raises(TypeError, match="Frame"):
        dsa.encode_response(PacketId.FULL_FRAME, ErrorReply())
    rejected = dsa.encode_response(PacketId.QUERY_SENSOR_CONFIGURATION, ErrorReply(13))
    assert parse_all(rejected) == [Packet(PacketId.QUERY_SENSOR_CONFIGURATION, b"\x0d\x00")]
    # IDs whose reply layout is [U] accept any response payload
    assert dsa.encode_response(PacketId.LOOP, ErrorReply())[3] == PacketId.LOOP


def test_response_round_trip_through_parser() -> None:
    infos = [MatrixInfo(cells_x=s.cells_x, cells_y=s.cells_y) for s in SDH2_MATRIX_SHAPES]
    stream = b"".join(
        dsa.encode_response(PacketId.QUERY_MATRIX_CONFIGURATION, info) for info in infos
    )
    got = [MatrixInfo.decode(p.payload) for p in packets_of(parse_all(stream))]
    assert [(g.cells_x, g.cells_y) for g in got] == [(6, 14), (6, 13)] * 3
    assert all(g.fullscale == 4095 for g in got)


# ---------------------------------------------------------------------------------------------
# RLE and frames (§1.5, §1.10)
# ---------------------------------------------------------------------------------------------


def test_rle_worked_example() -> None:
    out = dsa.rle_decode(hx("00 20 23 11 00 F0"), 18)
    assert out.dtype == np.uint16
    assert out.tolist() == [0, 0, 0x123] + [0] * 15


def test_rle_encode_greedy_runs() -> None:
    assert dsa.rle_encode([0, 0, 0x123] + [0] * 15) == hx("00 20 23 11 00 F0")
    assert dsa.rle_encode([7] * 31) == hx("07 F0 07 F0 07 10")
    assert dsa.rle_encode([]) == b""
    assert dsa.rle_encode(np.array([4095], dtype=np.int64)) == hx("FF 1F")


def test_rle_zero_count_words_expand_to_nothing() -> None:
    assert dsa.rle_decode(hx("FF 0F 05 20"), 2).tolist() == [5, 5]


@pytest.mark.parametrize(
    ("data", "nb_cells", "match"),
    [
        ("00 20 23 11 00 F0", 17, "expands to 18"),
        ("00 20 23 11 00 F0", 19, "expands to 18"),
        ("00 20 23", 3, "odd length"),
    ],
)
def test_rle_decode_rejects(data: str, nb_cells: int, match: str) -> None:
    with pytest.raises(FrameError, match=match):
        dsa.rle_decode(hx(data), nb_cells)


def test_rle_frame_sizes_of_section_1_10() -> None:
    zeros = np.zeros(SDH2_NB_CELLS, dtype=np.uint16)
    across = dsa.encode_frame_payload(1, zeros, rle=True)
    per_matrix = dsa.encode_frame_payload(
        1, zeros, rle=True, rle_breaks=dsa.texel_offsets(SDH2_MATRIX_SHAPES)
    )
    per_row = dsa.encode_frame_payload(1, zeros, rle=True, rle_breaks=range(0, 486, 6))
    worst = dsa.encode_frame_payload(1, np.arange(SDH2_NB_CELLS) % 2, rle=True)
    assert [len(p) for p in (across, per_matrix, per_row, worst)] == [71, 77, 167, 977]
    for payload in (across, per_matrix, per_row, worst):
        assert dsa.decode_frame_payload(payload, SDH2_NB_CELLS).texels.size == SDH2_NB_CELLS


def test_rle_breaks_validation() -> None:
    with pytest.raises(ValueError, match="breaks"):
        dsa.rle_encode([1, 2, 3], breaks=[4])
    assert dsa.rle_encode([1, 1], breaks=[0, 1, 2]) == hx("01 10 01 10")


def test_uncompressed_frame_round_trip_and_exact_size() -> None:
    texels = np.arange(SDH2_NB_CELLS, dtype=np.uint16) * 8
    payload = dsa.encode_frame_payload(0xFFFF_FFFF, texels, rle=False)
    assert len(payload) == 5 + 2 * SDH2_NB_CELLS and payload[4] == 0
    assert payload[5:9] == hx("00 00 08 00")
    frame = dsa.decode_frame_payload(payload, SDH2_NB_CELLS)
    assert frame.timestamp_ms == 0xFFFF_FFFF and not frame.rle
    assert np.array_equal(frame.texels, texels)
    assert frame.encode() == payload
    for wrong in (payload[:-1], payload + b"\x00", payload[:-2], payload + b"\x00\x00"):
        with pytest.raises(FrameError, match="uncompressed frame"):
            dsa.decode_frame_payload(wrong, SDH2_NB_CELLS)
    with pytest.raises(FrameError, match="at least 5"):
        dsa.decode_frame_payload(payload[:4], SDH2_NB_CELLS)


def test_rle_frame_wrong_cell_count() -> None:
    payload = dsa.encode_frame_payload(5, np.zeros(SDH2_NB_CELLS, dtype=np.uint16), rle=True)
    for nb in (SDH2_NB_CELLS - 1, SDH2_NB_CELLS + 1):
        with pytest.raises(FrameError) as info:
            dsa.decode_frame_payload(payload, nb)
        assert info.value.code is DsaError.E_INCONSISTENT_DATA


def test_decoded_frames_are_read_only() -> None:
    texels = np.full(SDH2_NB_CELLS, 9, dtype=np.uint16)
    for rle in (True, False):
        frame = dsa.decode_frame_payload(dsa.encode_frame_payload(1, texels, rle=rle), 486)
        with pytest.raises(ValueError, match="read-only"):
            frame.texels[0] = 1
    assert "486 texels, max 9" in repr(frame)


def test_frame_flag_bits_other_than_rle_are_ignored() -> None:
    payload = bytearray(dsa.encode_frame_payload(3, [1, 2, 3], rle=True))
    payload[4] |= 0x80
    frame = dsa.decode_frame_payload(bytes(payload), 3)
    assert frame.rle and frame.texels.tolist() == [1, 2, 3]


@pytest.mark.parametrize(
    ("texels", "match"),
    [
        ([0, 4096], "0…4095"),
        ([-1, 5], "0…4095"),
        ([0.5, 1.0], "integers"),
        (np.zeros((14, 6), dtype=np.uint16), "1-D"),
    ],
)
def test_frame_encoder_rejects(texels: object, match: str) -> None:
    for rle in (True, False):
        with pytest.raises(ValueError, match=match):
            dsa.encode_frame_payload(1, texels, rle=rle)  # type: ignore[arg-type]


def test_frame_timestamp_range() -> None:
    with pytest.raises(ValueError, match="timestamp_ms"):
        dsa.encode_frame_payload(1 << 32, [0], rle=True)


# ---------------------------------------------------------------------------------------------
# Geometry (§1.5, §1.8)
# ---------------------------------------------------------------------------------------------


def test_sdh2_layout_offsets() -> None:
    assert SDH2_NB_CELLS == 486
    assert dsa.DEFAULT_MAX_PAYLOAD == 977
    assert dsa.texel_offsets(SDH2_MATRIX_SHAPES) == [0, 84, 162, 246, 324, 408]
    assert SDH2_MATRIX_SHAPES[1] == MatrixShape(cells_x=6, cells_y=13)
    assert SDH2_MATRIX_SHAPES[0].shape == (14, 6)


def test_split_matrices_texel_addressing() -> None:
    texels = np.arange(SDH2_NB_CELLS, dtype=np.uint16)
    mats = dsa.split_matrices(texels, SDH2_MATRIX_SHAPES)
    offsets = dsa.texel_offsets(SDH2_MATRIX_SHAPES)
    assert [m.shape for m in mats] == [(14, 6), (13, 6)] * 3
    for m, (mat, shape) in enumerate(zip(mats, SDH2_MATRIX_SHAPES, strict=True)):
        for x, y in [(0, 0), (5, 0), (0, 1), (shape.cells_x - 1, shape.cells_y - 1)]:
            assert mat[y, x] == offsets[m] + y * shape.cells_x + x
    infos = [MatrixInfo(cells_x=4, cells_y=2), MatrixInfo(cells_x=3, cells_y=1)]
    frame = Frame(1, False, np.arange(11, dtype=np.uint16))
    small = frame.matrices(infos)
    assert small[0].tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]] and small[1].tolist() == [[8, 9, 10]]


def test_split_matrices_wrong_length() -> None:
    with pytest.raises(ValueError, match="486"):
        dsa.split_matrices(np.zeros(485, dtype=np.uint16), SDH2_MATRIX_SHAPES)


# ---------------------------------------------------------------------------------------------
# PacketParser (§1.2, §1.7, PART 3)
# ---------------------------------------------------------------------------------------------

SMALL = [dsa.query_controller_info(), dsa.query_matrix_info(2), dsa.set_sensitivity(1, 0.5)]


def test_parser_one_byte_at_a_time() -> None:
    stream = b"".join(SMALL) + GOLDEN_FRAME
    parser = PacketParser()
    events: list[dsa.Event] = []
    for b in stream:
        events += parser.feed(bytes([b]))
    assert [e.id for e in packets_of(events)] == [0x01, 0x0B, 0x0F, 0x00]
    assert len(events) == 4 and parser.packets == 4 and parser.buffered == 0
    assert parser.garbage_bytes == parser.resyncs == parser.crc_errors == 0


def test_parser_bad_crc_then_recovery() -> None:
    bad = bytearray(dsa.query_matrix_info(3))
    bad[-1] ^= 0xFF
    parser = PacketParser()
    events = parser.feed(bytes(bad) + dsa.get_threshold(1))
    good_crc = crc16(bad[3:-2])
    assert events[0] == BadCrc(PacketId.QUERY_MATRIX_CONFIGURATION, 1, good_crc ^ 0xFF00, good_crc)
    assert events[1] == GarbageSkipped(len(bad))
    assert events[2] == Packet(PacketId.GET_MATRIX_THRESHOLD, b"\x01")
    assert (parser.crc_errors, parser.resyncs, parser.garbage_bytes) == (1, 1, len(bad))


def test_parser_finds_packet_hidden_inside_corrupt_one() -> None:
    # A header whose length swallows the next (good) packet: rescanning must still find it.
    hidden = dsa.get_sensitivity_info(4)
    corrupt = dsa.PREAMBLE + bytes([0x12, len(hidden) + 4, 0]) + b"\x01\x02"
    stream = corrupt + hidden + b"\x03\x04" + b"\xee\xee"  # last 2: the corrupt "CRC"
    events = parse_all(stream)
    assert isinstance(events[0], BadCrc) and events[0].length == len(hidden) + 4
    assert Packet(PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO, b"\x04") in events


def test_parser_flush_delivers_packet_stuck_behind_long_header() -> None:
    stuck = dsa.PREAMBLE + b"\x00\x00\x02"  # announces 512 bytes that never come
    parser = PacketParser()
    assert parser.feed(stuck + dsa.query_sensor_info()) == []
    assert parser.buffered == len(stuck) + 6
    events = parser.flush()
    assert events == [GarbageSkipped(len(stuck)), Packet(PacketId.QUERY_SENSOR_CONFIGURATION, b"")]
    assert parser.buffered == 0 and parser.flush() == []


def test_parser_oversized() -> None:
    parser = PacketParser(max_payload=10)
    header = dsa.PREAMBLE + b"\x00\x0b\x00"
    events = parser.feed(header + dsa.loop())
    assert events == [Oversized(PacketId.FULL_FRAME, 11), GarbageSkipped(6), Packet(0x06, b"")]
    assert parser.oversized == 1 and parser.resyncs == 1
    # exactly max_payload is accepted
    assert packets_of(parser.feed(dsa.encode_packet(0x20, bytes(10))))[0].payload == bytes(10)


def test_parser_long_preamble_run() -> None:
    parser = PacketParser()
    events = parser.feed(b"\xaa\xaa" + dsa.query_controller_info())
    assert events == [GarbageSkipped(2), Packet(PacketId.QUERY_CONTROLLER_CONFIGURATION, b"")]
    # the run split across feeds gives the same accounting
    parser = PacketParser()
    got = parser.feed(b"\xaa" * 7) + parser.feed(b"\x02\x00") + parser.feed(b"\x00")
    assert packets_of(got) == [Packet(0x02, b"")]
    assert parser.garbage_bytes == 4 and parser.resyncs == 1


def test_parser_boot_noise() -> None:
    boot = b"\x1b[5n" * 3
    parser = PacketParser()
    events = parser.feed(boot + dsa.query_controller_info())
    assert events == [BootNoise()] * 3 + [Packet(0x01, b"")]
    assert parser.boot_noise == 3 and parser.garbage_bytes == 0 and parser.resyncs == 0
    # split inside the query, and surrounded by garbage
    parser = PacketParser()
    events = parser.feed(b"zz\x1b[") + parser.feed(b"5nq") + parser.feed(dsa.loop())
    assert events == [GarbageSkipped(2), BootNoise(), GarbageSkipped(1), Packet(0x06, b"")]
    assert parser.garbage_bytes == 3 and parser.boot_noise == 1 and parser.resyncs == 2


def test_parser_incomplete_boot_noise_is_garbage() -> None:
    parser = PacketParser()
    events = parser.feed(b"\x1b[5" + dsa.loop())
    assert events == [GarbageSkipped(3), Packet(0x06, b"")]


def test_parser_crc_when_empty() -> None:
    strict = PacketParser(crc_when_empty=True)
    with_crc = dsa.encode_packet(0x06, crc_when_empty=True)
    assert strict.feed(with_crc) == [Packet(0x06, b"")]
    bad = with_crc[:-1] + bytes([with_crc[-1] ^ 1])
    assert isinstance(strict.feed(bad)[0], BadCrc)
    lenient = PacketParser()
    assert lenient.feed(with_crc) == [Packet(0x06, b""), GarbageSkipped(2)]


def test_parser_counters_mixed_stream() -> None:
    bad = bytearray(dsa.set_threshold(0, 5))
    bad[8] ^= 0x01
    stream = (
        b"\x00\x01"
        + b"\x1b[5n"
        + dsa.query_controller_info()
        + bytes(bad)
        + dsa.PREAMBLE
        + b"\x00\xff\xff"
        + GOLDEN_FRAME
    )
    parser = PacketParser()
    events = parser.feed(stream)
    assert parser.packets == 2 and parser.crc_errors == 1 and parser.oversized == 1
    assert parser.boot_noise == 1 and parser.resyncs == 2
    assert parser.garbage_bytes == 2 + len(bad) + 6
    assert sum(e.nbytes for e in events if isinstance(e, GarbageSkipped)) == parser.garbage_bytes


def test_parser_buffer_stays_bounded() -> None:
    parser = PacketParser(max_payload=100)
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes().replace(b"\xaa", b"\x55")
    parser.feed(noise)
    assert parser.buffered <= 3 and parser.garbage_bytes >= len(noise) - 3
    parser.feed(b"\xaa" * 100_000)
    assert parser.buffered == 3
    parser.feed(b"\x00\x64\x00" + bytes(50))  # pending packet of 100 bytes
    assert parser.buffered == 3 + 3 + 50
    parser.feed(bytes(52) + dsa.loop())
    assert parser.crc_errors == 1 and parser.packets == 1 and parser.buffered == 0


def test_parser_rejects_bad_configuration() -> None:
    with pytest.raises(ValueError, match="max_payload"):
        PacketParser(max_payload=70_000)


# ---------------------------------------------------------------------------------------------
# Property tests
# ---------------------------------------------------------------------------------------------

uint12_arrays = st.lists(st.integers(0, 4095), max_size=600).map(
    lambda v: np.array(v, dtype=np.uint16)
)
# low-entropy arrays make long runs (> 15) likely
runny_arrays = st.lists(st.tuples(st.integers(0, 4095), st.integers(1, 60)), max_size=30).map(
    lambda runs: np.repeat(
        np.array([v for v, _ in runs], dtype=np.uint16), [n for _, n in runs]
    ).astype(np.uint16)
)


@PROPERTY
@given(st.one_of(uint12_arrays, runny_arrays), st.lists(st.integers(0, 700), max_size=5))
def test_rle_round_trip(values: np.ndarray, breaks: list[int]) -> None:
    breaks = [b for b in breaks if b <= values.size]
    data = dsa.rle_encode(values, breaks=breaks)
    words = np.frombuffer(data, dtype="<u2")
    assert ((words >> 12) >= 1).all()  # counts 1…15, never 0
    assert np.array_equal(dsa.rle_decode(data, values.size), values)


@PROPERTY
@given(uint12_arrays, st.integers(0, 0xFFFF_FFFF), st.booleans())
def test_frame_round_trip(values: np.ndarray, ts: int, rle: bool) -> None:
    frame = dsa.decode_frame_payload(dsa.encode_frame_payload(ts, values, rle=rle), values.size)
    assert (frame.timestamp_ms, frame.rle) == (ts, rle)
    assert np.array_equal(frame.texels, values)


packet_ids = st.integers(0, 255).filter(lambda i: i != 0xAA)
payloads = st.binary(max_size=120)


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    edges = [0, *points, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


@PROPERTY
@given(st.lists(st.tuples(packet_ids, payloads), max_size=8), st.lists(st.integers(0, 10**6)))
def test_packet_round_trip_any_chunking(packets: list[tuple[int, bytes]], cuts: list[int]) -> None:
    stream = b"".join(dsa.encode_packet(pid, payload) for pid, payload in packets)
    parser = PacketParser(max_payload=120)
    events: list[dsa.Event] = []
    for chunk in chunked(stream, cuts):
        events += parser.feed(chunk)
    assert events == [Packet(pid, payload) for pid, payload in packets]
    assert parser.buffered == 0 and parser.garbage_bytes == 0


command_strategy = st.one_of(
    st.builds(
        ConfigureAcquisition,
        acquire=st.booleans(),
        framerate=st.integers(0, 0xFFFF),
        rle=st.booleans(),
        flags=st.just(0),
    ).map(lambda c: ConfigureAcquisition(c.acquire, c.framerate, c.rle, 0x80 * c.acquire | c.rle)),
    st.builds(QueryMatrixInfo, st.integers(0, 255)),
    st.builds(GetThreshold, st.integers(0, 255)),
    st.builds(GetSensitivityInfo, st.integers(0, 255)),
    st.builds(
        SetSensitivity,
        st.integers(0, 255),
        st.floats(0.0, 1.0, width=32),
        st.booleans(),
        st.booleans(),
        st.booleans(),
    ),
    st.builds(
        SetThreshold, st.integers(0, 255), st.integers(0, 4095), st.booleans(), st.booleans()
    ),
    st.builds(ReadMatrixMask, st.integers(0, 255), st.booleans()),
    st.builds(ReadDescriptorString, st.sampled_from(list(DescriptorKind)), st.integers(0, 255)),
    st.sampled_from([QueryControllerInfo(), QuerySensorInfo(), Loop(), QueryControllerState()]),
)


@PROPERTY
@given(command_strategy)
def test_command_round_trip(cmd: dsa.Command) -> None:
    [pkt] = parse_all(dsa.encode_command(cmd))
    assert dsa.decode_command(pkt) == cmd


@PROPERTY
@given(
    st.builds(
        ControllerInfo,
        error_code=st.integers(0, 0xFFFF),
        serial_no=st.integers(0, 2**32 - 1),
        sw_version=st.integers(0, 0xFFFF),
        can_baudrate=st.integers(0, 2**32 - 1),
        can_id=st.integers(0, 255),
    )
    | st.builds(
        MatrixInfo,
        cells_x=st.integers(0, 0xFFFF),
        cells_y=st.integers(0, 0xFFFF),
        texel_width=st.floats(width=32, allow_nan=False),
        texel_height=st.floats(width=32, allow_nan=False),
        center=st.tuples(*[st.floats(width=32, allow_nan=False)] * 3),
        fullscale=st.integers(0, 2**32 - 1),
        uid=st.binary(min_size=6, max_size=6),
    )
    | st.builds(
        SensitivityInfo,
        cur_sens=st.floats(0, 1, width=32),
        fact_sens=st.floats(0, 1, width=32),
    )
    | st.builds(ThresholdInfo, threshold=st.integers(0, 0xFFFF))
    | st.builds(SensorInfo, nb_matrices=st.integers(0, 0xFFFF))
)
def test_response_round_trip(info: object) -> None:
    raw = info.encode()  # type: ignore[attr-defined]
    assert type(info).decode(raw) == info  # type: ignore[attr-defined]


@settings(PROPERTY, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300), st.lists(st.integers(0, 10**6), max_size=12))
def test_chunking_never_changes_the_result(data: bytes, cuts: list[int]) -> None:
    # seed the random bytes with valid packets so both paths are exercised
    data = data + dsa.query_matrix_info(1) + data[::-1] + GOLDEN_FRAME[:40]
    whole_parser = PacketParser(max_payload=64)
    whole = whole_parser.feed(data)
    parts_parser = PacketParser(max_payload=64)
    parts: list[dsa.Event] = []
    for chunk in chunked(data, cuts):
        parts += parts_parser.feed(chunk)
    assert merge_garbage(parts) == whole
    for name in ("packets", "crc_errors", "oversized", "garbage_bytes", "boot_noise", "resyncs"):
        assert getattr(parts_parser, name) == getattr(whole_parser, name), name


def merge_garbage(events: list[dsa.Event]) -> list[dsa.Event]:
    out: list[dsa.Event] = []
    for e in events:
        if isinstance(e, GarbageSkipped) and out and isinstance(out[-1], GarbageSkipped):
            out[-1] = GarbageSkipped(out[-1].nbytes + e.nbytes)
        else:
            out.append(e)
    return out
