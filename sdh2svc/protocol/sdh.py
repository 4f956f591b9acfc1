"""Sans-I/O codec for the SCHUNK SDH2 joint-controller serial protocol (protocols.md PART 2).

Design (h11 style): nothing here reads a port, opens a socket, sleeps or looks at a clock. Encoders
turn typed values into the exact bytes to write; parsers are fed whatever bytes arrived, in chunks
of any size, and hand back typed events. The same module serves both ends of the link:

* host (driver) side: :func:`encode_ascii`, :func:`encode_blank`, :func:`encode_binary_request`
  produce requests; :class:`ReplyParser` (ASCII lines, and binary replies unless
  ``binary=False``) turns the SDH's output into :class:`Reply`, :class:`ErrorLine`,
  :class:`DebugLine`, :class:`BinaryReply` and :class:`Garbage` events;
* controller (emulator) side: :class:`HostStreamParser` turns the host's output (ASCII command
  lines and binary frames mixed on one line, §2.6) into :class:`AsciiCommand`,
  :class:`BinaryRequest`, :class:`BlankLine` and :class:`ProtocolErrorEvent` events;
  :func:`encode_reply`, :func:`encode_error`, :func:`encode_debug` and
  :func:`encode_binary_reply` produce the answers.

Timing (timeouts, the 100 ms drain at connect, the host's 0.5 s ``BinarySync``) belongs to the
I/O layer; the parsers offer :meth:`reset` for it. Parsers never raise on any input bytes.

Resynchronisation rule (both stream parsers): a message boundary is the start of the stream, the
byte after a line's ``\\n`` or the byte after a complete binary frame. A byte ≥ 0x80 at a boundary
starts a binary frame; anything else starts a line. No line holds a byte ≥ 0x80, so in a
stream that may carry binary frames one that comes before the line's ``\\n`` (or while an
over-long line is being dropped) cuts the line short (reported, never answered) and starts a
frame: a stray byte or a frame cut short can then cost one reply, never every later frame of
the connection. A frame whose header is implausible costs one
byte (reported) and scanning resumes at the next byte; a frame with a wrong CRC is dropped whole
(reported) — the usual case is a bit error, and the host expects one reply per request. An
incomplete frame waits for its remaining bytes, so binary garbage can swallow up to 31 following
bytes; feeding :data:`RESYNC` (17 × ``\\r\\n``, as long as the longest binary message) after any
garbage always leaves the parser at a message boundary, so the next clean message is recovered
(proof sketch in :data:`RESYNC`). Without garbage no resync is needed.

Facts are cited as §x.y of ``docs/protocols.md``; behaviour that document marks
unconfirmed ([U]) is a parameter or is noted in the docstring that implements a choice.
"""

from __future__ import annotations

import math
import re
import struct
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum, StrEnum
from numbers import Integral, Real
from types import MappingProxyType
from typing import Final, Generic, TypeAlias, TypeVar

from sdh2svc.protocol.crc import crc16

__all__ = [
    "ASCII_COMMANDS",
    "BINARY_COMMANDS",
    "BLANK",
    "COMMAND_SINCE",
    "CPP_AXIS_FMT",
    "CPP_VECTOR_FMT",
    "DEFAULT_FMT",
    "DEFAULT_MAX_LINE",
    "EOL",
    "NUM_AXES",
    "RESYNC",
    "ArgForm",
    "AsciiCommand",
    "AxisState",
    "BinaryCommand",
    "BinaryReply",
    "BinaryRequest",
    "BlankLine",
    "CommandSpec",
    "DebugLine",
    "ErrorLine",
    "ErrorSource",
    "Event",
    "Garbage",
    "HostEvent",
    "HostStreamParser",
    "ProtocolErrorEvent",
    "Reply",
    "ReplyEvent",
    "ReplyParser",
    "SdhError",
    "SdhProtocolError",
    "binary_reply_size",
    "binary_request_size",
    "encode_ascii",
    "encode_binary_reply",
    "encode_binary_request",
    "encode_blank",
    "encode_debug",
    "encode_error",
    "encode_reply",
    "firmware_release",
    "parse_command_line",
    "parse_reply_line",
]

# ---------------------------------------------------------------------------------------------
# Constants and enumerations
# ---------------------------------------------------------------------------------------------

NUM_AXES: Final = 7
"""Number of joint axes (§2.2); every vector on the wire has this many elements."""

#: Commands older firmware does not know, and the release that brought each (SDHLibrary-CPP
#: ``sdh/sdh.cpp``: ``GetAxisLimitVelocity`` uses fixed values before 0.0.2.1,
#: ``GetAxisLimitAcceleration`` before 0.0.2.7, ``SetController``/``GetController`` send no
#: ``con`` before 0.0.2.6, where it "would yield an error from the firmware (unknown command)";
#: ``rvel`` came with the velocity controllers, §2.4). Such a firmware answers E13.
COMMAND_SINCE: Final[dict[str, tuple[int, ...]]] = {
    "vlim": (0, 0, 2, 1),
    "con": (0, 0, 2, 6),
    "rvel": (0, 0, 2, 6),
    "alim": (0, 0, 2, 7),
}


def firmware_release(version: str) -> tuple[int, ...]:
    """A ``VER=`` release, ``0.0.2.5``, as (0, 0, 2, 5), to compare; ValueError if it is none."""
    return tuple(int(x) for x in version.split("."))


EOL: Final = b"\r\n"
"""Line terminator for both directions (§2.1 host side; PART 4 item 3 settles the reply side)."""

DEFAULT_FMT: Final = "{:.3f}"
"""Default float format for ASCII values (firmware digits are [U], §2.3; any format parses)."""

CPP_AXIS_FMT: Final = "{:12.3f}"
"""SDHLibrary-CPP's single-axis set format (``%12.3f``, §2.3), for byte-exact host imitation."""

CPP_VECTOR_FMT: Final = "{:.6f}"
"""SDHLibrary-CPP/-python all-axes set format (``%f``, §2.3)."""

DEFAULT_MAX_LINE: Final = 256
"""Longest accepted line in bytes, terminator excluded (a 9-value ``%f`` reply is ≈ 100)."""

