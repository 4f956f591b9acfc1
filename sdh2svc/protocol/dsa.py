"""Sans-I/O codec for the SCHUNK DSACON32m tactile-sensor controller (protocols.md PART 1, 3, 4).

Design (h11 / wsproto style): this module never touches a port, a socket, a clock or a task.
The caller moves bytes; the module turns them into typed values and back:

* :class:`PacketParser` is fed whatever bytes arrived (any chunking) and returns events —
  :class:`Packet`, or the error/info events :class:`BadCrc`, :class:`Oversized`,
  :class:`GarbageSkipped`, :class:`BootNoise`. It never raises on input and keeps only a bounded
  tail of unparsed bytes.
* Host side: the command encoders (:func:`configure_acquisition`, :func:`query_matrix_info`, …)
  return complete packets; responses are decoded with ``ControllerInfo.decode(packet.payload)``
  etc. and frames with :func:`decode_frame_payload`.
* Device side (emulator): :func:`decode_command` turns a received :class:`Packet` into a
  ``Command`` dataclass; replies are built with :func:`encode_response` from the same response
  dataclasses.

Every multi-byte field is little-endian (protocols.md §0). Items the sources could not confirm
([U] in protocols.md) are parameters or are called out in the docstring that relies on them.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields
from enum import IntEnum, IntFlag
from typing import Any, ClassVar, NamedTuple, Protocol, Self, TypeAlias

import numpy as np
import numpy.typing as npt

from sdh2svc.protocol.crc import crc16

__all__ = [
    "DEFAULT_MAX_PAYLOAD",
    "PREAMBLE",
    "SDH2_MATRIX_SHAPES",
    "SDH2_NB_CELLS",
    "TEXEL_MAX",
    "THRESHOLD_SINCE",
    "AcqFlag",
    "AdjustFlag",
    "BadCrc",
    "BootNoise",
    "Command",
    "ConfigureAcquisition",
    "ControllerInfo",
    "DescriptorKind",
    "DescriptorString",
    "DsaError",
    "ErrorReply",
    "Event",
    "Frame",
    "FrameError",
    "GarbageSkipped",
    "GetSensitivityInfo",
    "GetThreshold",
    "HasCells",
    "Loop",
    "MatrixInfo",
    "MatrixMask",
    "MatrixShape",
    "Oversized",
    "Packet",
    "PacketId",
    "PacketParser",
    "ProtocolError",
    "QueryControllerInfo",
    "QueryControllerState",
    "QueryMatrixInfo",
    "QuerySensorInfo",
    "ReadDescriptorString",
    "ReadMatrixMask",
    "SensitivityInfo",
    "SensorInfo",
    "SetSensitivity",
    "SetThreshold",
    "ThresholdInfo",
    "UnknownCommand",
    "configure_acquisition",
    "decode_command",
    "decode_frame_payload",
    "encode_command",
    "encode_frame_payload",
    "encode_packet",
    "encode_response",
    "get_sensitivity_info",
    "get_threshold",
    "loop",
    "query_controller_info",
    "query_controller_state",
    "query_matrix_info",
    "query_sensor_info",
    "read_descriptor_string",
    "read_matrix_mask",
    "rle_decode",
    "rle_encode",
    "set_sensitivity",
    "set_threshold",
    "single_frame_bug",
    "split_matrices",
    "texel_offsets",
]

# ---------------------------------------------------------------------------------------------
# Identifiers (protocols.md §1.3)
# ---------------------------------------------------------------------------------------------


class PacketId(IntEnum):
    """Packet / command IDs (protocols.md §1.3). A response carries the ID of its command."""

    FULL_FRAME = 0x00
    QUERY_CONTROLLER_CONFIGURATION = 0x01
    QUERY_SENSOR_CONFIGURATION = 0x02
    CONFIGURE_DATA_ACQUISITION = 0x03
    READ_MATRIX_MASK = 0x04
    READ_DESCRIPTOR_STRING = 0x05
    LOOP = 0x06
    QUERY_CONTROLLER_STATE = 0x0A
    QUERY_MATRIX_CONFIGURATION = 0x0B
    SET_PROPERTIES_SAMPLE_RATE = 0x0C
    SET_PROPERTIES_CONTROL_VECTOR_FOR_MATRIX = 0x0D
    GET_PROPERTIES_CONTROL_VECTOR_OF_MATRIX = 0x0E
    ADJUST_MATRIX_SENSITIVITY = 0x0F
    QUERY_CONTROLLER_FEATURES = 0x10
    GET_SENSITIVITY_ADJUSTMENT_INFO = 0x12
    SET_MATRIX_THRESHOLD = 0x13
    GET_MATRIX_THRESHOLD = 0x14
    SET_DYNAMIC_MASK = 0xAB


class DsaError(IntEnum):
    """Error codes, the u16 that starts most responses (protocols.md §1.3, second table)."""

    E_SUCCESS = 0
    E_NOT_AVAILABLE = 1
    E_NO_SENSOR = 2
    E_NOT_INITIALIZED = 3
    E_ALREADY_RUNNING = 4
    E_FEATURE_NOT_SUPPORTED = 5
    E_INCONSISTENT_DATA = 6
    E_TIMEOUT = 7
    E_READ_ERROR = 8
    E_WRITE_ERROR = 9
    E_INSUFFICIENT_RESOURCES = 10
    E_CHECKSUM_ERROR = 11
    E_CMD_NOT_ENOUGH_PARAMS = 12
    E_CMD_UNKNOWN = 13
    E_CMD_FORMAT_ERROR = 14
    E_ACCESS_DENIED = 15
    E_ALREADY_OPEN = 16
    E_CMD_FAILED = 17
    E_CMD_ABORTED = 18
    E_INVALID_HANDLE = 19
    E_DEVICE_NOT_FOUND = 20
    E_DEVICE_NOT_OPENED = 21
    E_IO_ERROR = 22
    E_INVALID_PARAMETER = 23
    E_INDEX_OUT_OF_BOUNDS = 24
    E_CMD_PENDING = 25
    E_OVERRUN = 26
    E_RANGE_ERROR = 27


class AcqFlag(IntFlag):
    """Flags byte of CONFIGURE_DATA_ACQUISITION (protocols.md §1.6)."""

    RLE = 0x01
    RISING_HIGH = 0x08  # trigger bits: commented out in every host library
    LEVEL_TRIGGER = 0x10
    INTERNAL_TRIGGER = 0x20  # RobWork sends 0xA0 / 0xA1
    SINGLE_SHOT = 0x40  # never set by any host
    ENABLE = 0x80


class AdjustFlag(IntFlag):
    """Flags byte of sensitivity (0x0F) and threshold (0x13) writes (protocols.md §1.4.4-5)."""

    RESET = 0x01
    ALL_MATRICES = 0x02
    PERSISTENT = 0x80


class DescriptorKind(IntEnum):
    """Type byte of READ_DESCRIPTOR_STRING (protocols.md §1.3)."""

    SENSOR = 0
    MATRIX = 1


class ProtocolError(ValueError):
    """A payload that does not fit its layout.

    ``code`` is the :class:`DsaError` a device would answer with (the real controller's answer to
    malformed commands is [U], protocols.md §1.3 / open question 6); ``packet_id`` is the ID of
    the offending packet when known, so an emulator can reply under the same ID.
    """

    def __init__(
        self,
        message: str,
        code: DsaError = DsaError.E_CMD_FORMAT_ERROR,
        packet_id: int | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.packet_id = packet_id


class FrameError(ProtocolError):
    """A full-frame payload whose texel count does not match ``nb_cells`` (protocols.md §1.5)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, DsaError.E_INCONSISTENT_DATA, PacketId.FULL_FRAME)


