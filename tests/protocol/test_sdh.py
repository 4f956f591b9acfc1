"""Tests of the SDH2 joint-controller codec (sdh2svc.protocol.sdh, protocols.md PART 2)."""

from __future__ import annotations

import itertools
import math
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sdh2svc.protocol.crc import crc16
from sdh2svc.protocol.sdh import (
    ASCII_COMMANDS,
    BINARY_COMMANDS,
    BLANK,
    CPP_AXIS_FMT,
    CPP_VECTOR_FMT,
    NUM_AXES,
    RESYNC,
    ArgForm,
    AsciiCommand,
    AxisState,
    BinaryCommand,
    BinaryReply,
    BinaryRequest,
    BlankLine,
    DebugLine,
    ErrorLine,
    ErrorSource,
    Garbage,
    HostStreamParser,
    ProtocolErrorEvent,
    Reply,
    ReplyParser,
    SdhError,
    SdhProtocolError,
    binary_reply_size,
    binary_request_size,
    encode_ascii,
    encode_binary_reply,
    encode_binary_request,
    encode_blank,
    encode_debug,
    encode_error,
    encode_reply,
    parse_command_line,
    parse_reply_line,
)

HOST_EVENT_TYPES = (AsciiCommand, BinaryRequest, BlankLine, ProtocolErrorEvent)
REPLY_EVENT_TYPES = (Reply, ErrorLine, DebugLine, Garbage, BinaryReply)

TARGETS = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
POSE = (0.0, -45.0, 0.0, -90.0, 0.0, -45.0, 0.0)


def f32(values: tuple[float, ...]) -> bytes:
    return struct.pack("<7f", *values)


# --------------------------------------------------------------------------- enums and tables


def test_error_codes_match_table_2_5() -> None:
    assert len(SdhError) == 37
    assert [int(e) for e in SdhError] == list(range(37))
    assert SdhError.CMD_UNKNOWN == 13
    assert SdhError.CMD_FORMAT_ERROR == 14
    assert SdhError.RANGE_ERROR == 24
    assert SdhError.INDEX_OUT_OF_BOUNDS == 26
    assert SdhError.MAX_COMMANDLINE_EXCEEDED == 32
    assert SdhError.CRC_ERROR == 33
    assert SdhError.NO_COMMAND == 34
    assert SdhError.UNKNOWN_ERROR == 36


def test_axis_states() -> None:
    assert [int(s) for s in AxisState] == list(range(8))
    assert AxisState.POSITIONING == 1 and AxisState.DISABLED == 6 and AxisState.LIMITS_REACHED == 7


def test_binary_command_codes() -> None:
    assert [int(c) for c in BinaryCommand] == list(range(0x80, 172))
    assert BinaryCommand.V == 0x80
    assert BinaryCommand.POS == 131 and BinaryCommand.P == 133 and BinaryCommand.M == 135
    assert BinaryCommand.TVAV == 140 and BinaryCommand.ILIM == 163 and BinaryCommand.POWER == 164
    assert BinaryCommand.CHANGE_CHANNEL == 171
    assert BinaryCommand.GET_DURATION.keyword == "get_duration"


def test_binary_subset_used_by_sdhlibrary_cpp() -> None:
    assert set(BINARY_COMMANDS) == {
        "p",
        "pos",
        "v",
        "a",
        "tpap",
        "tvav",
        "vel",
        "rvel",
        "state",
        "ilim",
        "power",
    }
    for keyword, code in BINARY_COMMANDS.items():
        assert code.keyword == keyword
        assert ASCII_COMMANDS[keyword].binary is code
    assert [s.keyword for s in ASCII_COMMANDS.values() if s.binary] == [
        k for k in ASCII_COMMANDS if k in BINARY_COMMANDS
    ]


def test_ascii_table_covers_section_2_4() -> None:
    # every binary code except the three transport settings has an ASCII command in §2.4
    extra = {"use_fixed_length", "change_rs232", "change_channel"}
    assert {c.keyword for c in BinaryCommand} - extra == set(ASCII_COMMANDS)
    assert ASCII_COMMANDS["p"].form is ArgForm.VECTOR and ASCII_COMMANDS["p"].settable
    assert not ASCII_COMMANDS["pos"].settable
    assert ASCII_COMMANDS["kv"].form is ArgForm.AXIS_ONLY
    assert ASCII_COMMANDS["pid"].n_values == 3
    assert ASCII_COMMANDS["grip"].n_values == 2 and not ASCII_COMMANDS["grip"].readable
    assert ASCII_COMMANDS["temp"].reply_values == 9
    assert ASCII_COMMANDS["selgrip"].reply_keyword == "SELGRIP"
    assert ASCII_COMMANDS["con"].integer and not ASCII_COMMANDS["grip"].integer


# --------------------------------------------------------------------------- binary: golden bytes


def test_golden_get_actual_angles() -> None:
    frame = encode_binary_request(BinaryCommand.POS)
    assert frame == bytes.fromhex("83 03 00 DC 1E")
    assert BinaryRequest.decode(frame) == BinaryRequest(BinaryCommand.POS, None, True)