RESYNC: Final = b"\r\n" * 17
"""Bytes that bring either stream parser back to a message boundary after arbitrary garbage.

Why it suffices: the longest binary message is 34 bytes. A frame whose 3 header bytes are all
garbage ends at most 31 bytes into ``RESYNC``; a frame whose header would include a CR or LF is
rejected at once (``nb_data_bytes`` 10/13 and ``nb_valid_params`` 10/13 are never valid). A line
in progress ends at the first LF. What is left of ``RESYNC`` after that is CR/LF only, which forms
blank lines, and ``RESYNC`` ends with LF. The controller parser reports those blank lines as
:class:`BlankLine` events (to be ignored); the reply parser drops them.
"""

_BINARY_MIN: Final = 0x80  # §2.6: all command codes are >= 0x80, so never printable ASCII
_HIGH: Final = re.compile(rb"[\x80-\xff]")  # a byte no line holds: where a binary frame starts
_STRIP: Final = "\r\n "  # §2.1 / PART 3 item 1: strip CR, LF and spaces around a line


class SdhError(IntEnum):
    """Firmware error codes, used in ``E<n>`` lines and as the binary status byte (§2.5)."""

    SUCCESS = 0
    NOT_AVAILABLE = 1
    NOT_INITIALIZED = 2
    ALREADY_RUNNING = 3
    FEATURE_NOT_SUPPORTED = 4
    INCONSISTENT_DATA = 5
    TIMEOUT = 6
    READ_ERROR = 7
    WRITE_ERROR = 8
    INSUFFICIENT_RESOURCES = 9
    CHECKSUM_ERROR = 10
    NOT_ENOUGH_PARAMS = 11
    NO_PARAMS_EXPECTED = 12
    CMD_UNKNOWN = 13
    CMD_FORMAT_ERROR = 14
    ACCESS_DENIED = 15
    ALREADY_OPEN = 16
    CMD_FAILED = 17
    CMD_ABORTED = 18
    INVALID_HANDLE = 19
    DEVICE_NOT_FOUND = 20
    DEVICE_NOT_OPENED = 21
    IO_ERROR = 22
    INVALID_PARAMETER = 23
    RANGE_ERROR = 24
    NO_DATAPIPE = 25
    INDEX_OUT_OF_BOUNDS = 26
    HOMING_ERROR = 27
    AXIS_DISABLED = 28
    OVER_TEMPERATURE = 29
    MAX_COMMANDS_EXCEEDED = 30
    INVALID_PASSWORD = 31
    MAX_COMMANDLINE_EXCEEDED = 32
    CRC_ERROR = 33
    NO_COMMAND = 34
    INTERNAL = 35
    UNKNOWN_ERROR = 36


class AxisState(IntEnum):
    """Per-axis value of the ``state`` command (§2.4, CPP ``eAxisState``)."""

    IDLE = 0
    POSITIONING = 1
    SPEED_MODE = 2
    NOT_INITIALIZED = 3
    CW_BLOCKED = 4
    CCW_BLOCKED = 5
    DISABLED = 6
    LIMITS_REACHED = 7


class BinaryCommand(IntEnum):
    """Binary command codes (§2.6, CPP ``sdh_command_codes.h``); the name is the ASCII keyword."""

    V = 0x80
    VEL = 129
    RVEL = 130
    POS = 131
    STATE = 132
    P = 133
    A = 134
    M = 135
    STOP = 136
    VP = 137
    CON = 138
    TPAP = 139
    TVAV = 140
    VLIM = 141
    ALIM = 142
    POS_SAVE = 143
    REF = 144
    TEMP = 145
    ID = 146
    SN = 147
    VER = 148
    VER_DATE = 149
    SOC = 150
    SOC_DATE = 151
    NUMAXIS = 152
    P_MIN = 153
    P_MAX = 154
    P_OFFSET = 155
    GET_DURATION = 156
    IGRIP = 157
    IHOLD = 158
    SELGRIP = 159
    GRIP = 160
    PID = 161
    KV = 162
    ILIM = 163
    POWER = 164
    DEMO = 165
    USER_ERRORS = 166
    TERMINAL = 167
    DEBUG = 168
    USE_FIXED_LENGTH = 169
    CHANGE_RS232 = 170
    CHANGE_CHANNEL = 171

    @property
    def keyword(self) -> str:
        """The matching ASCII keyword (lower-case name)."""
        return self.name.lower()


_CODES: Final = frozenset(int(c) for c in BinaryCommand)

BINARY_COMMANDS: Final[Mapping[str, BinaryCommand]] = MappingProxyType(
    {
        c.keyword: c
        for c in (
            BinaryCommand.P,
            BinaryCommand.POS,
            BinaryCommand.V,
            BinaryCommand.A,
            BinaryCommand.TPAP,
            BinaryCommand.TVAV,
            BinaryCommand.VEL,
            BinaryCommand.RVEL,
            BinaryCommand.STATE,
            BinaryCommand.ILIM,
            BinaryCommand.POWER,
        )
    }
)
"""The 11 commands SDHLibrary-CPP sends as binary frames (§2.6), keyed by ASCII keyword."""


class SdhProtocolError(ValueError):
    """Malformed input, with the firmware error code an emulator should answer (§2.5)."""

    def __init__(self, code: SdhError, message: str) -> None:
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message


# ---------------------------------------------------------------------------------------------
# Shared command table (§2.4)
# ---------------------------------------------------------------------------------------------


class ArgForm(Enum):
    """Which request forms of §2.3 a command accepts."""

    VECTOR = "vector"  # `kw`, `kw(i)`, and if settable `kw=v0,…,v6`, `kw(i)=v`
    AXIS_ONLY = "axis_only"  # `kw(i)`, `kw(i)=…` only (kv, pid: §2.4)
    SCALAR = "scalar"  # `kw` and/or `kw=a[,b]` (vp, con, selgrip, grip, properties)
    NONE = "none"  # bare `kw` only (m, stop, temp, ver, …)


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """One ASCII command of §2.4, shared by the driver (encoding) and emulator (validation).

    ``n_values`` is the value count of a set: 7 for the all-axes form of VECTOR commands (their
    per-axis set takes 1), the per-axis count for AXIS_ONLY, the count for SCALAR. ``readable``
    says whether the bare/``(i)`` get form is accepted. ``integer`` marks commands whose request
    values are integers (the host prints them with ``%d``); ``reply_integer`` those whose reply
    values all are (``POWER=0,…``, ``STATE=…``; not ``SELGRIP=<T>,<id>``). ``reply_values`` is
    the number of values in the reply (None: text or [U]). ``binary`` is the code SDHLibrary-CPP
    sends instead of the ASCII line (§2.6).
    """

    keyword: str
    form: ArgForm
    settable: bool = False
    n_values: int = 0
    readable: bool = True
    reply_values: int | None = None
    integer: bool = False
    reply_integer: bool = False
    binary: BinaryCommand | None = None

    @property
    def reply_keyword(self) -> str:
        """Upper-case echo the firmware puts before ``=`` (§2.3)."""
        return self.keyword.upper()