# ---------------------------------------------------------------------------------------------
# Geometry constants (protocols.md §1.8, §1.10)
# ---------------------------------------------------------------------------------------------


class MatrixShape(NamedTuple):
    """Cell counts of one tactile matrix; ``shape`` is the numpy (rows, cols) = (y, x) shape."""

    cells_x: int
    cells_y: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.cells_y, self.cells_x)

    @property
    def nb_cells(self) -> int:
        return self.cells_x * self.cells_y


#: SDH2 layout, matrix m = 2·finger + (0 proximal | 1 distal), 6×14 and 6×13 (protocols.md §1.8).
SDH2_MATRIX_SHAPES: tuple[MatrixShape, ...] = (MatrixShape(6, 14), MatrixShape(6, 13)) * 3
SDH2_NB_CELLS = sum(s.nb_cells for s in SDH2_MATRIX_SHAPES)  # 486
#: Largest texel value: 12-bit converter, and the RLE value field is 12 bits (protocols.md §1.8).
TEXEL_MAX = 0x0FFF
#: Largest payload the host accepts: an uncompressed SDH2 frame (protocols.md PART 4 item 16).
DEFAULT_MAX_PAYLOAD = 5 + 2 * SDH2_NB_CELLS

#: Oldest firmware with the threshold commands 0x13/0x14 (SDHLibrary-CPP refuses them below).
THRESHOLD_SINCE = 268


def single_frame_bug(sw_version: int) -> bool:
    """Whether a controller reporting ``sw_version`` answers a pull request ("rate 0, acq on")
    with a stream at its maximum rate instead of one frame: releases up to and including 288
    except 269 (SDHLibrary-CPP ``sdh/dsa.cpp``, ``cDSA::ReadFrame``; fixed in 2.9.0.0, whose
    nibble-coded version 0x2900 is far above). SDHLibrary stops acquisition after each frame."""
    return sw_version <= 288 and sw_version != 269


# ---------------------------------------------------------------------------------------------
# Packet framing (protocols.md §1.2)
# ---------------------------------------------------------------------------------------------

PREAMBLE = b"\xaa\xaa\xaa"
_SYNC = 0xAA
_BOOT_NOISE = b"\x1b[5n"  # VT100 "terminal presence" query sent while booting (§1.1)
_HEADER = struct.Struct("<BH")
_U16 = struct.Struct("<H")
_MAX_LEN = 0xFFFF


def encode_packet(pid: int, payload: bytes = b"", *, crc_when_empty: bool = False) -> bytes:
    """Frame ``payload`` as ``AA AA AA | id | len u16 | payload | crc u16`` (protocols.md §1.2).

    The CRC covers id, length and payload and is sent low byte first. SDHLibrary appends it only
    when the payload is non-empty, so payload-less commands are 6 bytes; ``crc_when_empty=True``
    appends it anyway (what the Python and RobWork *readers* expect — irrelevant in practice,
    since no controller response is empty, §1.2).

    ID 0xAA is refused: a receiver takes every 0xAA after the preamble as more preamble
    (§1.7), so such a packet could never be parsed.
    """
    if not 0 <= pid <= 0xFF or pid == _SYNC:
        raise ValueError(f"packet id must be in 0…255 and not 0xAA, got {pid!r}")
    if len(payload) > _MAX_LEN:
        raise ValueError(f"payload of {len(payload)} bytes exceeds the u16 length field")
    body = _HEADER.pack(pid, len(payload)) + bytes(payload)
    if payload or crc_when_empty:
        return PREAMBLE + body + _U16.pack(crc16(body))
    return PREAMBLE + body


# Events returned by PacketParser.feed -------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Packet:
    """A complete packet with a valid CRC (or none, for an empty payload). ``id`` is a
    :class:`PacketId` when the value is listed in §1.3, else the raw int."""

    id: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class BadCrc:
    """A packet whose CRC did not match; its bytes are rescanned (and end up as garbage)."""

    id: int
    length: int
    received: int
    computed: int


@dataclass(frozen=True, slots=True)
class Oversized:
    """A header announcing more than ``max_payload`` bytes; treated as a false preamble."""

    id: int
    length: int


@dataclass(frozen=True, slots=True)
class GarbageSkipped:
    """``nbytes`` bytes that belonged to no packet (line noise, partial or rejected packets)."""

    nbytes: int


@dataclass(frozen=True, slots=True)
class BootNoise:
    """The ``ESC [ 5 n`` query the controller emits ≈7 s after power-up (protocols.md §1.1)."""


Event: TypeAlias = Packet | BadCrc | Oversized | GarbageSkipped | BootNoise

_KNOWN_IDS = frozenset(m.value for m in PacketId)
_ID_LOOKUP: tuple[int, ...] = tuple(PacketId(i) if i in _KNOWN_IDS else i for i in range(256))


def _boot_or_sync_prefix(tail: bytes | bytearray) -> bool:
    """True if ``tail`` may be the start of a boot-noise query or of a preamble."""
    return _BOOT_NOISE.startswith(tail) or PREAMBLE.startswith(tail)