def test_golden_set_targets() -> None:
    frame = encode_binary_request(BinaryCommand.P, TARGETS)
    assert frame == bytes.fromhex("85 1F 07") + f32(TARGETS) + bytes.fromhex("43 64")
    assert frame[3:11] == bytes.fromhex("00000000 00002041")
    assert len(frame) == 33 == binary_request_size(True, True)
    assert BinaryRequest.decode(frame) == BinaryRequest(BinaryCommand.P, TARGETS, True)


def test_golden_pos_reply() -> None:
    frame = encode_binary_reply(BinaryCommand.POS, SdhError.SUCCESS, POSE)
    assert frame == bytes.fromhex("83 20 07 00") + f32(POSE) + bytes.fromhex("B4 E7")
    assert len(frame) == 34 == binary_reply_size(True)
    reply = BinaryReply.decode(frame)
    assert reply == BinaryReply(BinaryCommand.POS, 0, POSE, True)
    assert reply.ok and reply.error is SdhError.SUCCESS


def test_tcp_forms_have_no_crc() -> None:
    # PART 4 item 1: 3 / 31 request bytes, 32 reply bytes
    assert encode_binary_request(BinaryCommand.POS, with_crc=False) == bytes.fromhex("83 01 00")
    setf = encode_binary_request(BinaryCommand.P, TARGETS, with_crc=False)
    assert setf == bytes.fromhex("85 1D 07") + f32(TARGETS)
    assert len(setf) == 31 == binary_request_size(True, False)
    rep = encode_binary_reply(BinaryCommand.POS, 0, POSE, with_crc=False)
    assert rep == bytes.fromhex("83 1E 07 00") + f32(POSE)
    assert len(rep) == 32 == binary_reply_size(False)
    assert BinaryRequest.decode(setf) == BinaryRequest(BinaryCommand.P, TARGETS, False)
    assert BinaryReply.decode(rep).with_crc is False


def test_crc_form_detection_and_forcing() -> None:
    serial = encode_binary_request(BinaryCommand.V, TARGETS)
    tcp = encode_binary_request(BinaryCommand.V, TARGETS, with_crc=False)
    assert BinaryRequest.decode(serial, crc=True).with_crc
    assert not BinaryRequest.decode(tcp, crc=False).with_crc
    with pytest.raises(SdhProtocolError) as exc:
        BinaryRequest.decode(tcp, crc=True)
    assert exc.value.code is SdhError.CMD_FORMAT_ERROR
    with pytest.raises(SdhProtocolError):
        BinaryReply.decode(encode_binary_reply(BinaryCommand.V, 0, TARGETS), crc=False)


def test_binary_decode_errors() -> None:
    good = bytearray(encode_binary_request(BinaryCommand.P, TARGETS))
    good[5] ^= 0x01
    with pytest.raises(SdhProtocolError) as exc:
        BinaryRequest.decode(bytes(good))
    assert exc.value.code is SdhError.CRC_ERROR
    with pytest.raises(SdhProtocolError) as exc:
        BinaryRequest.decode(b"\xfe\x03\x00\x00\x00")
    assert exc.value.code is SdhError.CMD_UNKNOWN
    bad_nvalid = bytes((0x85, 0x0B, 0x02)) + b"\x00" * 10
    with pytest.raises(SdhProtocolError) as exc:
        BinaryRequest.decode(bad_nvalid)
    assert exc.value.code is SdhError.CMD_FORMAT_ERROR
    reply = bytearray(encode_binary_reply(BinaryCommand.POS, 0, POSE))
    reply[1] = 31  # neither 30 nor 32: nb − 2 − 4·7 must be 0 or 2
    with pytest.raises(SdhProtocolError):
        BinaryReply.decode(bytes(reply))


def test_binary_encode_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        encode_binary_request(BinaryCommand.P, (1.0, 2.0))
    with pytest.raises(ValueError):
        encode_binary_request(0x7F)
    with pytest.raises(ValueError):
        encode_binary_request(BinaryCommand.P, (1e39,) * 7)
    with pytest.raises(ValueError):
        encode_binary_reply(BinaryCommand.P, 256)


def test_binary_error_reply_and_status() -> None:
    frame = encode_binary_reply(BinaryCommand.P, SdhError.RANGE_ERROR)
    reply = BinaryReply.decode(frame)
    assert reply.status == 24 and reply.error is SdhError.RANGE_ERROR and not reply.ok
    assert reply.values == (0.0,) * NUM_AXES
    assert BinaryReply.decode(encode_binary_reply(BinaryCommand.P, 200)).error is None


f32s = st.floats(width=32, allow_nan=False)
vectors = st.tuples(*[f32s] * NUM_AXES)
commands = st.sampled_from(list(BinaryCommand))


@settings(max_examples=150, deadline=None)
@given(cmd=commands, values=st.none() | vectors, with_crc=st.booleans())
def test_binary_request_round_trip(cmd, values, with_crc) -> None:
    frame = encode_binary_request(cmd, values, with_crc=with_crc)
    assert len(frame) == binary_request_size(values is not None, with_crc)
    assert BinaryRequest.decode(frame) == BinaryRequest(cmd, values, with_crc)
    assert HostStreamParser().feed(frame) == [BinaryRequest(cmd, values, with_crc)]
    if with_crc:
        assert crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")