def _vector(kw: str, *, settable: bool, integer: bool = False) -> CommandSpec:
    return CommandSpec(
        kw,
        ArgForm.VECTOR,
        settable=settable,
        n_values=NUM_AXES,
        reply_values=NUM_AXES,
        integer=integer,
        reply_integer=integer,
        binary=BINARY_COMMANDS.get(kw),
    )


def _scalar(
    kw: str, n: int, *, integer: bool, readable: bool = True, reply: int | None = 1
) -> CommandSpec:
    # Integer scalars echo their integer, except selgrip whose reply starts with a duration.
    return CommandSpec(
        kw,
        ArgForm.SCALAR,
        settable=True,
        n_values=n,
        readable=readable,
        reply_values=reply,
        integer=integer,
        reply_integer=integer and reply != 2,
    )


def _bare(kw: str, reply: int | None, *, integer: bool = False) -> CommandSpec:
    return CommandSpec(kw, ArgForm.NONE, reply_values=reply, reply_integer=integer)


_SPECS: Final = (
    # Integer vectors: power/pos_save/ref are 0/1(/2) flags. The libraries send them with %f
    # (`power=1.000000,…`, §2.3) but quote `power=0,0,0,0,0,0,0` as actual firmware I/O (§2.3),
    # so the firmware takes both; we print ints and accept either.
    _vector("power", settable=True, integer=True),
    _vector("p", settable=True),
    _bare("m", 1),  # M=<T>; a trailing "s" is tolerated when parsing (open question 9)
    _bare("get_duration", 1),
    _bare("stop", None),  # reply text [U]
    _vector("pos", settable=False),
    _vector("vel", settable=False),
    _vector("rvel", settable=False),
    _vector("state", settable=False, integer=True),
    _vector("v", settable=True),
    _vector("a", settable=True),
    _vector("tpap", settable=True),
    _vector("tvav", settable=True),
    _vector("vlim", settable=False),
    _vector("alim", settable=False),
    _vector("p_min", settable=True),
    _vector("p_max", settable=True),
    _vector("p_offset", settable=True),
    # %d in both libraries (CPP vp()/con()/selgrip()/property(), PY property()):
    _scalar("vp", 1, integer=True),
    _scalar("con", 1, integer=True),
    _vector("ilim", settable=True),
    _vector("igrip", settable=True),
    _vector("ihold", settable=True),
    CommandSpec("kv", ArgForm.AXIS_ONLY, settable=True, n_values=1, reply_values=1),
    CommandSpec("pid", ArgForm.AXIS_ONLY, settable=True, n_values=3, reply_values=3),
    _bare("temp", 9),
    _bare("ver", None),
    _bare("ver_date", None),
    _bare("id", None),
    _bare("sn", None),
    _bare("soc", None),
    _bare("soc_date", None),
    _bare("numaxis", 1, integer=True),
    _scalar("selgrip", 1, integer=True, readable=False, reply=2),  # SELGRIP=<T>,<id>
    _scalar("grip", 2, integer=False, readable=False, reply=2),  # grip=%f,%f → GRIP=<T>,<close>
    _vector("pos_save", settable=True, integer=True),
    _vector("ref", settable=True, integer=True),
    _scalar("demo", 1, integer=True, reply=None),  # replies [U]
    _scalar("user_errors", 1, integer=True, reply=None),
    _scalar("terminal", 1, integer=True, reply=None),
    _scalar("debug", 1, integer=True, reply=None),
)

ASCII_COMMANDS: Final[Mapping[str, CommandSpec]] = MappingProxyType({s.keyword: s for s in _SPECS})
"""Every ASCII command of §2.4 by lower-case keyword."""


_AXIS_FORMS: Final = (ArgForm.VECTOR, ArgForm.AXIS_ONLY)  # the forms with an axis index


def _shape_error(
    spec: CommandSpec, axis: int | None, values: tuple[float, ...] | None
) -> tuple[SdhError, str] | None:
    """Check a request form against ``spec``; the error codes are our choice (§2.5 is [U]).

    Form not offered → CMD_FORMAT_ERROR; values for a read-only command → NO_PARAMS_EXPECTED;
    too few values (or a bare get of selgrip/grip) → NOT_ENOUGH_PARAMS; too many →
    CMD_FORMAT_ERROR; non-integral value for an integer command → INVALID_PARAMETER.
    """
    if axis is not None and spec.form not in _AXIS_FORMS:
        return SdhError.CMD_FORMAT_ERROR, f"{spec.keyword} has no per-axis form"
    if axis is None and spec.form is ArgForm.AXIS_ONLY:
        return SdhError.CMD_FORMAT_ERROR, f"{spec.keyword} needs an axis index"
    if values is None:
        if spec.readable:
            return None
        return SdhError.NOT_ENOUGH_PARAMS, f"{spec.keyword} needs values"
    if not spec.settable:
        return SdhError.NO_PARAMS_EXPECTED, f"{spec.keyword} takes no values"
    want = 1 if axis is not None and spec.form is ArgForm.VECTOR else spec.n_values
    if len(values) < want:
        return SdhError.NOT_ENOUGH_PARAMS, f"{spec.keyword} needs {want} values"
    if len(values) > want:
        return SdhError.CMD_FORMAT_ERROR, f"{spec.keyword} takes {want} values"
    if spec.integer and not all(float(v).is_integer() for v in values):
        return SdhError.INVALID_PARAMETER, f"{spec.keyword} takes integers"
    return None


# ---------------------------------------------------------------------------------------------
# ASCII encoding
# ---------------------------------------------------------------------------------------------

_IDENT_RE: Final = re.compile(r"[A-Za-z_][A-Za-z0-9_]*", re.ASCII)
_NUMBER: Final = r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
_NUMBER_RE: Final = re.compile(rf"\s*({_NUMBER})\s*", re.ASCII)
_REPLY_NUMBER_RE: Final = re.compile(rf"\s*({_NUMBER})\s*s?\s*", re.ASCII)