class PacketParser:
    """Incremental packet reader for either direction (protocols.md §1.2, §1.7, PART 3 item 1).

    ``feed`` accepts any chunking and returns the events completed by the new bytes. Every byte
    fed ends up in exactly one of: a :class:`Packet`, a :class:`BootNoise` (4 bytes), a
    :class:`GarbageSkipped` count, or the pending buffer (:attr:`buffered`).

    Resynchronisation: the parser hunts for ``AA AA AA``. After a run of more than three 0xAA
    bytes the ID is the first non-0xAA byte (as SDHLibrary counts "at least three"; no ID 0xAA
    exists, §1.3), and the surplus 0xAA bytes count as garbage. On a bad CRC or a length above
    ``max_payload`` only the first preamble byte is dropped and the bytes already buffered are
    rescanned, so a good packet swallowed by a corrupted header is still found. SDHLibrary
    instead discards the whole announced length (§1.7); rescanning loses strictly less.

    ``crc_when_empty``: whether an empty payload is followed by a CRC. Default False matches
    SDHLibrary's writer and its C++ reader (§1.2); controller responses are never empty.

    Counters (monotonic): ``packets``, ``crc_errors``, ``oversized``, ``garbage_bytes``,
    ``boot_noise``, and ``resyncs`` — the number of maximal runs of skipped bytes, i.e. how often
    the parser lost alignment and had to hunt for the next preamble (a rejected packet always
    starts one, because its first byte is skipped).

    The pending buffer never exceeds ``max_payload + 8`` bytes after ``feed`` returns.
    """

    __slots__ = (
        "_buf",
        "_skipping",
        "boot_noise",
        "crc_errors",
        "crc_when_empty",
        "garbage_bytes",
        "max_payload",
        "oversized",
        "packets",
        "resyncs",
    )

    def __init__(
        self, *, max_payload: int = DEFAULT_MAX_PAYLOAD, crc_when_empty: bool = False
    ) -> None:
        if not 0 <= max_payload <= _MAX_LEN:
            raise ValueError(f"max_payload must be in 0…65535, got {max_payload!r}")
        self.max_payload = max_payload
        self.crc_when_empty = crc_when_empty
        self._buf = bytearray()
        self._skipping = False
        self.packets = 0
        self.crc_errors = 0
        self.oversized = 0
        self.garbage_bytes = 0
        self.boot_noise = 0
        self.resyncs = 0

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a packet (or of a preamble / boot query)."""
        return len(self._buf)

    def flush(self) -> list[Event]:
        """Resolve everything buffered, as if no more bytes were coming (e.g. after a timeout).

        A pending partial packet is abandoned one preamble byte at a time, so a complete packet
        stuck behind a corrupted header that announced a long payload is still delivered; all
        other leftover bytes become garbage. Afterwards :attr:`buffered` is 0.
        """
        buf = self._buf
        events: list[Event] = []
        while buf:
            self._garbage(1, events)
            del buf[:1]
            del buf[: self._scan(buf, events)]
        return events

    def feed(self, data: bytes | bytearray | memoryview) -> list[Event]:
        """Consume ``data`` and return the events it completed, in stream order."""
        buf = self._buf
        buf += data
        events: list[Event] = []
        consumed = self._scan(buf, events)
        del buf[:consumed]
        return events

    def _scan(self, buf: bytearray, events: list[Event]) -> int:
        """Parse ``buf`` as far as possible; return how many leading bytes are done with."""
        pos = 0  # first byte not yet accounted for
        search = 0  # where to look for the next preamble (> pos after a rejection)
        end = len(buf)
        while True:
            start = buf.find(PREAMBLE, search)
            if start < 0:
                keep = self._tail_start(buf, max(pos, end - 3), end)
                self._skip(buf, pos, keep, events)
                return keep
            self._skip(buf, pos, start, events)
            id_pos = self._end_of_sync_run(buf, start + 3, end)
            surplus = id_pos - 3 - start
            if surplus:  # more than three 0xAA: the extra ones are noise
                self._garbage(surplus, events)
                start += surplus
            pos = search = start
            if id_pos + 3 > end:
                return pos  # wait for ID and length
            pid, length = _HEADER.unpack_from(buf, id_pos)
            if length > self.max_payload:
                self.oversized += 1
                events.append(Oversized(_ID_LOOKUP[pid], length))
                search = start + 1
                continue
            body_end = id_pos + 3 + length
            has_crc = length > 0 or self.crc_when_empty
            pkt_end = body_end + 2 if has_crc else body_end
            if pkt_end > end:
                return pos  # wait for the rest of the packet
            body = bytes(buf[id_pos:body_end])
            if has_crc:
                received = buf[body_end] | (buf[body_end + 1] << 8)
                computed = crc16(body)
                if received != computed:
                    self.crc_errors += 1
                    events.append(BadCrc(_ID_LOOKUP[pid], length, received, computed))
                    search = start + 1
                    continue
            self.packets += 1
            self._skipping = False
            events.append(Packet(_ID_LOOKUP[pid], body[3:]))
            pos = search = pkt_end

    @staticmethod
    def _end_of_sync_run(buf: bytearray, i: int, end: int) -> int:
        """Index of the first non-0xAA byte at or after ``i`` (``end`` if none yet)."""
        while i < end and buf[i] == _SYNC:  # rare: only for runs of more than three 0xAA
            chunk = buf[i : i + 4096]
            i += len(chunk) - len(chunk.lstrip(b"\xaa"))
        return i

    @staticmethod
    def _tail_start(buf: bytearray, lo: int, end: int) -> int:
        """Start of the longest suffix (from ``lo``) that may begin a preamble or boot query."""
        for i in range(lo, end):
            if _boot_or_sync_prefix(buf[i:end]):
                return i
        return end

    def _skip(self, buf: bytearray, lo: int, hi: int, events: list[Event]) -> None:
        """Account for ``buf[lo:hi]``: boot-noise queries are reported, the rest is garbage."""
        while lo < hi:
            k = buf.find(_BOOT_NOISE, lo, hi)
            if k < 0:
                self._garbage(hi - lo, events)
                return
            if k > lo:
                self._garbage(k - lo, events)
            self.boot_noise += 1
            self._skipping = False
            events.append(BootNoise())
            lo = k + len(_BOOT_NOISE)

    def _garbage(self, n: int, events: list[Event]) -> None:
        """Count ``n`` skipped bytes, merging with a directly preceding GarbageSkipped event."""
        self.garbage_bytes += n
        if not self._skipping:
            self._skipping = True
            self.resyncs += 1
        if events and isinstance(events[-1], GarbageSkipped):
            n += events[-1].nbytes
            events.pop()
        events.append(GarbageSkipped(n))


# ---------------------------------------------------------------------------------------------
# Argument validation and struct helpers
# ---------------------------------------------------------------------------------------------


def _check_int(name: str, value: int, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in {lo}…{hi}, got {value}")
    return int(value)


def _check_matrix(matrix: int) -> int:
    return _check_int("matrix", matrix, 0, 0xFF)


def _check_sensitivity(value: float) -> float:
    if not (isinstance(value, int | float | np.floating) and 0.0 <= value <= 1.0):
        raise ValueError(f"sensitivity must be a number in 0.0…1.0, got {value!r}")
    return float(value)


def _pack(st: struct.Struct, *values: object) -> bytes:
    try:
        return st.pack(*values)
    except struct.error as exc:
        raise ValueError(f"field out of range for layout {st.format!r}: {exc}") from None


def _unpack(cls_name: str, st: struct.Struct, payload: bytes) -> tuple[Any, ...]:
    if len(payload) != st.size:
        raise ProtocolError(
            f"{cls_name} payload must be exactly {st.size} bytes, got {len(payload)}",
            DsaError.E_INCONSISTENT_DATA,
        )
    return st.unpack(payload)


_KNOWN_ERRORS = frozenset(m.value for m in DsaError)


def _error_code(value: int) -> int:
    """The :class:`DsaError` member for ``value`` when it is one, else the raw int."""
    return DsaError(value) if value in _KNOWN_ERRORS else value


def _adjust_flags(*, all_matrices: bool, persistent: bool, reset: bool) -> int:
    return (
        (AdjustFlag.PERSISTENT if persistent else 0)
        | (AdjustFlag.ALL_MATRICES if all_matrices else 0)
        | (AdjustFlag.RESET if reset else 0)
    )


# ---------------------------------------------------------------------------------------------
# Host → controller commands: encoders (protocols.md §1.3, §1.4, §1.6; golden bytes §1.2.2)
# ---------------------------------------------------------------------------------------------

_ACQ = struct.Struct("<BH")
_SENS_REQ = struct.Struct("<BBf")
_THR_REQ = struct.Struct("<BBH")
_EXTRA_ACQ_BITS = 0x7E  # bits 1…6: single shot and trigger options


def query_controller_info() -> bytes:
    """0x01, 6 bytes; answered by :class:`ControllerInfo` (protocols.md §1.4.1)."""
    return encode_packet(PacketId.QUERY_CONTROLLER_CONFIGURATION)


def query_sensor_info() -> bytes:
    """0x02, 6 bytes; answered by :class:`SensorInfo` (protocols.md §1.4.2)."""
    return encode_packet(PacketId.QUERY_SENSOR_CONFIGURATION)


def query_matrix_info(matrix: int) -> bytes:
    """0x0B with the matrix index; answered by :class:`MatrixInfo` (protocols.md §1.4.3)."""
    return encode_packet(PacketId.QUERY_MATRIX_CONFIGURATION, bytes([_check_matrix(matrix)]))


def configure_acquisition(
    *, acquire: bool, framerate: int, rle: bool = True, extra_flags: int = 0
) -> bytes:
    """0x03 ``flags u8 | framerate u16`` (protocols.md §1.6); answered by an :class:`ErrorReply`.

    * stop: ``acquire=False, framerate=0`` (SDHLibrary keeps the RLE bit: flags 0x01);
    * pull: ``acquire=True, framerate=0`` — ACK, then exactly one frame;
    * push: ``acquire=True, framerate>0`` — ACK, then frames until stopped. Whether the firmware
      honours the rate or always streams at its maximum (~30 fps) is [U].

    ``extra_flags`` may carry the bits no SCHUNK host sets (:class:`AcqFlag` SINGLE_SHOT, trigger
    bits — RobWork sends INTERNAL_TRIGGER); their effect is [U].
    """
    framerate = _check_int("framerate", framerate, 0, 0xFFFF)
    if extra_flags & ~_EXTRA_ACQ_BITS:  # also catches negative values
        raise ValueError(f"extra_flags must only use bits 1…6 (mask 0x7E), got {extra_flags:#x}")
    flags = (AcqFlag.ENABLE if acquire else 0) | (AcqFlag.RLE if rle else 0) | extra_flags
    return encode_packet(PacketId.CONFIGURE_DATA_ACQUISITION, _ACQ.pack(flags, framerate))


def set_sensitivity(
    matrix: int,
    value: float,
    *,
    all_matrices: bool = False,
    persistent: bool = False,
    reset: bool = False,
) -> bytes:
    """0x0F ``flags u8 | matrix u8 | sensitivity f32`` (protocols.md §1.4.4), value 0.0…1.0.

    The controller answers with an :class:`ErrorReply` — except when ``persistent`` is set:
    then it sends nothing at all (firmware bug; §1.4.4, PART 4 item 15), so don't wait for one.
    """
    flags = _adjust_flags(all_matrices=all_matrices, persistent=persistent, reset=reset)
    payload = _SENS_REQ.pack(flags, _check_matrix(matrix), _check_sensitivity(value))
    return encode_packet(PacketId.ADJUST_MATRIX_SENSITIVITY, payload)


def get_sensitivity_info(matrix: int) -> bytes:
    """0x12 with the matrix index; answered by :class:`SensitivityInfo` (protocols.md §1.4.4)."""
    return encode_packet(PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO, bytes([_check_matrix(matrix)]))


def set_threshold(
    matrix: int,
    value: int,
    *,
    all_matrices: bool = False,
    persistent: bool = False,
    reset: bool = False,
) -> bytes:
    """0x13 ``flags u8 | matrix u8 | threshold u16`` (protocols.md §1.4.5), value 0…4095.

    Needs firmware ≥ R268. No reply when ``persistent`` is set (as for sensitivity).
    """
    flags = _adjust_flags(all_matrices=all_matrices, persistent=persistent, reset=reset)
    payload = _THR_REQ.pack(flags, _check_matrix(matrix), _check_int("threshold", value, 0, 4095))
    return encode_packet(PacketId.SET_MATRIX_THRESHOLD, payload)


def get_threshold(matrix: int) -> bytes:
    """0x14 with the matrix index; answered by :class:`ThresholdInfo` (protocols.md §1.4.5)."""
    return encode_packet(PacketId.GET_MATRIX_THRESHOLD, bytes([_check_matrix(matrix)]))


def read_matrix_mask(matrix: int, dynamic: bool = False) -> bytes:
    """0x04 ``type u8 (0 static, 1 dynamic) | matrix u8``; answered by :class:`MatrixMask`.

    RobWork only; the exact meaning of static vs dynamic is [U] (protocols.md §1.4.6).
    """
    return encode_packet(PacketId.READ_MATRIX_MASK, bytes([int(dynamic), _check_matrix(matrix)]))


def read_descriptor_string(kind: DescriptorKind | int, matrix: int) -> bytes:
    """0x05 ``type u8 (0 sensor, 1 matrix) | matrix u8``; answered by :class:`DescriptorString`."""
    kind = _check_int("kind", kind, 0, 1)
    return encode_packet(PacketId.READ_DESCRIPTOR_STRING, bytes([kind, _check_matrix(matrix)]))


def loop() -> bytes:
    """0x06 LOOP, 6 bytes. The reply layout is [U] (RobWork only reads an ID-0x06 packet)."""
    return encode_packet(PacketId.LOOP)


def query_controller_state() -> bytes:
    """0x0A, 6 bytes. The reply starts with an error u16; the rest is [U] (protocols.md §1.3)."""
    return encode_packet(PacketId.QUERY_CONTROLLER_STATE)


# ---------------------------------------------------------------------------------------------
# Host → controller commands: decoded form (for the device emulator)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ConfigureAcquisition:
    """0x03. ``flags`` is the raw byte; ``acquire`` / ``rle`` are its bits 7 and 0 (§1.6)."""

    acquire: bool
    framerate: int
    rle: bool
    flags: int

    @property
    def pull(self) -> bool:
        """One frame after the ACK (acquire with rate 0)."""
        return self.acquire and self.framerate == 0

    @property
    def push(self) -> bool:
        """Frames until stopped (acquire with rate > 0)."""
        return self.acquire and self.framerate > 0


@dataclass(frozen=True, slots=True)
class QueryControllerInfo:
    """0x01."""


@dataclass(frozen=True, slots=True)
class QuerySensorInfo:
    """0x02."""


@dataclass(frozen=True, slots=True)
class QueryMatrixInfo:
    """0x0B."""

    matrix: int


@dataclass(frozen=True, slots=True)
class SetSensitivity:
    """0x0F. ``value`` is the f32 as sent — range checking is the device's job (§1.4.4)."""

    matrix: int
    value: float
    all_matrices: bool = False
    persistent: bool = False
    reset: bool = False

    @property
    def expects_reply(self) -> bool:
        """False for persistent writes: the firmware never answers them (PART 4 item 15)."""
        return not self.persistent