@settings(max_examples=150, deadline=None)
@given(cmd=commands, status=st.integers(0, 255), values=vectors, with_crc=st.booleans())
def test_binary_reply_round_trip(cmd, status, values, with_crc) -> None:
    frame = encode_binary_reply(cmd, status, values, with_crc=with_crc)
    assert len(frame) == binary_reply_size(with_crc)
    expected = BinaryReply(cmd, status, values, with_crc)
    assert BinaryReply.decode(frame) == expected
    assert expected.encode() == frame
    assert ReplyParser().feed(frame) == [expected]


# --------------------------------------------------------------------------- ASCII: host encoding


@pytest.mark.parametrize(
    ("args", "kwargs", "expected"),
    [
        (("p",), {}, b"p\r\n"),
        (("p",), {"axis": 3}, b"p(3)\r\n"),
        (("p", -45), {"axis": 3}, b"p(3)=-45.000\r\n"),
        (("p", -45.0), {"axis": 3, "fmt": CPP_AXIS_FMT}, b"p(3)=     -45.000\r\n"),
        (("p", POSE), {}, b"p=0.000,-45.000,0.000,-90.000,0.000,-45.000,0.000\r\n"),
        (
            ("p", POSE),
            {"fmt": CPP_VECTOR_FMT},
            b"p=0.000000,-45.000000,0.000000,-90.000000,0.000000,-45.000000,0.000000\r\n",
        ),
        (("vp", 1), {}, b"vp=1\r\n"),
        (("con", 2.0), {}, b"con=2\r\n"),
        (("con",), {}, b"con\r\n"),
        (("selgrip", 1), {}, b"selgrip=1\r\n"),
        (("grip", (0.1, 40)), {}, b"grip=0.100,40.000\r\n"),
        (("power", (0,) * 7), {}, b"power=0,0,0,0,0,0,0\r\n"),
        (("power", 1), {"axis": 2}, b"power(2)=1\r\n"),
        (("pid", (1, 0.5, 0)), {"axis": 6}, b"pid(6)=1.000,0.500,0.000\r\n"),
        (("kv", 2.5), {"axis": 0}, b"kv(0)=2.500\r\n"),
        (("m",), {}, b"m\r\n"),
        (("ver",), {}, b"ver\r\n"),
        (("custom", (1.5,)), {}, b"custom=1.500\r\n"),
    ],
)
def test_encode_ascii_forms(args, kwargs, expected) -> None:
    assert encode_ascii(*args, **kwargs) == expected


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [
        (("p", (1.0, 2.0)), {}),  # wrong count
        (("p", (1.0,) * 8), {}),
        (("p",), {"axis": 7}),  # axis out of range
        (("p", 1.0), {"axis": -1}),
        (("pos", POSE), {}),  # read-only
        (("power", (0.5,) * 7), {}),  # integer command
        (("con", 1.5), {}),
        (("kv",), {}),  # per-axis only
        (("m",), {"axis": 1}),
        (("selgrip",), {}),  # needs a value
        (("p", (math.nan,) * 7), {}),
        (("p q",), {}),  # not a keyword
    ],
)
def test_encode_ascii_rejects(args, kwargs) -> None:
    with pytest.raises(ValueError):
        encode_ascii(*args, **kwargs)


def test_blank_handshake() -> None:
    assert encode_blank() == b" \r\n"
    assert parse_command_line(" ") is BLANK
    assert HostStreamParser().feed(encode_blank()) == [BlankLine()]