Values: TypeAlias = float | Sequence[float] | None


def _as_values(values: Values) -> tuple[float, ...] | None:
    if values is None:
        return None
    if type(values) is tuple or type(values) is list:  # the usual case: no ABC check
        return tuple(map(float, values))
    if isinstance(values, (float, Real)):
        return (float(values),)
    return tuple(float(v) for v in values)


def _format_number(value: float, fmt: str, integer: bool) -> str:
    if not math.isfinite(value):
        raise ValueError(f"cannot send non-finite value {value!r}")
    if integer:
        if not value.is_integer():
            raise ValueError(f"integer expected, got {value!r}")
        return str(int(value))
    return fmt.format(value)


def _check_axis(axis: int | None) -> None:
    if axis is not None and not 0 <= axis < NUM_AXES:
        raise ValueError(f"axis {axis} out of range 0..{NUM_AXES - 1}")


def encode_ascii(
    keyword: str, values: Values = None, *, axis: int | None = None, fmt: str = DEFAULT_FMT
) -> bytes:
    """Encode a host command line (§2.3 forms) terminated by ``\\r\\n``.

    ``values=None`` is a get (``p``, ``p(3)``); a number or sequence is a set (``p(3)=-45.000``,
    ``p=0.000,…``, ``vp=1``). Known keywords are checked against :data:`ASCII_COMMANDS` (raising
    ``ValueError`` for a form or value count the firmware would reject); commands flagged
    ``integer`` (power, state, vp, con, selgrip, pos_save, ref, demo, user_errors, terminal,
    debug) are printed as ints and must be integral. Other values use ``fmt``: the default
    ``{:.3f}``; :data:`CPP_AXIS_FMT` / :data:`CPP_VECTOR_FMT` imitate SDHLibrary-CPP exactly.
    Unknown keywords are encoded unchecked.
    """
    if _IDENT_RE.fullmatch(keyword) is None:
        raise ValueError(f"invalid keyword {keyword!r}")
    _check_axis(axis)
    vals = _as_values(values)
    spec = ASCII_COMMANDS.get(keyword.lower())
    if spec is not None and (err := _shape_error(spec, axis, vals)) is not None:
        raise ValueError(err[1])
    head = keyword if axis is None else f"{keyword}({axis})"
    if vals is None:
        return head.encode("ascii") + EOL
    integer = spec is not None and spec.integer
    body = ",".join([_format_number(v, fmt, integer) for v in vals])
    return f"{head}={body}".encode("ascii") + EOL


def encode_blank() -> bytes:
    """The connect handshake's blank command ``" \\r\\n"`` (§2.3, §2.8 step 1)."""
    return b" " + EOL


def encode_reply(
    keyword: str, values: Values | str, *, axis: int | None = None, fmt: str = DEFAULT_FMT
) -> bytes:
    """Encode a controller reply ``KEYWORD=v0,v1,…\\r\\n`` (§2.3, PART 3 item 2).

    The keyword is echoed in upper case, with ``(n)`` for single-axis forms. ``values`` may be a
    string (``VER=0.0.3.3``), a number or a sequence. Python ints, and every integral value of a
    command flagged ``reply_integer`` (``POWER=0,0,…``, ``STATE=…``), are printed with ``%d``;
    other numbers use ``fmt`` (the firmware's digits are [U], §2.3; hosts parse any format).
    ``values=None`` gives an empty body (``STOP=``; the real ``stop`` reply text is [U]).
    """
    if _IDENT_RE.fullmatch(keyword) is None:
        raise ValueError(f"invalid keyword {keyword!r}")
    head = keyword.upper() if axis is None else f"{keyword.upper()}({axis})"
    if isinstance(values, str):
        body = values
    else:
        spec = ASCII_COMMANDS.get(keyword.lower())
        integer = spec is not None and spec.reply_integer
        if values is None:
            raw: Sequence[float] = ()
        elif type(values) is tuple or type(values) is list:  # the usual case: no ABC check
            raw = values
        elif isinstance(values, (float, Real)):
            raw = (values,)
        else:
            raw = values
        body = ",".join([_format_reply_value(v, fmt, integer) for v in raw])
    line = f"{head}={body}"
    if not (line.isascii() and line.isprintable()):
        raise ValueError(f"reply must be printable ASCII: {line!r}")
    return line.encode("ascii") + EOL


def _format_reply_value(value: float, fmt: str, integer: bool) -> str:
    if type(value) is float:  # the usual case: no ABC check (a float is no Integral)
        return _format_number(value, fmt, integer and value.is_integer())
    if isinstance(value, Integral):
        return str(int(value))
    v = float(value)
    return _format_number(v, fmt, integer and v.is_integer())


def encode_error(code: int) -> bytes:
    """Encode an error line ``E<n>\\r\\n`` (§2.3, codes of §2.5)."""
    if not 0 <= int(code) <= 255:
        raise ValueError(f"error code {code} out of range")
    return f"E{int(code)}".encode("ascii") + EOL


def encode_debug(text: str) -> bytes:
    """Encode a debug/info line ``@text\\r\\n`` (§2.3; hosts skip these lines)."""
    line = "@" + text
    if not (line.isascii() and line.isprintable()):
        raise ValueError(f"debug text must be printable ASCII: {text!r}")
    return line.encode("ascii") + EOL


# ---------------------------------------------------------------------------------------------
# ASCII parsing
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BlankLine:
    """An empty (or all-space) command line, e.g. the connect handshake ``" \\r\\n"`` (§2.3).

    What the firmware answers is [U]; PART 4 item 4 allows silence or an immediate answer (e.g.
    ``E34``). Our choice for the emulator: stay silent (the suggested reply is empty).
    """


BLANK: Final = BlankLine()


@dataclass(frozen=True, slots=True)
class AsciiCommand:
    """A parsed host command line (§2.3): ``values`` is None for a get, a tuple for a set."""

    keyword: str
    axis: int | None = None
    values: tuple[float, ...] | None = None

    @property
    def reply_keyword(self) -> str:
        """Upper-case echo keyword the reply must start with (§2.3)."""
        return self.keyword.upper()


def _parse_axis(text: str, num_axes: int) -> int:
    text = text.strip()
    if re.fullmatch(r"[+-]?[0-9]+", text, re.ASCII) is None:
        raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, f"bad axis index {text!r}")
    # More than 9 digits is out of range anyway; avoids int()'s huge-string limit.
    axis = int(text) if len(text) <= 10 else num_axes
    if not 0 <= axis < num_axes:
        raise SdhProtocolError(SdhError.INDEX_OUT_OF_BOUNDS, f"axis {text} out of range")
    return axis