@dataclass(frozen=True, slots=True)
class GetSensitivityInfo:
    """0x12."""

    matrix: int


@dataclass(frozen=True, slots=True)
class SetThreshold:
    """0x13. ``value`` is the u16 as sent (valid range 0…4095, §1.4.5)."""

    matrix: int
    value: int
    all_matrices: bool = False
    persistent: bool = False
    reset: bool = False

    @property
    def expects_reply(self) -> bool:
        """False for persistent writes: the firmware never answers them (PART 4 item 15)."""
        return not self.persistent


@dataclass(frozen=True, slots=True)
class GetThreshold:
    """0x14."""

    matrix: int


@dataclass(frozen=True, slots=True)
class ReadMatrixMask:
    """0x04. A mask-type byte other than 0/1 decodes as ``dynamic=True`` (meaning [U])."""

    matrix: int
    dynamic: bool = False


@dataclass(frozen=True, slots=True)
class ReadDescriptorString:
    """0x05. ``kind`` is a :class:`DescriptorKind` when 0/1, else the raw byte."""

    kind: int
    matrix: int


@dataclass(frozen=True, slots=True)
class Loop:
    """0x06."""


@dataclass(frozen=True, slots=True)
class QueryControllerState:
    """0x0A."""


@dataclass(frozen=True, slots=True)
class UnknownCommand:
    """Any other ID (including 0x00 and the [U] commands 0x0C…0x10, 0xAB). How the real
    controller answers is [U]; an emulator will typically reply E_CMD_UNKNOWN."""

    id: int
    payload: bytes