# --------------------------------------------------------------------------- ASCII: controller


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("p", AsciiCommand("p")),
        ("p(3)", AsciiCommand("p", 3)),
        ("p(3)=     -45.000", AsciiCommand("p", 3, (-45.0,))),
        ("p(3)=-45.000000", AsciiCommand("p", 3, (-45.0,))),
        ("p = 1, 2 ,3,4,5,6, 7", AsciiCommand("p", None, (1, 2, 3, 4, 5, 6, 7))),
        (
            "p=0.000000,-45.000000,0.000000,-90.000000,0.000000,-45.000000,0.000000",
            AsciiCommand("p", None, POSE),
        ),
        ("power=1.000000,1,1,1,1,1,1e0", AsciiCommand("power", None, (1.0,) * 7)),
        ("vp=1", AsciiCommand("vp", None, (1.0,))),
        ("con=2", AsciiCommand("con", None, (2.0,))),
        ("grip=0.100000,40.000000", AsciiCommand("grip", None, (0.1, 40.0))),
        ("pid(2)=1,.5,-3.", AsciiCommand("pid", 2, (1.0, 0.5, -3.0))),
        ("  POS\r", AsciiCommand("pos")),
        ("get_duration", AsciiCommand("get_duration")),
        ("", BLANK),
        (" \r\n", BLANK),
    ],
)
def test_parse_command_line(line, expected) -> None:
    assert parse_command_line(line) == expected


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("foo", SdhError.CMD_UNKNOWN),
        ("123", SdhError.CMD_UNKNOWN),
        ("=1", SdhError.CMD_UNKNOWN),
        ("p(3", SdhError.CMD_FORMAT_ERROR),
        ("p(x)", SdhError.CMD_FORMAT_ERROR),
        ("p 1", SdhError.CMD_FORMAT_ERROR),
        ("p(7)", SdhError.INDEX_OUT_OF_BOUNDS),
        ("p(-1)=0", SdhError.INDEX_OUT_OF_BOUNDS),
        ("p(99999999999999)", SdhError.INDEX_OUT_OF_BOUNDS),
        ("p=1,2,3", SdhError.NOT_ENOUGH_PARAMS),
        ("p=", SdhError.NOT_ENOUGH_PARAMS),
        ("p=1,2,3,4,5,6,7,8", SdhError.CMD_FORMAT_ERROR),
        ("p=1,abc,3,4,5,6,7", SdhError.CMD_FORMAT_ERROR),
        ("p=1,,3,4,5,6,7", SdhError.CMD_FORMAT_ERROR),
        ("p=1e999,0,0,0,0,0,0", SdhError.CMD_FORMAT_ERROR),
        ("p=nan,0,0,0,0,0,0", SdhError.CMD_FORMAT_ERROR),
        ("p(1)=1,2", SdhError.CMD_FORMAT_ERROR),
        ("pos=1,2,3,4,5,6,7", SdhError.NO_PARAMS_EXPECTED),
        ("m(1)", SdhError.CMD_FORMAT_ERROR),
        ("kv", SdhError.CMD_FORMAT_ERROR),
        ("selgrip", SdhError.NOT_ENOUGH_PARAMS),
        ("grip=0.5", SdhError.NOT_ENOUGH_PARAMS),
        ("pid(1)=1,2", SdhError.NOT_ENOUGH_PARAMS),
        ("con=1.5", SdhError.INVALID_PARAMETER),
    ],
)
def test_parse_command_line_errors(line, code) -> None:
    with pytest.raises(SdhProtocolError) as exc:
        parse_command_line(line)
    assert exc.value.code is code


def test_parse_command_line_without_table() -> None:
    assert parse_command_line("frob(2)=1", commands=None) == AsciiCommand("frob", 2, (1.0,))
    assert parse_command_line("p=", commands=None) == AsciiCommand("p", None, ())
    with pytest.raises(SdhProtocolError):
        parse_command_line("p(7)", commands=None)


@settings(max_examples=150, deadline=None)
@given(
    keyword=st.sampled_from(["p", "v", "a", "tpap", "tvav", "ilim", "p_min"]),
    values=st.tuples(*[st.floats(-1e5, 1e5)] * NUM_AXES),
    axis=st.none() | st.integers(0, NUM_AXES - 1),
)
def test_ascii_command_round_trip(keyword, values, axis) -> None:
    sent = values if axis is None else values[axis]
    line = encode_ascii(keyword, sent, axis=axis, fmt=CPP_VECTOR_FMT)
    [event] = HostStreamParser().feed(line)
    assert isinstance(event, AsciiCommand)
    assert (event.keyword, event.axis) == (keyword, axis)
    expected = values if axis is None else (values[axis],)
    assert event.values is not None
    pairs = zip(event.values, expected, strict=True)
    assert all(math.isclose(g, e, abs_tol=1e-6) for g, e in pairs)


# --------------------------------------------------------------------------- ASCII: replies


@pytest.mark.parametrize(
    ("args", "kwargs", "expected"),
    [
        (("p", POSE), {}, b"P=0.000,-45.000,0.000,-90.000,0.000,-45.000,0.000\r\n"),
        (("p", -45.0), {"axis": 3}, b"P(3)=-45.000\r\n"),
        (("power", (0.0,) * 7), {}, b"POWER=0,0,0,0,0,0,0\r\n"),
        (("state", (1, 1, 0, 0, 6, 2.0, 7)), {}, b"STATE=1,1,0,0,6,2,7\r\n"),
        (("m", 4.51), {"fmt": "{:.2f}"}, b"M=4.51\r\n"),
        (("selgrip", (0.0, 1)), {"fmt": "{:.1f}"}, b"SELGRIP=0.0,1\r\n"),
        (("ver", "0.0.3.3"), {}, b"VER=0.0.3.3\r\n"),
        (("con", 2), {}, b"CON=2\r\n"),
        (("stop", None), {}, b"STOP=\r\n"),
    ],
)
def test_encode_reply(args, kwargs, expected) -> None:
    assert encode_reply(*args, **kwargs) == expected