def _parse_values(text: str) -> tuple[float, ...]:
    if not text.strip():
        return ()
    out = []
    for field in text.split(","):
        m = _NUMBER_RE.fullmatch(field)
        value = float(m[1]) if m else math.nan
        if not math.isfinite(value):
            raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, f"bad number {field!r}")
        out.append(value)
    return tuple(out)


_COMMAND_RE: Final = re.compile(
    r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:\(([^()]*)\)\s*)?(?:=(.*))?", re.ASCII | re.DOTALL
)


def parse_command_line(
    line: str,
    *,
    commands: Mapping[str, CommandSpec] | None = ASCII_COMMANDS,
    num_axes: int = NUM_AXES,
) -> AsciiCommand | BlankLine:
    """Parse one host command line (controller side, §2.3, PART 3 item 1).

    Leading/trailing CR, LF and spaces are stripped; spaces around ``=``, ``(``, ``)``, ``,`` and
    ``%12.3f`` padding are accepted; the keyword is lower-cased (firmware case-sensitivity is
    [U]). An empty line returns :data:`BLANK`. With ``commands`` (default the §2.4 table) the
    keyword and form are validated too; ``commands=None`` checks syntax only.

    Raises :class:`SdhProtocolError`: no keyword → CMD_UNKNOWN; unknown keyword → CMD_UNKNOWN;
    malformed syntax or number (including inf/nan) → CMD_FORMAT_ERROR; axis outside
    ``0…num_axes-1`` → INDEX_OUT_OF_BOUNDS; form/count errors as in :class:`CommandSpec`.
    """
    text = line.strip(_STRIP)
    if not text:
        return BLANK
    m = _COMMAND_RE.fullmatch(text)
    if m is None:
        code = SdhError.CMD_FORMAT_ERROR if _IDENT_RE.match(text) else SdhError.CMD_UNKNOWN
        raise SdhProtocolError(code, f"cannot parse {text[:40]!r}")
    keyword = m[1].lower()
    spec = None if commands is None else commands.get(keyword)
    if commands is not None and spec is None:
        raise SdhProtocolError(SdhError.CMD_UNKNOWN, f"unknown command {keyword!r}")
    if m[2] is not None and spec is not None and spec.form not in _AXIS_FORMS:
        # no per-axis form at all: that, whatever the index (temp(0) and temp(8) alike)
        raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, f"{keyword} has no per-axis form")
    axis = None if m[2] is None else _parse_axis(m[2], num_axes)
    values = None if m[3] is None else _parse_values(m[3])
    if spec is not None and (err := _shape_error(spec, axis, values)) is not None:
        raise SdhProtocolError(*err)
    return AsciiCommand(keyword, axis, values)


@dataclass(frozen=True, slots=True)
class Reply:
    """A reply line (§2.3). ``keyword`` is upper-cased; ``text`` is everything after ``=``.

    ``values`` holds the comma-separated numbers of ``text`` (a trailing ``s`` unit is tolerated,
    open question 9), or ``()`` if ``text`` is not a number list (``VER=0.0.3.3``). A line
    without ``=`` (e.g. the [U] reply of ``stop``) gives ``keyword=""`` and the line as ``text``.
    """

    keyword: str
    axis: int | None
    values: tuple[float, ...]
    text: str


@dataclass(frozen=True, slots=True)
class ErrorLine:
    """A firmware error line ``E<n>`` (§2.3); ``error`` is None for codes outside §2.5."""

    code: int
    error: SdhError | None


@dataclass(frozen=True, slots=True)
class DebugLine:
    """A debug/info line; ``text`` excludes the leading ``@`` (§2.3)."""

    text: str


@dataclass(frozen=True, slots=True)
class Garbage:
    """Bytes the host-side parsers could not use, with the reason (never raised)."""

    data: bytes
    reason: str


_ERROR_RE: Final = re.compile(r"E\s*([0-9]{1,9})(?:[^0-9A-Za-z_=].*)?", re.ASCII | re.DOTALL)
_REPLY_RE: Final = re.compile(
    r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:\(\s*([0-9]{1,9})\s*\)\s*)?=(.*)", re.ASCII | re.DOTALL
)


def _reply_values(text: str) -> tuple[float, ...]:
    if not text.strip():
        return ()
    out = []
    for field in text.split(","):
        m = _REPLY_NUMBER_RE.fullmatch(field)
        if m is None:
            return ()
        out.append(float(m[1]))
    return tuple(out)


def parse_reply_line(line: str) -> Reply | ErrorLine | DebugLine | Garbage | None:
    """Interpret one reply line (host side, §2.3); None for a blank line.

    ``@…`` → :class:`DebugLine`; ``E<n>`` (as the host's ``sscanf("%d")`` reads it) →
    :class:`ErrorLine`; ``KW=…``/``KW(n)=…`` → :class:`Reply`; an ``=`` line with a malformed
    keyword or a non-printable line → :class:`Garbage`.
    """
    text = line.strip(_STRIP)
    if not text:
        return None
    if not (text.isascii() and text.isprintable()):
        return Garbage(text.encode("latin-1", "replace"), "non-printable reply line")
    if text[0] == "@":
        return DebugLine(text[1:])
    if (m := _ERROR_RE.fullmatch(text)) is not None:
        code = int(m[1])
        return ErrorLine(code, SdhError(code) if code <= max(SdhError) else None)
    if "=" not in text:
        return Reply("", None, (), text)
    if (m := _REPLY_RE.fullmatch(text)) is None:
        return Garbage(text.encode("ascii"), "malformed reply keyword")
    axis = None if m[2] is None else int(m[2])
    body = m[3].strip()
    return Reply(m[1].upper(), axis, _reply_values(body), body)


# ---------------------------------------------------------------------------------------------
# Binary frames (§2.6, PART 4 items 1–2)
# ---------------------------------------------------------------------------------------------

_F7: Final = struct.Struct(f"<{NUM_AXES}f")  # LE f32 vector (§0 conventions)
_CRC: Final = struct.Struct("<H")


def binary_request_size(with_values: bool, with_crc: bool) -> int:
    """Total request length: get 5 / 3 bytes, set 33 / 31 bytes (serial / TCP, PART 4 item 1)."""
    return 3 + (_F7.size if with_values else 0) + (2 if with_crc else 0)