Command: TypeAlias = (
    ConfigureAcquisition
    | QueryControllerInfo
    | QuerySensorInfo
    | QueryMatrixInfo
    | SetSensitivity
    | GetSensitivityInfo
    | SetThreshold
    | GetThreshold
    | ReadMatrixMask
    | ReadDescriptorString
    | Loop
    | QueryControllerState
    | UnknownCommand
)


def _dec_acq(p: bytes) -> Command:
    flags, rate = _ACQ.unpack(p)
    return ConfigureAcquisition(
        bool(flags & AcqFlag.ENABLE), rate, bool(flags & AcqFlag.RLE), flags
    )


def _dec_sens(p: bytes) -> Command:
    flags, matrix, value = _SENS_REQ.unpack(p)
    return SetSensitivity(matrix, value, *_adjust_bits(flags))


def _dec_thr(p: bytes) -> Command:
    flags, matrix, value = _THR_REQ.unpack(p)
    return SetThreshold(matrix, value, *_adjust_bits(flags))


def _adjust_bits(flags: int) -> tuple[bool, bool, bool]:
    """(all_matrices, persistent, reset) from an :class:`AdjustFlag` byte."""
    return (
        bool(flags & AdjustFlag.ALL_MATRICES),
        bool(flags & AdjustFlag.PERSISTENT),
        bool(flags & AdjustFlag.RESET),
    )


def _dec_descriptor(p: bytes) -> Command:
    kind = DescriptorKind(p[0]) if p[0] in (0, 1) else p[0]
    return ReadDescriptorString(kind, p[1])


# ID → (exact request payload size, decoder), protocols.md §1.3 "Request payload" column.
_COMMANDS: dict[int, tuple[int, Callable[[bytes], Command]]] = {
    PacketId.QUERY_CONTROLLER_CONFIGURATION: (0, lambda p: QueryControllerInfo()),
    PacketId.QUERY_SENSOR_CONFIGURATION: (0, lambda p: QuerySensorInfo()),
    PacketId.CONFIGURE_DATA_ACQUISITION: (3, _dec_acq),
    PacketId.READ_MATRIX_MASK: (2, lambda p: ReadMatrixMask(p[1], bool(p[0]))),
    PacketId.READ_DESCRIPTOR_STRING: (2, _dec_descriptor),
    PacketId.LOOP: (0, lambda p: Loop()),
    PacketId.QUERY_CONTROLLER_STATE: (0, lambda p: QueryControllerState()),
    PacketId.QUERY_MATRIX_CONFIGURATION: (1, lambda p: QueryMatrixInfo(p[0])),
    PacketId.ADJUST_MATRIX_SENSITIVITY: (6, _dec_sens),
    PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO: (1, lambda p: GetSensitivityInfo(p[0])),
    PacketId.SET_MATRIX_THRESHOLD: (4, _dec_thr),
    PacketId.GET_MATRIX_THRESHOLD: (1, lambda p: GetThreshold(p[0])),
}


def decode_command(packet: Packet) -> Command:
    """Decode a host command received by a device (protocols.md §1.3, PART 3 item 1).

    IDs without a known request layout give :class:`UnknownCommand`. A known ID with the wrong
    payload size raises :class:`ProtocolError` with ``code`` E_CMD_NOT_ENOUGH_PARAMS (too short)
    or E_CMD_FORMAT_ERROR (too long) — our choice: the real controller's reaction is [U].
    Field values are not range-checked; that is the device's decision.
    """
    entry = _COMMANDS.get(packet.id)
    if entry is None:
        return UnknownCommand(packet.id, packet.payload)
    size, decode = entry
    n = len(packet.payload)
    if n != size:
        code = DsaError.E_CMD_NOT_ENOUGH_PARAMS if n < size else DsaError.E_CMD_FORMAT_ERROR
        raise ProtocolError(
            f"command {packet.id:#04x} takes {size} payload bytes, got {n}", code, packet.id
        )
    return decode(packet.payload)


def encode_command(cmd: Command) -> bytes:
    """Inverse of :func:`decode_command`, validating fields like the individual encoders."""
    match cmd:
        case ConfigureAcquisition():
            extra = cmd.flags & _EXTRA_ACQ_BITS
            return configure_acquisition(
                acquire=cmd.acquire, framerate=cmd.framerate, rle=cmd.rle, extra_flags=extra
            )
        case SetSensitivity():
            return set_sensitivity(
                cmd.matrix,
                cmd.value,
                all_matrices=cmd.all_matrices,
                persistent=cmd.persistent,
                reset=cmd.reset,
            )
        case SetThreshold():
            return set_threshold(
                cmd.matrix,
                cmd.value,
                all_matrices=cmd.all_matrices,
                persistent=cmd.persistent,
                reset=cmd.reset,
            )
        case QueryMatrixInfo(matrix=m):
            return query_matrix_info(m)
        case GetSensitivityInfo(matrix=m):
            return get_sensitivity_info(m)
        case GetThreshold(matrix=m):
            return get_threshold(m)
        case ReadMatrixMask():
            return read_matrix_mask(cmd.matrix, cmd.dynamic)
        case ReadDescriptorString():
            return read_descriptor_string(cmd.kind, cmd.matrix)
        case QueryControllerInfo():
            return query_controller_info()
        case QuerySensorInfo():
            return query_sensor_info()
        case Loop():
            return loop()
        case QueryControllerState():
            return query_controller_state()
        case UnknownCommand():
            return encode_packet(cmd.id, cmd.payload)
    raise TypeError(f"not a DSACON32m command: {cmd!r}")


# ---------------------------------------------------------------------------------------------
# Controller → host responses (protocols.md §1.4; exact sizes PART 3 item 2)
# ---------------------------------------------------------------------------------------------