def test_encode_error_and_debug() -> None:
    assert encode_error(13) == b"E13\r\n"
    assert encode_error(SdhError.CRC_ERROR) == b"E33\r\n"
    assert encode_debug("Enabling all axis") == b"@Enabling all axis\r\n"
    with pytest.raises(ValueError):
        encode_debug("two\r\nlines")
    with pytest.raises(ValueError):
        encode_reply("ver", "a\nb")


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("P=0.0,-45,0,-90,0,-45,0", Reply("P", None, POSE, "0.0,-45,0,-90,0,-45,0")),
        ("P(3)=     -45.000", Reply("P", 3, (-45.0,), "-45.000")),
        ("P(3)= -45.000\r", Reply("P", 3, (-45.0,), "-45.000")),
        ("M=4.51", Reply("M", None, (4.51,), "4.51")),
        ("M=4.51s", Reply("M", None, (4.51,), "4.51s")),
        ("SELGRIP=0.0,1", Reply("SELGRIP", None, (0.0, 1.0), "0.0,1")),
        ("VER=0.0.3.3", Reply("VER", None, (), "0.0.3.3")),
        ("vp=1", Reply("VP", None, (1.0,), "1")),
        ("STOP=", Reply("STOP", None, (), "")),
        ("STOP", Reply("", None, (), "STOP")),
        ("E13", ErrorLine(13, SdhError.CMD_UNKNOWN)),
        ("E 24", ErrorLine(24, SdhError.RANGE_ERROR)),
        ("E99", ErrorLine(99, None)),
        ("@max distance=45.06, T=4.51s", DebugLine("max distance=45.06, T=4.51s")),
        ("P(x)=1", Garbage(b"P(x)=1", "malformed reply keyword")),
        ("  \r", None),
    ],
)
def test_parse_reply_line(line, expected) -> None:
    assert parse_reply_line(line) == expected


@settings(max_examples=150, deadline=None)
@given(
    keyword=st.sampled_from(["p", "pos", "vel", "v", "tvav", "vlim", "ilim", "temp"]),
    values=st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=9),
    axis=st.none() | st.integers(0, NUM_AXES - 1),
)
def test_ascii_reply_round_trip(keyword, values, axis) -> None:
    [event] = ReplyParser().feed(encode_reply(keyword, values, axis=axis))
    assert isinstance(event, Reply)
    assert (event.keyword, event.axis) == (keyword.upper(), axis)
    assert len(event.values) == len(values)
    pairs = zip(event.values, values, strict=True)
    assert all(math.isclose(g, e, abs_tol=5.001e-4) for g, e in pairs)  # "{:.3f}" rounding


# --------------------------------------------------------------------------- line parser


def test_line_parser_host_role_terminators_and_debug() -> None:
    stream = (
        b"@Enabling all axis\r\n"
        b"M=4.51\n"  # bare LF
        b"P(3)=     -45.000\r\n"
        b"\r\n"  # blank: dropped on the host side
        b"E13\r\n"
        b"VEL=1,2,3,4,5,6,7\n\r"  # the [U] "\n\r" terminator of §2.1
        b"VP=0\r\n"
    )
    expected = [
        DebugLine("Enabling all axis"),
        Reply("M", None, (4.51,), "4.51"),
        Reply("P", 3, (-45.0,), "-45.000"),
        ErrorLine(13, SdhError.CMD_UNKNOWN),
        Reply("VEL", None, (1, 2, 3, 4, 5, 6, 7), "1,2,3,4,5,6,7"),
        Reply("VP", None, (0.0,), "0"),
    ]
    assert ReplyParser(binary=False).feed(stream) == expected
    quiet = ReplyParser(binary=False, report_debug=False).feed(stream)
    assert quiet == expected[1:]


def test_line_parser_bare_cr_does_not_end_a_line() -> None:
    parser = ReplyParser(binary=False)
    assert parser.feed(b"P=1\r") == []
    assert parser.feed(b"\n") == [Reply("P", None, (1.0,), "1")]


def test_line_parser_controller_role() -> None:
    parser = HostStreamParser(binary=False)
    events = parser.feed(b" \r\nver\r\np(3)=     -45.000\r\nbogus\r\n\x83\x03\x00\r\n")
    assert events[:3] == [BLANK, AsciiCommand("ver"), AsciiCommand("p", 3, (-45.0,))]
    assert isinstance(events[3], ProtocolErrorEvent) and events[3].code is SdhError.CMD_UNKNOWN
    # no binary framing in a pure line parser: the frame is a non-printable line
    assert isinstance(events[4], ProtocolErrorEvent) and events[4].source is ErrorSource.LINE
    assert len(events) == 5


def test_overlong_lines_reported_once_then_recovered() -> None:
    long = b"p=" + b"1," * 40 + b"\r\n"
    host = HostStreamParser(max_line=32)
    events = host.feed(long + b"pos\r\n")
    assert len(events) == 2
    assert events[0].code is SdhError.MAX_COMMANDLINE_EXCEEDED
    assert events[0].source is ErrorSource.LINE and events[0].data == long[:32]
    assert events[0].suggested_reply() == b"E32\r\n"
    assert events[1] == AsciiCommand("pos")
    # chunked: identical events
    chunked = HostStreamParser(max_line=32)
    assert [e for b in long + b"pos\r\n" for e in chunked.feed(bytes([b]))] == events
    reply = ReplyParser(max_line=32, binary=False).feed(b"X" * 100 + b"\r\nCON=1\r\n")
    assert reply == [
        Garbage(b"X" * 32, "line longer than 32 bytes"),
        Reply("CON", None, (1.0,), "1"),
    ]


# --------------------------------------------------------------------------- mixed streams