def binary_reply_size(with_crc: bool) -> int:
    """Total reply length the host reads: 34 with CRC (serial), 32 without (TCP)."""
    return 4 + _F7.size + (2 if with_crc else 0)


def _request_crc_form(nb: int, nvalid: int) -> bool | None:
    """CRC present? from ``nb_data_bytes − 1 − 4·nb_valid ∈ {0, 2}`` (PART 4 item 1).

    ``nb_valid`` must be 0 (get) or 7 (set): the host never sends anything else (§2.6).
    """
    if nvalid not in (0, NUM_AXES):
        return None
    return {0: False, 2: True}.get(nb - 1 - 4 * nvalid)


def _reply_crc_form(nb: int, nvalid: int) -> bool | None:
    """Reply equivalent: ``nb_data_bytes − 2 − 4·nb_valid ∈ {0, 2}`` (the status byte adds 1).

    ``nb_valid`` must be 7 because the host reads a fixed 34/32 bytes (§2.6), so the accepted
    ``nb_data_bytes`` are 32 (serial, PART 4 item 2) and 30 (TCP, derived [I]).
    """
    if nvalid != NUM_AXES:
        return None
    return {0: False, 2: True}.get(nb - 2 - 4 * nvalid)


def _with_crc(head: bytes, with_crc: bool) -> bytes:
    return head + _CRC.pack(crc16(head)) if with_crc else head


def _pack(values: Sequence[float]) -> bytes:
    vals = tuple(float(v) for v in values)
    if len(vals) != NUM_AXES:
        raise ValueError(f"binary frames carry exactly {NUM_AXES} values, got {len(vals)}")
    try:
        return _F7.pack(*vals)
    except OverflowError as exc:
        raise ValueError("value outside float32 range") from exc


def _command(code: int) -> BinaryCommand:
    if code not in _CODES:
        raise SdhProtocolError(SdhError.CMD_UNKNOWN, f"unknown binary command 0x{code:02x}")
    return BinaryCommand(code)


def _check_crc(frame: bytes) -> None:
    (got,) = _CRC.unpack_from(frame, len(frame) - 2)
    want = crc16(frame[:-2])
    if got != want:
        raise SdhProtocolError(SdhError.CRC_ERROR, f"CRC 0x{got:04x}, expected 0x{want:04x}")


def encode_binary_request(
    cmd: BinaryCommand | int, values: Sequence[float] | None = None, *, with_crc: bool = True
) -> bytes:
    """Encode a host request ``cmd | nb_data_bytes | nb_valid | [7×f32] | [CRC16 LE]`` (§2.6).

    ``values=None`` is a get (5 bytes serial, 3 TCP); 7 values a set (33 / 31). ``with_crc``
    is True on serial lines, False over TCP (PART 4 item 1).
    """
    code = BinaryCommand(cmd)
    payload = b"" if values is None else _pack(values)
    nvalid = 0 if values is None else NUM_AXES
    nb = 1 + len(payload) + (2 if with_crc else 0)
    return _with_crc(bytes((code, nb, nvalid)) + payload, with_crc)


def encode_binary_reply(
    cmd: BinaryCommand | int,
    status: SdhError | int = SdhError.SUCCESS,
    values: Sequence[float] | None = None,
    *,
    with_crc: bool = True,
) -> bytes:
    """Encode a controller reply ``cmd | nb | 7 | status | 7×f32 | [CRC16 LE]`` (§2.6).

    Always 7 values (``None`` sends zeros, e.g. with an error status); ``nb_data_bytes`` is 32
    with CRC (exactly what the serial host expects, PART 4 item 2) and 30 without (TCP): 34 / 32
    bytes in all.
    """
    code = BinaryCommand(cmd)
    if not 0 <= int(status) <= 255:
        raise ValueError(f"status {status} out of range")
    payload = _pack(values if values is not None else (0.0,) * NUM_AXES)
    nb = 2 + len(payload) + (2 if with_crc else 0)
    return _with_crc(bytes((code, nb, NUM_AXES, int(status))) + payload, with_crc)


@dataclass(frozen=True, slots=True)
class BinaryRequest:
    """A binary host request (§2.6): ``values`` None for a get, 7 floats for a set."""

    cmd: BinaryCommand
    values: tuple[float, ...] | None
    with_crc: bool

    def encode(self) -> bytes:
        """Bytes of this request (inverse of :meth:`decode`)."""
        return encode_binary_request(self.cmd, self.values, with_crc=self.with_crc)

    @classmethod
    def decode(cls, frame: bytes, *, crc: bool | None = None) -> BinaryRequest:
        """Decode one complete request; ``crc=None`` detects the form from the header.

        Raises :class:`SdhProtocolError` (CMD_UNKNOWN, CMD_FORMAT_ERROR, CRC_ERROR).
        """
        frame = bytes(frame)
        if len(frame) < 3:
            raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, "binary request too short")
        cmd = _command(frame[0])
        form = _request_crc_form(frame[1], frame[2])
        if form is None or (crc is not None and form != crc) or len(frame) != 2 + frame[1]:
            raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, "inconsistent binary request")
        if form:
            _check_crc(frame)
        values = _F7.unpack_from(frame, 3) if frame[2] else None
        return cls(cmd, values, form)


@dataclass(frozen=True, slots=True)
class BinaryReply:
    """A binary controller reply (§2.6); ``status`` is the raw byte (table §2.5)."""

    cmd: BinaryCommand
    status: int
    values: tuple[float, ...]
    with_crc: bool

    @property
    def error(self) -> SdhError | None:
        """``status`` as :class:`SdhError` (None if outside the table)."""
        return SdhError(self.status) if self.status <= max(SdhError) else None

    @property
    def ok(self) -> bool:
        """True for status SUCCESS; the host retries otherwise (PART 4 item 2)."""
        return self.status == SdhError.SUCCESS

    def encode(self) -> bytes:
        """Bytes of this reply (inverse of :meth:`decode`)."""
        return encode_binary_reply(self.cmd, self.status, self.values, with_crc=self.with_crc)

    @classmethod
    def decode(cls, frame: bytes, *, crc: bool | None = None) -> BinaryReply:
        """Decode one complete reply; ``crc=None`` detects the form from ``nb_data_bytes``.

        Raises :class:`SdhProtocolError` (CMD_UNKNOWN, CMD_FORMAT_ERROR, CRC_ERROR).
        """
        frame = bytes(frame)
        if len(frame) < 4:
            raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, "binary reply too short")
        cmd = _command(frame[0])
        form = _reply_crc_form(frame[1], frame[2])
        if form is None or (crc is not None and form != crc) or len(frame) != 2 + frame[1]:
            raise SdhProtocolError(SdhError.CMD_FORMAT_ERROR, "inconsistent binary reply")
        if form:
            _check_crc(frame)
        return cls(cmd, frame[3], _F7.unpack_from(frame, 4), form)