class _FlatResponse:
    """Mixin: the dataclass fields map 1:1, in order, onto ``_LAYOUT``; the first is error_code."""

    __slots__ = ()
    _LAYOUT: ClassVar[struct.Struct]

    def encode(self) -> bytes:
        """The payload bytes (no framing)."""
        return _pack(self._LAYOUT, *(getattr(self, f.name) for f in fields(self)))  # type: ignore[arg-type]

    @classmethod
    def decode(cls, payload: bytes) -> Self:
        """Parse a payload of exactly ``_LAYOUT.size`` bytes, else raise :class:`ProtocolError`."""
        code, *rest = _unpack(cls.__name__, cls._LAYOUT, payload)
        names = [f.name for f in fields(cls)]  # type: ignore[arg-type]
        return cls(**dict(zip(names, (_error_code(code), *rest), strict=True)))


@dataclass(frozen=True, slots=True, kw_only=True)
class ControllerInfo(_FlatResponse):
    """Response to 0x01: exactly 18 bytes (protocols.md §1.4.1).

    ``can_id`` is a single byte on the wire (the library struct's u16 high byte is never sent).
    ``sw_version`` < 0x1000 is a plain release number (e.g. 288), ≥ 0x1000 nibble-coded a.b.c.d.
    Defaults describe an operable, idle DSACON32 on RS-232 reporting firmware 0x2900 (2.9.0.0),
    as PART 3 item 6 recommends for emulators; the other defaults (0) are not from any source.
    """

    _LAYOUT: ClassVar[struct.Struct] = struct.Struct("<HIBHBBBBIB")

    error_code: int = DsaError.E_SUCCESS
    serial_no: int = 0
    hw_version: int = 0
    sw_version: int = 0x2900
    status_flags: int = 0x80
    feature_flags: int = 0x10
    senscon_type: int = 1
    active_interface: int = 0
    can_baudrate: int = 0
    can_id: int = 0

    @property
    def operable(self) -> bool:
        """status_flags bit 7: sensor controller operable."""
        return bool(self.status_flags & 0x80)

    @property
    def acquiring(self) -> bool:
        """status_flags bit 6: data acquisition running."""
        return bool(self.status_flags & 0x40)


@dataclass(frozen=True, slots=True, kw_only=True)
class SensorInfo(_FlatResponse):
    """Response to 0x02: exactly 12 bytes (protocols.md §1.4.2). Defaults: the SDH2's 6 matrices."""

    _LAYOUT: ClassVar[struct.Struct] = struct.Struct("<HHHBIB")

    error_code: int = DsaError.E_SUCCESS
    nb_matrices: int = len(SDH2_MATRIX_SHAPES)
    generated_by: int = 0
    hw_revision: int = 0
    serial_no: int = 0
    feature_flags: int = 0


@dataclass(frozen=True, slots=True, kw_only=True)
class SensitivityInfo(_FlatResponse):
    """Response to 0x12: exactly 11 bytes (protocols.md §1.4.4).

    Defaults: user-adjustable (adj_flags bit 1), current and factory sensitivity 0.5 — the factory
    value is inferred [I] from old firmware always reporting 0.5.
    """

    _LAYOUT: ClassVar[struct.Struct] = struct.Struct("<HBff")

    error_code: int = DsaError.E_SUCCESS
    adj_flags: int = 0x02
    cur_sens: float = 0.5
    fact_sens: float = 0.5

    @property
    def adjustable(self) -> bool:
        """adj_flags bit 1: the user may change the sensitivity."""
        return bool(self.adj_flags & 0x02)


@dataclass(frozen=True, slots=True, kw_only=True)
class ThresholdInfo(_FlatResponse):
    """Response to 0x14: exactly 4 bytes, error u16 | threshold u16 (protocols.md §1.4.5).
    The factory default threshold is [U], hence no default here."""

    _LAYOUT: ClassVar[struct.Struct] = struct.Struct("<HH")

    error_code: int = DsaError.E_SUCCESS
    threshold: int


@dataclass(frozen=True, slots=True)
class ErrorReply(_FlatResponse):
    """The 2-byte error-code response — the ACK of 0x03, 0x0F and 0x13 (protocols.md §1.3, §1.6).

    ``ErrorReply(DsaError.E_SUCCESS)`` is the ACK. An emulator may also use it for commands whose
    reply layout is [U] (0x06 LOOP, 0x0A QUERY_CONTROLLER_STATE) or to reject a command.
    """

    _LAYOUT: ClassVar[struct.Struct] = struct.Struct("<H")

    error_code: int = DsaError.E_SUCCESS

    @property
    def ok(self) -> bool:
        return self.error_code == DsaError.E_SUCCESS


_MATRIX_INFO = struct.Struct("<HffHH6s2sB3f3fIB")
_Vec3: TypeAlias = tuple[float, float, float]


@dataclass(frozen=True, slots=True, kw_only=True)
class MatrixInfo:
    """Response to 0x0B: exactly 52 bytes (protocols.md §1.4.3).

    ``fullscale`` (offset 47) is encoded as **u32**, default 4095: SDHLibrary-C++ declares it f32
    but uses it nowhere, the Python library and RobWork read u32 (PART 4 item 12).
    ``texel_width``/``texel_height`` default to 3.4 mm, a value no source confirms [U].
    ``feature_flags`` bit 0 = descriptor string set; bit 1 = sensitivity adjustable [U].
    """

    error_code: int = DsaError.E_SUCCESS
    texel_width: float = 3.4
    texel_height: float = 3.4
    cells_x: int
    cells_y: int
    uid: bytes = bytes(6)
    reserved: bytes = bytes(2)
    hw_revision: int = 0
    center: _Vec3 = (0.0, 0.0, 0.0)
    theta: _Vec3 = (0.0, 0.0, 0.0)
    fullscale: int = TEXEL_MAX
    feature_flags: int = 0

    @property
    def nb_cells(self) -> int:
        return self.cells_x * self.cells_y

    @property
    def shape(self) -> tuple[int, int]:
        """numpy shape (cells_y, cells_x) of this matrix's texels (protocols.md §1.5)."""
        return (self.cells_y, self.cells_x)

    def encode(self) -> bytes:
        """The 52 payload bytes."""
        if len(self.uid) != 6 or len(self.reserved) != 2:
            raise ValueError("uid must be 6 bytes and reserved 2 bytes")
        if len(self.center) != 3 or len(self.theta) != 3:
            raise ValueError("center and theta must have 3 components")
        return _pack(
            _MATRIX_INFO,
            self.error_code,
            self.texel_width,
            self.texel_height,
            self.cells_x,
            self.cells_y,
            bytes(self.uid),
            bytes(self.reserved),
            self.hw_revision,
            *self.center,
            *self.theta,
            self.fullscale,
            self.feature_flags,
        )

    @classmethod
    def decode(cls, payload: bytes) -> Self:
        """Parse exactly 52 bytes, else raise :class:`ProtocolError`."""
        f = _unpack(cls.__name__, _MATRIX_INFO, payload)
        return cls(
            error_code=_error_code(f[0]),
            texel_width=f[1],
            texel_height=f[2],
            cells_x=f[3],
            cells_y=f[4],
            uid=f[5],
            reserved=f[6],
            hw_revision=f[7],
            center=f[8:11],
            theta=f[11:14],
            fullscale=f[14],
            feature_flags=f[15],
        )


def _mask_bytes(nb_cells: int) -> int:
    return (nb_cells + 7) // 8