REPLY_STREAM = (
    encode_reply("ver", "0.0.3.3")
    + encode_binary_reply(BinaryCommand.POS, 0, POSE)
    + encode_debug("Enabling all axis")
    + encode_reply("m", 4.51)
    + encode_binary_reply(BinaryCommand.STATE, 0, (1, 1, 1, 0, 0, 0, 0))
    + encode_error(SdhError.RANGE_ERROR)
    + encode_binary_reply(BinaryCommand.P, SdhError.CRC_ERROR)
    + encode_reply("p", -45.0, axis=3, fmt=CPP_AXIS_FMT)
)
REPLY_EVENTS = [
    Reply("VER", None, (), "0.0.3.3"),
    BinaryReply(BinaryCommand.POS, 0, POSE, True),
    DebugLine("Enabling all axis"),
    Reply("M", None, (4.51,), "4.510"),
    BinaryReply(BinaryCommand.STATE, 0, (1, 1, 1, 0, 0, 0, 0), True),
    ErrorLine(24, SdhError.RANGE_ERROR),
    BinaryReply(BinaryCommand.P, 33, (0.0,) * 7, True),
    Reply("P", 3, (-45.0,), "-45.000"),
]

HOST_STREAM = (
    encode_blank()
    + encode_ascii("ver")
    + encode_binary_request(BinaryCommand.POS)
    + encode_ascii("p", -45.0, axis=3, fmt=CPP_AXIS_FMT)
    + encode_binary_request(BinaryCommand.TVAV, TARGETS)
    + b"con=2\n"
    + encode_binary_request(BinaryCommand.STATE, with_crc=False)
    + b"p=1\r\n"
    + encode_binary_request(BinaryCommand.POWER, (0,) * 7)
)
HOST_EVENTS = [
    BLANK,
    AsciiCommand("ver"),
    BinaryRequest(BinaryCommand.POS, None, True),
    AsciiCommand("p", 3, (-45.0,)),
    BinaryRequest(BinaryCommand.TVAV, TARGETS, True),
    AsciiCommand("con", None, (2.0,)),
    BinaryRequest(BinaryCommand.STATE, None, False),
    ProtocolErrorEvent(SdhError.NOT_ENOUGH_PARAMS, "p needs 7 values", b"p=1\r", ErrorSource.LINE),
    BinaryRequest(BinaryCommand.POWER, (0.0,) * 7, True),
]


def test_reply_stream_one_shot() -> None:
    assert ReplyParser().feed(REPLY_STREAM) == REPLY_EVENTS


def test_host_stream_one_shot() -> None:
    assert HostStreamParser().feed(HOST_STREAM) == HOST_EVENTS


@pytest.mark.parametrize(
    ("factory", "stream", "expected"),
    [(ReplyParser, REPLY_STREAM, REPLY_EVENTS), (HostStreamParser, HOST_STREAM, HOST_EVENTS)],
    ids=["replies", "requests"],
)
def test_split_at_every_byte_boundary(factory, stream, expected) -> None:
    for i in range(len(stream) + 1):
        parser = factory()
        assert parser.feed(stream[:i]) + parser.feed(stream[i:]) == expected, i
        assert parser.buffered == 0
    parser = factory()
    assert [e for b in stream for e in parser.feed(bytes([b]))] == expected


def test_host_crc_error_reports_and_resyncs_at_once() -> None:
    bad = bytearray(encode_binary_request(BinaryCommand.P, TARGETS))
    bad[10] ^= 0x40
    parser = HostStreamParser()
    events = parser.feed(bytes(bad) + encode_binary_request(BinaryCommand.POS) + b"vlim\r\n")
    assert len(events) == 3
    err = events[0]
    assert isinstance(err, ProtocolErrorEvent)
    assert (err.code, err.source, err.binary_cmd, err.with_crc) == (
        SdhError.CRC_ERROR,
        ErrorSource.FRAME,
        BinaryCommand.P,
        True,
    )
    assert err.data == bytes(bad)
    answer = err.suggested_reply()
    assert len(answer) == 34 and BinaryReply.decode(answer).status == SdhError.CRC_ERROR
    assert events[1:] == [BinaryRequest(BinaryCommand.POS, None, True), AsciiCommand("vlim")]


def test_lf_cr_terminator_does_not_break_following_binary_reply() -> None:
    # PART 4 item 3: the C++ host breaks here; our parser drops a CR at a message boundary.
    frame = encode_binary_reply(BinaryCommand.POS, 0, POSE)
    events = ReplyParser().feed(b"CON=0\n\r" + frame)
    assert events == [Reply("CON", None, (0.0,), "0"), BinaryReply.decode(frame)]


def test_reply_crc_error_is_garbage_of_whole_frame() -> None:
    bad = bytearray(encode_binary_reply(BinaryCommand.POS, 0, POSE))
    bad[-1] ^= 0xFF
    events = ReplyParser().feed(bytes(bad) + b"CON=0\r\n")
    assert isinstance(events[0], Garbage) and events[0].data == bytes(bad)
    assert "CRC" in events[0].reason
    assert events[1:] == [Reply("CON", None, (0.0,), "0")]