# ---------------------------------------------------------------------------------------------
# Stream parsers
# ---------------------------------------------------------------------------------------------


class ErrorSource(StrEnum):
    """What a :class:`ProtocolErrorEvent` concerns, i.e. how an emulator should answer."""

    LINE = "line"  # a complete command line: answer E<n>
    FRAME = "frame"  # a correctly framed binary request: answer a binary reply with status
    GARBAGE = "garbage"  # bytes that frame nothing: stay silent (PART 4 item 11)


@dataclass(frozen=True, slots=True)
class ProtocolErrorEvent:
    """Malformed host input seen by :class:`HostStreamParser` (never raised)."""

    code: SdhError
    message: str
    data: bytes
    source: ErrorSource
    binary_cmd: BinaryCommand | None = None
    with_crc: bool | None = None

    def suggested_reply(self) -> bytes:
        """The answer that keeps a host in step: ``E<n>`` line, 34/32-byte status reply, or none.

        A stray byte on a serial line misaligns every later binary reply (PART 4 item 11), so
        garbage gets no answer.
        """
        if self.source is ErrorSource.LINE:
            return encode_error(self.code)
        if self.source is ErrorSource.FRAME and self.binary_cmd is not None:
            return encode_binary_reply(self.binary_cmd, self.code, with_crc=bool(self.with_crc))
        return b""


ReplyEvent: TypeAlias = Reply | ErrorLine | DebugLine | Garbage | BinaryReply
HostEvent: TypeAlias = AsciiCommand | BinaryRequest | BlankLine | ProtocolErrorEvent
Event: TypeAlias = ReplyEvent | HostEvent

E = TypeVar("E")


def _printable(raw: bytes) -> str | None:
    text = raw.decode("latin-1").strip(_STRIP)
    return text if text.isascii() and text.isprintable() else None


class _Framer(ABC, Generic[E]):
    """Split a byte stream into lines and (optionally) binary frames at message boundaries."""

    def __init__(self, *, max_line: int, binary: bool) -> None:
        if max_line < 1:
            raise ValueError("max_line must be positive")
        self._max_line = max_line
        self._binary = binary
        self._buf = bytearray()
        self._discarding = False  # inside an over-long line, dropping up to its LF

    def feed(self, data: bytes | bytearray | memoryview) -> list[E]:
        """Add received bytes; return the events they complete, in stream order."""
        self._buf += data
        events: list[E] = []
        while self._step(events):
            pass
        return events

    def reset(self) -> None:
        """Forget buffered bytes, e.g. after the I/O layer drained the line on a timeout."""
        self._buf.clear()
        self._discarding = False

    @property
    def buffered(self) -> int:
        """Bytes held for an incomplete line or frame."""
        return len(self._buf)

    def flush(self) -> bytes:
        """Drop and return the bytes held for an incomplete line or frame: the I/O layer knows
        its rest is not coming (e.g. nothing more arrived for a while)."""
        held = bytes(self._buf)
        self.reset()
        return held

    def _step(self, events: list[E]) -> bool:
        buf = self._buf
        if self._discarding:
            idx = buf.find(b"\n")
            high = self._high(buf, len(buf) if idx < 0 else idx)
            if high is not None:  # a frame starts: the dropped line ends there
                del buf[:high]
                self._discarding = False
                return True
            if idx < 0:
                buf.clear()
                return False
            del buf[: idx + 1]
            self._discarding = False
            return True
        if not buf:
            return False
        if buf[0] == 0x0D:
            # A CR at a boundary can only be the tail of a "\n\r" terminator (§2.1); dropping it
            # keeps a following binary frame intact (the C++ host breaks here, PART 4 item 3).
            del buf[:1]
            return True
        if self._binary and buf[0] >= _BINARY_MIN:
            got = self._frame(buf)
            if got is None:
                return False
            used, event = got
            del buf[:used]
            events.append(event)
            return True
        idx = buf.find(b"\n", 0, self._max_line + 1)
        high = self._high(buf, min(len(buf), self._max_line + 1) if idx < 0 else idx)
        if high is not None:  # the line was cut short by a frame (a stray byte, a lost one)
            events.append(self._broken(bytes(buf[:high])))
            del buf[:high]
            return True
        if idx < 0:
            if len(buf) <= self._max_line:
                return False
            events.append(self._overflow(bytes(buf[: self._max_line])))
            self._discarding = True
            return True
        line = bytes(buf[:idx])
        del buf[: idx + 1]
        events.extend(self._line(line))
        return True

    def _high(self, buf: bytearray, end: int) -> int | None:
        """Where the first byte ≥ 0x80 before ``end`` is, if frames may come (else None)."""
        if not self._binary:
            return None
        m = _HIGH.search(buf, 0, end)
        return None if m is None else m.start()

    @abstractmethod
    def _line(self, raw: bytes) -> list[E]: ...

    @abstractmethod
    def _overflow(self, prefix: bytes) -> E: ...

    @abstractmethod
    def _broken(self, prefix: bytes) -> E:
        """The event for the start of a line that a binary frame cut short."""

    @abstractmethod
    def _frame(self, buf: bytearray) -> tuple[int, E] | None:
        """(bytes consumed, event) for the frame at ``buf[0]``, or None to wait for more."""


def _nb_choices(crc: bool | None, sizes: dict[bool, int]) -> frozenset[int]:
    return frozenset(v for k, v in sizes.items() if crc is None or k == crc)