@dataclass(frozen=True, slots=True, kw_only=True)
class MatrixMask:
    """Response to 0x04: error u16, then one bit per cell (protocols.md §1.4.6).

    Bits are LSB-first and continue across bytes in row-major order (x fastest), as RobWork reads
    them. We assume exactly ceil(cells/8) bytes follow, with no per-row padding [U: no sample of
    a real reply exists].
    """

    bits: bytes
    error_code: int = DsaError.E_SUCCESS

    @classmethod
    def from_array(cls, mask: npt.ArrayLike, *, error_code: int = DsaError.E_SUCCESS) -> Self:
        """Pack a (cells_y, cells_x) boolean array (or a flat row-major one)."""
        flat = np.asarray(mask, dtype=bool).ravel()
        return cls(bits=np.packbits(flat, bitorder="little").tobytes(), error_code=error_code)

    def to_array(self, cells_x: int, cells_y: int) -> npt.NDArray[np.bool_]:
        """The mask as a (cells_y, cells_x) boolean array."""
        n = cells_x * cells_y
        if len(self.bits) != _mask_bytes(n):
            raise ProtocolError(f"{len(self.bits)} mask bytes do not fit {n} cells")
        raw = np.frombuffer(self.bits, dtype=np.uint8)
        return np.unpackbits(raw, count=n, bitorder="little").astype(bool).reshape(cells_y, cells_x)

    def encode(self) -> bytes:
        return _pack(_U16, self.error_code) + bytes(self.bits)

    @classmethod
    def decode(cls, payload: bytes, nb_cells: int) -> Self:
        """Parse exactly 2 + ceil(nb_cells/8) bytes, else raise :class:`ProtocolError`."""
        expected = 2 + _mask_bytes(nb_cells)
        if len(payload) != expected:
            raise ProtocolError(
                f"MatrixMask payload for {nb_cells} cells must be exactly {expected} bytes, "
                f"got {len(payload)}",
                DsaError.E_INCONSISTENT_DATA,
            )
        return cls(bits=bytes(payload[2:]), error_code=_error_code(_U16.unpack_from(payload)[0]))


@dataclass(frozen=True, slots=True, kw_only=True)
class DescriptorString:
    """Response to 0x05: error u16 + text of N−2 bytes (protocols.md §1.3).

    The text is stored decoded as Latin-1 so any byte round-trips (the sources say ASCII);
    whether the firmware appends a NUL is [U], so nothing is stripped.
    """

    text: str
    error_code: int = DsaError.E_SUCCESS

    def encode(self) -> bytes:
        return _pack(_U16, self.error_code) + self.text.encode("latin-1")

    @classmethod
    def decode(cls, payload: bytes) -> Self:
        """Parse at least 2 bytes, else raise :class:`ProtocolError`."""
        if len(payload) < 2:
            raise ProtocolError(
                f"DescriptorString payload needs at least 2 bytes, got {len(payload)}",
                DsaError.E_INCONSISTENT_DATA,
            )
        code = _error_code(_U16.unpack_from(payload)[0])
        return cls(text=bytes(payload[2:]).decode("latin-1"), error_code=code)


# ---------------------------------------------------------------------------------------------
# Full frames and RLE (protocols.md §1.5)
# ---------------------------------------------------------------------------------------------

_FRAME_HEAD = struct.Struct("<IB")
_FLAG_RLE = 0x01
_RUN_MAX = 15  # 4-bit run length
# texel indices, and whether an offset into a run starts a word (a lookup: cheaper than `% 15`),
# for frames of up to 4096 texels
_INDEX = np.arange(4096, dtype=np.intp)
_WORD_START = _INDEX % _RUN_MAX == 0


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Frame:
    """A full frame (ID 0x00, protocols.md §1.5).

    ``timestamp_ms``: controller clock (u32 ms). ``texels``: flat uint16 array of nb_cells values,
    matrices in index order, each row-major (x fastest); decoded frames hold read-only arrays.
    ``eq=False`` because arrays do not compare to a single bool; compare the fields instead.
    The repr summarises the texels instead of printing 486 numbers.
    """

    timestamp_ms: int
    rle: bool
    texels: npt.NDArray[np.uint16]

    def __repr__(self) -> str:
        t = self.texels
        peak = int(t.max()) if t.size else 0
        texels = f"<{t.size} texels, max {peak}>"
        return f"Frame(timestamp_ms={self.timestamp_ms}, rle={self.rle}, texels={texels})"

    def encode(self) -> bytes:
        """The frame payload (see :func:`encode_frame_payload`)."""
        return encode_frame_payload(self.timestamp_ms, self.texels, rle=self.rle)

    def matrices(self, matrix_infos: Sequence[HasCells]) -> list[npt.NDArray[np.uint16]]:
        """The texels split per matrix (see :func:`split_matrices`)."""
        return split_matrices(self.texels, matrix_infos)


def _as_texels(values: npt.ArrayLike) -> npt.NDArray[np.uint16]:
    """Validate a flat integer array of 12-bit values and return it as uint16."""
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"texels must be a flat 1-D array (row-major per matrix), got {arr.shape}")
    if arr.size == 0:
        return arr.astype(np.uint16)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"texels must be integers, got dtype {arr.dtype}")
    # (unsigned values cannot be below 0: one reduction, not two, for every frame)
    if int(arr.max()) > TEXEL_MAX or (arr.dtype.kind == "i" and int(arr.min()) < 0):
        lo, hi = int(arr.min()), int(arr.max())
        raise ValueError(f"texel values must be in 0…{TEXEL_MAX}, got {lo}…{hi}")
    return arr.astype(np.uint16, copy=False)


def rle_encode(values: npt.ArrayLike, *, breaks: Iterable[int] = ()) -> bytes:
    """RLE words ``count << 12 | value`` (count 1…15), little-endian (protocols.md §1.5).

    Runs are greedy (15, 15, …, rest) and by default cross row and matrix boundaries — this is
    what produces the 33-word all-zero frame of §1.2.2. Whether the firmware restarts runs at
    boundaries is [U]; pass texel indices in ``breaks`` (e.g. :func:`texel_offsets` for matrices,
    or every row start) to force a new run there (§1.10 gives the resulting sizes).
    """
    return _rle_words(_as_texels(values), breaks)


def _rle_words(v: npt.NDArray[np.uint16], breaks: Iterable[int]) -> bytes:
    """:func:`rle_encode` of texels already checked (:func:`_as_texels`).

    A word starts where a run starts and every 15 texels into a run; each texel's offset into
    its run is its index minus the running maximum of the run starts' indices.
    """
    n = v.size
    if n == 0:
        return b""
    starts = np.empty(n, dtype=bool)
    starts[0] = True
    np.not_equal(v[1:], v[:-1], out=starts[1:])
    b = np.fromiter(breaks, dtype=np.intp)
    if b.size:
        if int(b.min()) < 0 or int(b.max()) > n:
            raise ValueError(f"RLE breaks must lie in 0…{n}")
        starts[b[b < n]] = True
    if n <= _INDEX.size:
        idx, word_start = _INDEX[:n], _WORD_START
    else:  # larger than any real sensor's frame
        idx = np.arange(n)
        word_start = idx % _RUN_MAX == 0
    since = idx - np.maximum.accumulate(idx * starts)  # offset into the texel's run
    first = word_start[since].nonzero()[0]
    lengths = np.empty_like(first)  # np.diff(np.append(first, n)), without their overhead
    np.subtract(first[1:], first[:-1], out=lengths[:-1])
    lengths[-1] = n - first[-1]
    words: npt.NDArray[np.intp] = (lengths << 12) | v[first]
    return words.astype("<u2").tobytes()