def test_crc_mode_forcing_in_streams() -> None:
    tcp_get = encode_binary_request(BinaryCommand.POS, with_crc=False)
    serial = HostStreamParser(crc=True)
    events = serial.feed(tcp_get + b"\r\n")
    assert not any(isinstance(e, BinaryRequest) for e in events)
    assert events[0].source is ErrorSource.GARBAGE and events[0].suggested_reply() == b""
    assert HostStreamParser(crc=False).feed(tcp_get) == [
        BinaryRequest(BinaryCommand.POS, None, False)
    ]
    tcp_reply = encode_binary_reply(BinaryCommand.POS, 0, POSE, with_crc=False)
    assert ReplyParser(crc=False).feed(tcp_reply) == [
        BinaryReply(BinaryCommand.POS, 0, POSE, False)
    ]
    assert not any(isinstance(e, BinaryReply) for e in ReplyParser(crc=True).feed(tcp_reply))


def test_unknown_binary_code_costs_one_byte() -> None:
    events = HostStreamParser().feed(b"\xff\xfepos\r\n")
    assert [e.source for e in events[:2]] == [ErrorSource.GARBAGE] * 2
    assert events[0].code is SdhError.CMD_UNKNOWN and events[0].data == b"\xff"
    assert events[2:] == [AsciiCommand("pos")]
    replies = ReplyParser().feed(b"\xffPOS=1,2,3,4,5,6,7\r\n")
    assert replies[0] == Garbage(b"\xff", "unknown binary command 0xff")
    assert replies[1].keyword == "POS"


def test_reset_drops_partial_frame() -> None:
    parser = HostStreamParser()
    assert parser.feed(encode_binary_request(BinaryCommand.P, TARGETS)[:20]) == []
    assert parser.buffered == 20
    parser.reset()
    assert parser.buffered == 0
    assert parser.feed(b"pos\r\n") == [AsciiCommand("pos")]


def test_flush_hands_over_a_partial_reply_and_starts_afresh() -> None:
    parser = ReplyParser()
    assert parser.feed(b"POS=1,2,3") == []
    assert parser.flush() == b"POS=1,2,3" and parser.buffered == 0
    assert parser.flush() == b""
    assert parser.feed(b"POS=1,2,3,4,5,6,7\r\n")[0].keyword == "POS"  # not glued to the rest


def test_suggested_replies() -> None:
    line_err = ProtocolErrorEvent(SdhError.CMD_UNKNOWN, "x", b"x", ErrorSource.LINE)
    assert line_err.suggested_reply() == b"E13\r\n"
    frame_err = ProtocolErrorEvent(
        SdhError.CRC_ERROR, "x", b"", ErrorSource.FRAME, BinaryCommand.POS, False
    )
    assert frame_err.suggested_reply() == encode_binary_reply(BinaryCommand.POS, 33, with_crc=False)


# --------------------------------------------------------------------------- recovery rule + fuzz


def test_single_blank_line_resyncs_after_ascii_garbage() -> None:
    parser = HostStreamParser()
    parser.feed(b"po\x01\x02zz")
    events = parser.feed(b"\r\npos\r\n")
    assert events[-1] == AsciiCommand("pos") and events[0].source is ErrorSource.LINE


def test_partial_binary_header_swallows_one_blank_line_but_not_resync() -> None:
    # Documented limit: a plausible frame header waits for its 33 bytes, so a single blank line
    # and the next command are taken as payload; RESYNC (34 bytes) always ends such a frame.
    parser = HostStreamParser()
    assert parser.feed(b"\x85\x1f\x07" + b"\r\npos\r\n") == []
    events = parser.feed(RESYNC + b"pos\r\n")
    assert events[0].code is SdhError.CRC_ERROR
    assert AsciiCommand("pos") not in events[:-1]
    assert events[-1] == AsciiCommand("pos") and parser.buffered == 0
    assert set(map(type, events[1:-1])) == {BlankLine}


def test_resync_is_as_long_as_the_longest_binary_message() -> None:
    assert RESYNC == b"\r\n" * 17
    assert len(RESYNC) == binary_reply_size(True) > binary_request_size(True, True)


CLEAN_REQUESTS = [
    encode_ascii(k, v, axis=a)
    for k, v, a in [("pos", None, None), ("p", 1.5, 2), ("v", TARGETS, None), ("con", 1, None)]
] + [
    encode_binary_request(BinaryCommand.POS),
    encode_binary_request(BinaryCommand.P, TARGETS),
    encode_binary_request(BinaryCommand.VEL, with_crc=False),
    encode_binary_request(BinaryCommand.TVAV, TARGETS, with_crc=False),
    encode_blank(),
]
CLEAN_REPLIES = [
    encode_reply("pos", POSE),
    encode_reply("p", -45.0, axis=3),
    encode_error(13),
    encode_debug("hello"),
    encode_reply("ver", "0.0.3.3"),
    encode_binary_reply(BinaryCommand.POS, 0, POSE),
    encode_binary_reply(BinaryCommand.STATE, 0, (1,) * 7, with_crc=False),
    encode_binary_reply(BinaryCommand.P, SdhError.RANGE_ERROR),
]


@st.composite
def mutated(draw: st.DrawFn, pool: list[bytes]) -> bytes:
    data = bytearray(b"".join(draw(st.lists(st.sampled_from(pool), min_size=1, max_size=5))))
    for _ in range(draw(st.integers(1, 5))):
        if not data:
            break
        pos = draw(st.integers(0, len(data) - 1))
        op = draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        if op == "flip":
            data[pos] ^= draw(st.integers(1, 255))
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 8))]
        else:
            del data[pos:]
    return bytes(data)