class ReplyParser(_Framer[ReplyEvent]):
    """Host-side parser of everything the SDH sends: ASCII reply lines and binary replies.

    At a message boundary a byte ≥ 0x80 starts a binary reply (§2.6), whose length follows from
    ``nb_data_bytes`` (32 → CRC, 30 → none; ``crc`` forces one form, None detects per frame);
    anything else starts a line. Blank lines are dropped; ``@`` lines are reported as
    :class:`DebugLine` unless ``report_debug`` is False. Over-long lines, non-printable lines,
    implausible headers (one byte each) and CRC failures (whole frame) become :class:`Garbage`.
    See the module docstring and :data:`RESYNC` for recovery. ``binary=False`` gives a pure
    line parser.
    """

    def __init__(
        self,
        *,
        crc: bool | None = None,
        max_line: int = DEFAULT_MAX_LINE,
        report_debug: bool = True,
        binary: bool = True,
    ) -> None:
        super().__init__(max_line=max_line, binary=binary)
        self._crc = crc
        self._report_debug = report_debug
        self._nb = _nb_choices(crc, {True: 32, False: 30})

    def _line(self, raw: bytes) -> list[ReplyEvent]:
        if _printable(raw) is None:
            return [Garbage(raw, "non-printable reply line")]
        event = parse_reply_line(raw.decode("ascii"))
        if event is None or (isinstance(event, DebugLine) and not self._report_debug):
            return []
        return [event]

    def _overflow(self, prefix: bytes) -> ReplyEvent:
        return Garbage(prefix, f"line longer than {self._max_line} bytes")

    def _broken(self, prefix: bytes) -> ReplyEvent:
        return Garbage(prefix, "a line cut short by a binary reply")

    def _frame(self, buf: bytearray) -> tuple[int, ReplyEvent] | None:
        if buf[0] not in _CODES:
            return 1, Garbage(bytes(buf[:1]), f"unknown binary command 0x{buf[0]:02x}")
        if len(buf) < 2:
            return None
        if buf[1] not in self._nb:
            return 1, Garbage(bytes(buf[:1]), f"implausible reply nb_data_bytes {buf[1]}")
        if len(buf) < 3:
            return None
        if buf[2] != NUM_AXES:
            return 1, Garbage(bytes(buf[:1]), f"implausible reply nb_valid_params {buf[2]}")
        total = 2 + buf[1]
        if len(buf) < total:
            return None
        frame = bytes(buf[:total])
        try:
            return total, BinaryReply.decode(frame, crc=self._crc)
        except SdhProtocolError as exc:
            return total, Garbage(frame, f"binary reply: {exc.message}")


class HostStreamParser(_Framer[HostEvent]):
    """Controller-side parser of everything a host sends: ASCII command lines and binary frames.

    Binary requests are recognised by a byte ≥ 0x80 at a message boundary (§2.6) and sized from
    ``nb_data_bytes``; ``crc`` True (serial) / False (TCP) forces a form, None detects it per
    frame from ``nb_data_bytes − 1 − 4·nb_valid ∈ {0, 2}`` (PART 4 item 1). Events:

    * :class:`AsciiCommand` — a valid line (validated against ``commands``);
    * :class:`BlankLine` — an empty line (the connect handshake, PART 4 item 4: stay silent);
    * :class:`BinaryRequest` — a valid frame;
    * :class:`ProtocolErrorEvent` — bad line (source LINE, ``E<n>``), over-long line (LINE,
      MAX_COMMANDLINE_EXCEEDED; the rest up to LF is dropped), framed request with a bad CRC
      (FRAME, CRC_ERROR; the whole frame is dropped so the next one parses at once), or an
      implausible header (GARBAGE: one byte dropped, scanning resumes at the next byte).

    See the module docstring and :data:`RESYNC` for recovery after garbage.
    """

    def __init__(
        self,
        *,
        crc: bool | None = None,
        max_line: int = DEFAULT_MAX_LINE,
        commands: Mapping[str, CommandSpec] | None = ASCII_COMMANDS,
        num_axes: int = NUM_AXES,
        binary: bool = True,
    ) -> None:
        super().__init__(max_line=max_line, binary=binary)
        self._crc = crc
        self._commands = commands
        self._num_axes = num_axes
        self._nb = _nb_choices(crc, {True: 3, False: 1}) | _nb_choices(crc, {True: 31, False: 29})

    def _line(self, raw: bytes) -> list[HostEvent]:
        text = _printable(raw)
        if text is None:
            return [
                ProtocolErrorEvent(
                    SdhError.CMD_FORMAT_ERROR, "non-printable command line", raw, ErrorSource.LINE
                )
            ]
        try:
            return [parse_command_line(text, commands=self._commands, num_axes=self._num_axes)]
        except SdhProtocolError as exc:
            return [ProtocolErrorEvent(exc.code, exc.message, raw, ErrorSource.LINE)]

    def _overflow(self, prefix: bytes) -> HostEvent:
        return ProtocolErrorEvent(
            SdhError.MAX_COMMANDLINE_EXCEEDED,
            f"line longer than {self._max_line} bytes",
            prefix,
            ErrorSource.LINE,
        )

    def _broken(self, prefix: bytes) -> HostEvent:
        # never answered: the host speaks binary now, an E<n> line would misalign its replies
        return ProtocolErrorEvent(SdhError.CMD_FORMAT_ERROR, "a line cut short by a binary "
                                  "request", prefix, ErrorSource.GARBAGE)  # fmt: skip

    def _garbage(self, buf: bytearray, code: SdhError, message: str) -> tuple[int, HostEvent]:
        return 1, ProtocolErrorEvent(code, message, bytes(buf[:1]), ErrorSource.GARBAGE)

    def _frame(self, buf: bytearray) -> tuple[int, HostEvent] | None:
        if buf[0] not in _CODES:
            return self._garbage(
                buf, SdhError.CMD_UNKNOWN, f"unknown binary command 0x{buf[0]:02x}"
            )
        if len(buf) < 2:
            return None
        if buf[1] not in self._nb:
            return self._garbage(
                buf, SdhError.CMD_FORMAT_ERROR, f"implausible request nb_data_bytes {buf[1]}"
            )
        if len(buf) < 3:
            return None
        form = _request_crc_form(buf[1], buf[2])
        if form is None:
            return self._garbage(
                buf, SdhError.CMD_FORMAT_ERROR, f"implausible request nb_valid_params {buf[2]}"
            )
        total = 2 + buf[1]
        if len(buf) < total:
            return None
        frame = bytes(buf[:total])
        try:
            return total, BinaryRequest.decode(frame, crc=self._crc)
        except SdhProtocolError as exc:
            return total, ProtocolErrorEvent(
                exc.code, exc.message, frame, ErrorSource.FRAME, BinaryCommand(frame[0]), form
            )