def rle_decode(data: bytes | memoryview, nb_cells: int) -> npt.NDArray[np.uint16]:
    """Expand RLE words; raise :class:`FrameError` unless they give exactly ``nb_cells`` texels.

    Words with count 0 produce nothing (protocols.md §1.5). An odd byte count is rejected.
    """
    if len(data) % 2:
        raise FrameError(f"RLE data has an odd length ({len(data)} bytes)")
    words: npt.NDArray[np.uint16] = np.frombuffer(data, dtype="<u2")
    # the methods, not np.repeat/np.sum: their dispatch costs more than the work; the size is
    # checked after expanding (a payload's u16 length bounds it to 32767 · 15 texels)
    texels = (words & np.uint16(TEXEL_MAX)).repeat((words >> 12).astype(np.intp))
    if texels.size != nb_cells:
        raise FrameError(f"RLE data expands to {texels.size} texels, expected {nb_cells}")
    return texels


def encode_frame_payload(
    timestamp_ms: int, texels: npt.ArrayLike, *, rle: bool, rle_breaks: Iterable[int] = ()
) -> bytes:
    """``timestamp u32 | flags u8 | texel data`` (protocols.md §1.5).

    Texel values must be 0…4095 (12-bit converter; the RLE value field has 12 bits) and
    ``texels`` flat. A timestamp of 0 is valid here, but hosts treat it as "re-take the clock
    base" (PART 4 item 17), so an emulator should start its clock above 0.
    """
    ts = _check_int("timestamp_ms", timestamp_ms, 0, 0xFFFF_FFFF)
    values = _as_texels(texels)
    head = _FRAME_HEAD.pack(ts, _FLAG_RLE if rle else 0)
    data = _rle_words(values, rle_breaks) if rle else values.astype("<u2").tobytes()
    return head + data


def decode_frame_payload(payload: bytes, nb_cells: int) -> Frame:
    """Parse a frame payload; raise :class:`FrameError` on any size mismatch (protocols.md §1.5).

    Uncompressed payloads must be exactly 5 + 2·nb_cells bytes; RLE data must expand to exactly
    nb_cells texels. Flag bits other than bit 0 are ignored (unused by hosts, meaning [U]).
    Uncompressed values above 4095 are passed through, as the host libraries do.
    """
    payload = bytes(payload)
    if len(payload) < _FRAME_HEAD.size:
        raise FrameError(f"frame payload needs at least 5 bytes, got {len(payload)}")
    ts, flags = _FRAME_HEAD.unpack_from(payload)
    data = memoryview(payload)[_FRAME_HEAD.size :]
    rle = bool(flags & _FLAG_RLE)
    if rle:
        texels = rle_decode(data, nb_cells)
        texels.flags.writeable = False
    elif len(data) != 2 * nb_cells:
        raise FrameError(
            f"uncompressed frame must be {5 + 2 * nb_cells} bytes for {nb_cells} cells, "
            f"got {len(payload)}"
        )
    else:
        texels = np.frombuffer(data, dtype="<u2").astype(np.uint16, copy=False)
    return Frame(ts, rle, texels)


# ---------------------------------------------------------------------------------------------
# Geometry (protocols.md §1.5, §1.8)
# ---------------------------------------------------------------------------------------------


class HasCells(Protocol):
    """Anything with matrix cell counts: :class:`MatrixInfo`, :class:`MatrixShape`."""

    @property
    def cells_x(self) -> int: ...

    @property
    def cells_y(self) -> int: ...


def texel_offsets(matrix_infos: Iterable[HasCells]) -> list[int]:
    """Index of each matrix's first texel in a frame: sum of the cells before it (§1.5)."""
    offsets: list[int] = []
    total = 0
    for m in matrix_infos:
        offsets.append(total)
        total += m.cells_x * m.cells_y
    return offsets


def split_matrices(
    texels: npt.NDArray[np.uint16], matrix_infos: Sequence[HasCells]
) -> list[npt.NDArray[np.uint16]]:
    """Views of the flat ``texels`` as one (cells_y, cells_x) array per matrix (§1.5).

    Texel (m, x, y) of the frame is ``split_matrices(...)[m][y, x]``.
    """
    sizes = [m.cells_x * m.cells_y for m in matrix_infos]
    arr = np.asarray(texels)
    if arr.shape != (sum(sizes),):
        raise ValueError(f"expected {sum(sizes)} texels for these matrices, got shape {arr.shape}")
    offsets = texel_offsets(matrix_infos)
    return [
        arr[o : o + n].reshape(m.cells_y, m.cells_x)
        for o, n, m in zip(offsets, sizes, matrix_infos, strict=True)
    ]


# ---------------------------------------------------------------------------------------------
# Response framing convenience (device side)
# ---------------------------------------------------------------------------------------------

Response: TypeAlias = (
    ControllerInfo
    | SensorInfo
    | MatrixInfo
    | SensitivityInfo
    | ThresholdInfo
    | ErrorReply
    | MatrixMask
    | DescriptorString
    | Frame
)

# Payload types a response to each ID may carry; ErrorReply is accepted for all but frames.
_RESPONSE_TYPES: dict[int, tuple[type, ...]] = {
    PacketId.FULL_FRAME: (Frame,),
    PacketId.QUERY_CONTROLLER_CONFIGURATION: (ControllerInfo, ErrorReply),
    PacketId.QUERY_SENSOR_CONFIGURATION: (SensorInfo, ErrorReply),
    PacketId.QUERY_MATRIX_CONFIGURATION: (MatrixInfo, ErrorReply),
    PacketId.CONFIGURE_DATA_ACQUISITION: (ErrorReply,),
    PacketId.ADJUST_MATRIX_SENSITIVITY: (ErrorReply,),
    PacketId.SET_MATRIX_THRESHOLD: (ErrorReply,),
    PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO: (SensitivityInfo, ErrorReply),
    PacketId.GET_MATRIX_THRESHOLD: (ThresholdInfo, ErrorReply),
    PacketId.READ_MATRIX_MASK: (MatrixMask, ErrorReply),
    PacketId.READ_DESCRIPTOR_STRING: (DescriptorString, ErrorReply),
}


def encode_response(pid: int, payload_obj: Response) -> bytes:
    """Frame a response payload under ``pid`` (the ID of the command it answers, §1.3).

    Refuses a payload type that cannot answer ``pid`` (e.g. SensorInfo under 0x01) — such a reply
    makes SDHLibrary throw (PART 3 item 2). Every response type is ≥ 2 bytes, so the packet
    always has a CRC, as hosts require (§1.2).
    """
    allowed = _RESPONSE_TYPES.get(pid)
    if allowed is not None and not isinstance(payload_obj, allowed):
        names = ", ".join(t.__name__ for t in allowed)
        raise TypeError(
            f"a response to {pid:#04x} must be {names}, got {type(payload_obj).__name__}"
        )
    return encode_packet(pid, payload_obj.encode())