def chunks(draw: st.DrawFn, data: bytes) -> list[bytes]:
    cuts = sorted(draw(st.lists(st.integers(0, len(data)), max_size=6)))
    edges = [0, *cuts, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


FUZZ = settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(data=st.data(), crc=st.sampled_from([None, True, False]))
def test_fuzz_host_stream_parser(data: st.DataObject, crc: bool | None) -> None:
    garbage = data.draw(st.binary(max_size=300) | mutated(CLEAN_REQUESTS), label="garbage")
    clean = data.draw(st.sampled_from(CLEAN_REQUESTS[:4] + CLEAN_REQUESTS[4:6]), label="clean")
    if crc is False and clean[0] >= 0x80:
        clean = encode_binary_request(BinaryCommand.POS, with_crc=False)
    parser = HostStreamParser(crc=crc)
    for chunk in chunks(data.draw, garbage):
        events = parser.feed(chunk)
        assert all(isinstance(e, HOST_EVENT_TYPES) for e in events)
    events = parser.feed(RESYNC + clean)
    assert events, "the clean message must produce an event"
    assert events[-1] == HostStreamParser(crc=crc).feed(clean)[0]
    assert not isinstance(events[-1], ProtocolErrorEvent)
    assert parser.buffered == 0


@FUZZ
@given(data=st.data(), crc=st.sampled_from([None, True, False]))
def test_fuzz_reply_parser(data: st.DataObject, crc: bool | None) -> None:
    garbage = data.draw(st.binary(max_size=300) | mutated(CLEAN_REPLIES), label="garbage")
    clean = data.draw(st.sampled_from(CLEAN_REPLIES[:3] + CLEAN_REPLIES[5:6]), label="clean")
    if crc is False and clean[0] >= 0x80:
        clean = encode_binary_reply(BinaryCommand.POS, 0, POSE, with_crc=False)
    parser = ReplyParser(crc=crc)
    for chunk in chunks(data.draw, garbage):
        events = parser.feed(chunk)
        assert all(isinstance(e, REPLY_EVENT_TYPES) for e in events)
    events = parser.feed(RESYNC + clean)
    [expected] = ReplyParser(crc=crc).feed(clean)
    assert not isinstance(expected, Garbage)
    assert events[-1] == expected
    assert parser.buffered == 0


@FUZZ
@given(garbage=st.binary(max_size=400))
def test_fuzz_line_parsers_never_raise(garbage: bytes) -> None:
    host = ReplyParser(max_line=64, binary=False)
    host.feed(garbage)
    assert host.feed(b"\r\nCON=1\r\n")[-1] == Reply("CON", None, (1.0,), "1")
    controller = HostStreamParser(max_line=64, binary=False)
    controller.feed(garbage)
    assert controller.feed(b"\r\ncon\r\n")[-1] == AsciiCommand("con")


# --- a line cut short by a binary frame (a stray byte, a frame cut short) ---------------------

GET_POS = encode_binary_request(BinaryCommand.POS)  # 83 03 00 dc 1e


@pytest.mark.parametrize(
    "stray",
    [GET_POS[:-1], b"x", bytes([0xAC, 0x03, 0x00, 0x83, 0xF1]), b"x" * 300],
    ids=["frame-cut-short", "stray-ascii-byte", "unknown-code", "over-long-line"],
)
def test_a_stray_costs_a_binary_host_one_reply_at_most(stray: bytes) -> None:
    """§2.6: frames are told from lines by their first byte (≥ 0x80, which no line holds). So
    a stray or a cut-short frame costs at most the next request, never every later one, and
    is never answered with an E<n> line, which would misalign a binary host's replies."""
    parser = HostStreamParser()
    parser.feed(stray)  # (an over-long line itself is answered E32: it is a line)
    events = []
    for _ in range(60):
        events += parser.feed(GET_POS)
    requests = [e for e in events if isinstance(e, BinaryRequest)]
    assert len(requests) >= 59 and requests[-1] == BinaryRequest(BinaryCommand.POS, None, True)
    errors = [e for e in events if isinstance(e, ProtocolErrorEvent)]
    assert all(e.suggested_reply() == b"" or e.source is ErrorSource.FRAME for e in errors), [
        (e.source, e.message) for e in errors
    ]


def test_a_reply_line_cut_short_by_a_binary_reply_is_garbage_then_the_reply() -> None:
    reply = encode_binary_reply(BinaryCommand.POS, 0, (1.0,) * NUM_AXES)
    events = ReplyParser(binary=True).feed(b"POS=1.0,2" + reply)
    assert isinstance(events[0], Garbage) and events[0].data == b"POS=1.0,2"
    assert isinstance(events[1], BinaryReply) and len(events) == 2


@pytest.mark.parametrize("line", ["temp(0)", "temp(8)", "ver(9)", "m(0)", "m(7)"])
def test_an_index_to_a_command_without_an_axis_form_is_a_format_error(line: str) -> None:
    with pytest.raises(SdhProtocolError) as bad:
        parse_command_line(line)
    assert bad.value.code is SdhError.CMD_FORMAT_ERROR and "no per-axis form" in str(bad.value)
