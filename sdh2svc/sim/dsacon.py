"""DSACON32m firmware emulator: the SDH2's tactile-sensor controller, as a sans-I/O device.

:class:`DsaconEmulator` implements :class:`~sdh2svc.sim.endpoint.Device`: an endpoint hands it the
host's bytes and asks for whole packets whenever the line is idle, always with the endpoint's
``now`` (seconds). It keeps no clock and starts no task, so the same ``now`` values give the same
bytes. Every byte goes through :mod:`sdh2svc.protocol.dsa`; what the pads feel comes from a
:class:`~sdh2svc.sim.world.HandWorld` (protocols.md PART 1, PART 3, PART 4).

Firmware behaviour the sources do not settle ([U] in protocols.md), our choice, and the
:class:`DsaconOptions` field (or argument) that controls it:

* Power-on: the controller clock starts at :meth:`DsaconEmulator.power_on`, or at the first call
  of any method (over a pty or TCP: when the first host opens the port). ``boot_s``
  (default 0; 8.0 like the real unit, §1.1): deaf and mute until then, except ``ESC [ 5 n`` three
  times, at boot_s − 1.0, − 0.59 and − 0.18 s (within 0.82 s; exact offsets [U]). Noise still
  unsent when the boot ends (nobody was listening) is dropped.
* Push rate (open question 1): ``honour_framerate`` (default False: any rate > 0 streams at
  ``max_fps``, default 30, as the SDHLibrary docs say); when True a rate below the cap sets it.
  Frames of a stream are at least 1/fps apart (next one due one period after the last was sampled)
  and line-limited by the endpoint. No internal ADC rate is modelled (230 Hz is [U]): each frame
  is sampled from the world when the line frees for it.
* Old firmware (``sw_version`` R288 or older, except R269): a pull request starts a stream at
  ``max_fps`` instead of sending one frame, as SDHLibrary-CPP's ``cDSA::ReadFrame`` says those
  releases do (§1.6); 0x2900 (2.9.0.0, the default) and later send one frame.
* Any 0x03 replaces the running mode; a pull frame queued before a stop still goes out (it
  precedes the stop's ACK, so no frame ever follows that ACK). Flag bits 1…6 (single shot,
  triggers) are ignored.
* Texel size (open question 2): ``texel_size_mm`` (3.4) for width and height. ``fullscale`` is u32
  4095 (the codec's MatrixInfo default, PART 4 item 12). MatrixInfo feature flags 0x03
  (descriptor set, sensitivity adjustable), SensorInfo feature flags 0x01, ``generated_by`` =
  ``sw_version`` (0x2900), uid = serial number LE + matrix index.
* Factory threshold (open question 5): ``factory_threshold`` (default 0, i.e. nothing suppressed,
  so frames carry the world's counts unchanged). Factory sensitivity ``factory_sensitivity`` (0.5,
  §1.4.4 [I]).
* Persistent writes (bit 7): applied and saved, never answered — not even with an error (PART 4
  item 15); a write of the wrong size is answered, as its flags cannot be trusted. Saved values
  are what :meth:`DsaconEmulator.power_on` restores; temporary ones last until then (PART 4
  item 14), across host disconnects.
* Rejections (open question 6): unknown IDs → E_CMD_UNKNOWN; wrong payload sizes → the codec's
  code (E_CMD_NOT_ENOUGH_PARAMS / E_CMD_FORMAT_ERROR); sensitivity outside 0…1 (or NaN) and
  threshold above 4095 → E_RANGE_ERROR; a matrix index ≥ nb_matrices → E_INDEX_OUT_OF_BOUNDS; a
  descriptor type other than 0/1 → E_INVALID_PARAMETER. Each as a 2-byte ErrorReply under the
  command's ID. Packets the host never sends (ID 0x00) get no reply: one would read as a frame.
* Bad host CRC: ``crc_error_reply`` (default True) → ErrorReply E_CHECKSUM_ERROR under the corrupt
  packet's ID (ID 0x00 excepted, see above); False → silence. A header announcing more than
  64 payload bytes is taken for line noise (no command has more than 6), so resync stays quick.
* 0x04 mask (§1.4.6): static = the physically present cells (``static_masks`` argument, e.g. a
  MatrixLayout's ``valid()``; default all present), dynamic = all cells enabled. Absent cells
  always read 0 in frames (§1.8 [I]).
* 0x05 text: ``sensor_descriptor`` for type 0; ``"matrix <m> <cols>x<rows>"`` for type 1.
* 0x06 LOOP → ErrorReply(E_SUCCESS). 0x0A → 7 bytes: ``error u16 | status u8 (as in 0x01) |
  controller clock u32 ms`` (both as the command arrived).
* RLE runs (open question 7): ``rle_breaks`` "none" (default, the 33-word all-zero frame of
  §1.2.2), "matrix" or "row".
* Timestamps: controller ms since power-on + ``clock_offset_ms`` (default 1000), wrapping at
  2**32; a value that wraps to 0 is sent as 1 (0 makes the host re-take its clock base, item 17).
* Status bit 6 (acquisition running): while a push stream runs or a pull frame is pending.
* Host disconnect: ``stream_survives_disconnect`` (default False: the stream stops, as if the host
  had sent a stop; True is closer to the real unit, which streams into the void — the next host's
  open copes either way). Replies not yet sent to the old host are dropped.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, TypeAlias, TypeVar

import numpy as np
import numpy.typing as npt

from sdh2svc.protocol.dsa import (
    BadCrc,
    Command,
    ConfigureAcquisition,
    ControllerInfo,
    DescriptorKind,
    DescriptorString,
    DsaError,
    ErrorReply,
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
    Response,
    SensitivityInfo,
    SensorInfo,
    SetSensitivity,
    SetThreshold,
    ThresholdInfo,
    UnknownCommand,
    decode_command,
    encode_frame_payload,
    encode_packet,
    encode_response,
    single_frame_bug,
    texel_offsets,
)
from sdh2svc.sim.world import HandWorld

__all__ = ["BOOT_NOISE", "DsaconEmulator", "DsaconOptions", "DsaconStats"]

#: VT100 "terminal presence" query the booting controller emits (protocols.md §1.1).
BOOT_NOISE = b"\x1b[5n"
_BOOT_NOISE_OFFSETS_S = (-1.0, -0.59, -0.18)  # relative to the end of the boot
_MAX_COMMAND_PAYLOAD = 64
_U32_RANGE = 1 << 32
_STATUS_OPERABLE = 0x80
_STATUS_ACQUIRING = 0x40
_ADJUSTABLE = 0x02  # SensitivityInfo adj_flags bit 1
_STATE = struct.Struct("<HBI")  # our 0x0A layout: error, status, clock ms

_MatrixReply: TypeAlias = Callable[[int], Response]
_T = TypeVar("_T", int, float)


@dataclass(frozen=True, slots=True, kw_only=True)
class DsaconOptions:
    """Firmware choices where the sources are silent; see the module docstring for each."""

    boot_s: float = 0.0
    max_fps: float = 30.0
    honour_framerate: bool = False
    texel_size_mm: float = 3.4
    factory_sensitivity: float = 0.5
    factory_threshold: int = 0
    crc_error_reply: bool = True
    stream_survives_disconnect: bool = False
    rle_breaks: Literal["none", "matrix", "row"] = "none"
    clock_offset_ms: int = 1000
    serial_no: int = 0x0001_2345
    sw_version: int = 0x2900
    sensor_descriptor: str = "DSACON32m emulator (sdh2svc)"

    def __post_init__(self) -> None:
        if not self.boot_s >= 0.0:
            raise ValueError(f"boot_s must be >= 0, got {self.boot_s!r}")
        if not self.max_fps > 0.0:
            raise ValueError(f"max_fps must be > 0, got {self.max_fps!r}")
        if not self.texel_size_mm > 0.0:
            raise ValueError(f"texel_size_mm must be > 0, got {self.texel_size_mm!r}")
        if not 0.0 <= self.factory_sensitivity <= 1.0:
            raise ValueError(f"factory_sensitivity must be in 0…1, got {self.factory_sensitivity}")
        if not 0 <= self.factory_threshold <= 4095:
            raise ValueError(f"factory_threshold must be in 0…4095, got {self.factory_threshold}")
        if self.rle_breaks not in ("none", "matrix", "row"):
            raise ValueError(f"rle_breaks must be none, matrix or row, got {self.rle_breaks!r}")
        if not 0 <= self.clock_offset_ms < _U32_RANGE:
            raise ValueError(f"clock_offset_ms must fit a u32, got {self.clock_offset_ms}")
        if not 0 <= self.sw_version <= 0xFFFF:
            raise ValueError(f"sw_version must fit a u16, got {self.sw_version:#x}")

    @property
    def streams_on_pull(self) -> bool:
        """Firmware R288 or older except R269 cannot send a single frame: a pull request
        starts a stream at the maximum rate (SDHLibrary-CPP ``cDSA::ReadFrame``, §1.6)."""
        return single_frame_bug(self.sw_version)


@dataclass(slots=True)
class DsaconStats:
    """Counters since construction (power cycles do not reset them)."""

    frames: int = 0  # full frames sent
    packets: int = 0  # every packet handed out: replies, frames, boot noise
    bytes: int = 0  # bytes of those packets
    commands: int = 0  # well-formed commands received (whether accepted or rejected)
    errors: int = 0  # bad CRCs, oversized headers, malformed, unknown or rejected commands
    crc_errors: int = 0
    deaf_bytes: int = 0  # host bytes that arrived while booting


@dataclass(frozen=True, slots=True)
class _PullFrame:
    """An outbox slot for a pull-mode frame, sampled only when the line frees for it."""

    rle: bool


@dataclass(frozen=True, slots=True)
class _Stream:
    period_s: float
    rle: bool


class DsaconEmulator:
    """A DSACON32m serving ``world``'s pads; implements the endpoint's ``Device`` protocol.

    ``static_masks``: one (rows, cols) boolean array per matrix, True where a cell physically
    exists (default: all); reported by 0x04 and applied to frames (absent cells read 0).
    """

    def __init__(
        self,
        world: HandWorld,
        *,
        options: DsaconOptions | None = None,
        static_masks: Sequence[npt.ArrayLike] | None = None,
    ) -> None:
        self.options = options or DsaconOptions()
        self.stats = DsaconStats()
        self._world = world
        self._shapes = tuple((int(r), int(c)) for r, c in world.matrix_shapes)
        self._masks = _check_masks(self._shapes, static_masks)
        self._present = np.concatenate([m.ravel() for m in self._masks])
        self._absent = np.flatnonzero(~self._present)  # an index: cheaper than a mask per frame
        self._breaks = _rle_breaks(self._shapes, self.options.rle_breaks)
        n = len(self._shapes)
        self._saved_sens = [self.options.factory_sensitivity] * n
        self._saved_thr = [self.options.factory_threshold] * n
        self._sens = list(self._saved_sens)
        self._thr = list(self._saved_thr)
        self._parser = _new_parser()
        self._outbox: deque[bytes | _PullFrame] = deque()
        self._stream: _Stream | None = None
        self._next_frame_at = math.inf
        self._power_at: float | None = None
        self._noise_at: deque[float] = deque()

    # -- inspection --------------------------------------------------------------------------

    @property
    def nb_matrices(self) -> int:
        return len(self._shapes)

    @property
    def sensitivity(self) -> tuple[float, ...]:
        """Current per-matrix sensitivity (0…1)."""
        return tuple(self._sens)

    @property
    def threshold(self) -> tuple[int, ...]:
        """Current per-matrix threshold (counts)."""
        return tuple(self._thr)

    @property
    def streaming(self) -> bool:
        """A push stream is running."""
        return self._stream is not None

    def booted(self, now: float) -> bool:
        return now >= self._boot_end(now)

    def clock_ms(self, now: float) -> int:
        """The controller clock at ``now`` as sent in frame timestamps (never 0)."""
        since = 0.0 if self._power_at is None else now - self._power_at
        ms = (math.floor(since * 1000.0 + 1e-6) + self.options.clock_offset_ms) % _U32_RANGE
        return ms or 1

    # -- power -------------------------------------------------------------------------------

    def power_on(self, now: float) -> None:
        """Switch on (or power-cycle) at ``now``: the clock and the boot start over, temporary
        settings fall back to the saved ones, acquisition stops and buffers are emptied."""
        self._power_at = now
        self._sens = list(self._saved_sens)
        self._thr = list(self._saved_thr)
        self._reset_link()
        self._stream = None
        boot = self.options.boot_s
        offsets = _BOOT_NOISE_OFFSETS_S if boot > 0.0 else ()
        self._noise_at = deque(now + max(0.0, boot + off) for off in offsets)

    def _boot_end(self, now: float) -> float:
        """When the boot ends; the first call of any kind switches the controller on."""
        if self._power_at is None:
            self.power_on(now)
        assert self._power_at is not None
        return self._power_at + self.options.boot_s

    # -- Device protocol ---------------------------------------------------------------------

    def connected(self, now: float) -> None:
        self._boot_end(now)
        self._parser = _new_parser()  # no half command carried over from another host

    def disconnected(self, now: float) -> None:
        self._boot_end(now)
        self._reset_link()
        if not self.options.stream_survives_disconnect:
            self._stream = None

    def receive(self, data: bytes, now: float) -> None:
        if not self.booted(now):
            self.stats.deaf_bytes += len(data)
            return
        for event in self._parser.feed(data):
            match event:
                case Packet():
                    self._on_packet(event, now)
                case BadCrc():
                    self.stats.errors += 1
                    self.stats.crc_errors += 1
                    if self.options.crc_error_reply:
                        self._reply(event.id, ErrorReply(DsaError.E_CHECKSUM_ERROR))
                case Oversized():
                    self.stats.errors += 1
                case _:  # garbage between packets, or a terminal query echoed back: ignore
                    pass

    def next_packet(self, now: float) -> bytes | None:
        if not self.booted(now):
            if self._noise_at and now >= self._noise_at[0]:
                self._noise_at.popleft()
                return self._sent(BOOT_NOISE)
            return None
        self._noise_at.clear()  # not sent before the boot ended: nobody was listening
        if self._outbox:
            item = self._outbox.popleft()
            return self._sent(item if isinstance(item, bytes) else self._frame(now, item.rle))
        if self._stream is not None and now >= self._next_frame_at:
            self._next_frame_at = now + self._stream.period_s
            return self._sent(self._frame(now, self._stream.rle))
        return None

    def next_wakeup(self, now: float) -> float | None:
        if not self.booted(now):
            return self._noise_at[0] if self._noise_at else None
        if self._outbox:
            return now
        return self._next_frame_at if self._stream is not None else None

    # -- commands ----------------------------------------------------------------------------

    def _on_packet(self, packet: Packet, now: float) -> None:
        try:
            cmd = decode_command(packet)
        except ProtocolError as exc:
            self.stats.errors += 1
            self._reply(packet.id, ErrorReply(exc.code))
            return
        self.stats.commands += 1
        self._execute(cmd, now)

    def _execute(self, cmd: Command, now: float) -> None:
        match cmd:
            case ConfigureAcquisition():
                self._configure(cmd, now)
            case QueryControllerInfo():
                self._reply(PacketId.QUERY_CONTROLLER_CONFIGURATION, self._controller_info())
            case QuerySensorInfo():
                self._reply(PacketId.QUERY_SENSOR_CONFIGURATION, self._sensor_info())
            case QueryMatrixInfo(matrix=m):
                self._reply_for_matrix(PacketId.QUERY_MATRIX_CONFIGURATION, m, self._matrix_info)
            case SetSensitivity() | SetThreshold():
                self._adjust(cmd)
            case GetSensitivityInfo(matrix=m):
                self._reply_for_matrix(PacketId.GET_SENSITIVITY_ADJUSTMENT_INFO, m, self._sens_info)
            case GetThreshold(matrix=m):
                self._reply_for_matrix(PacketId.GET_MATRIX_THRESHOLD, m, self._thr_info)
            case ReadMatrixMask():
                self._reply_for_matrix(PacketId.READ_MATRIX_MASK, cmd.matrix, self._mask(cmd))
            case ReadDescriptorString():
                self._descriptor(cmd)
            case Loop():
                self._reply(PacketId.LOOP, ErrorReply())
            case QueryControllerState():
                state = _STATE.pack(DsaError.E_SUCCESS, self._status(), self.clock_ms(now))
                self._send(encode_packet(PacketId.QUERY_CONTROLLER_STATE, state))
            case UnknownCommand(id=pid):
                self._reject(pid, DsaError.E_CMD_UNKNOWN)

    def _configure(self, cmd: ConfigureAcquisition, now: float) -> None:
        """0x03: ACK first, always; then one frame (pull) or a stream (push) (§1.6)."""
        self._reply(PacketId.CONFIGURE_DATA_ACQUISITION, ErrorReply())
        self._stream = None
        if cmd.pull and not self.options.streams_on_pull:
            self._outbox.append(_PullFrame(cmd.rle))
        elif cmd.pull:  # old firmware: a stream instead (DsaconOptions.streams_on_pull)
            self._stream = _Stream(1.0 / self.options.max_fps, cmd.rle)
            self._next_frame_at = now
        elif cmd.push:
            fps = self.options.max_fps
            if self.options.honour_framerate:
                fps = min(fps, cmd.framerate)
            self._stream = _Stream(1.0 / fps, cmd.rle)
            self._next_frame_at = now

    def _adjust(self, cmd: SetSensitivity | SetThreshold) -> None:
        """0x0F / 0x13 (§1.4.4-5); persistent writes are applied but never answered."""
        o = self.options
        if not cmd.all_matrices and cmd.matrix >= self.nb_matrices:
            code = DsaError.E_INDEX_OUT_OF_BOUNDS
        elif isinstance(cmd, SetSensitivity):
            ok = 0.0 <= cmd.value <= 1.0  # False for NaN too
            code = _store(self._sens, self._saved_sens, cmd, cmd.value, o.factory_sensitivity, ok)
        else:
            ok = cmd.value <= 4095
            code = _store(self._thr, self._saved_thr, cmd, cmd.value, o.factory_threshold, ok)
        if code != DsaError.E_SUCCESS:
            self.stats.errors += 1
        if not cmd.persistent:
            self._reply(_write_id(cmd), ErrorReply(code))

    def _descriptor(self, cmd: ReadDescriptorString) -> None:
        pid = PacketId.READ_DESCRIPTOR_STRING
        if cmd.kind == DescriptorKind.SENSOR:
            self._reply(pid, DescriptorString(text=self.options.sensor_descriptor))
        elif cmd.kind == DescriptorKind.MATRIX:
            self._reply_for_matrix(pid, cmd.matrix, self._matrix_descriptor)
        else:
            self._reject(pid, DsaError.E_INVALID_PARAMETER)

    # -- replies -----------------------------------------------------------------------------

    def _status(self) -> int:
        acquiring = self._stream is not None or any(
            isinstance(item, _PullFrame) for item in self._outbox
        )
        return _STATUS_OPERABLE | (_STATUS_ACQUIRING if acquiring else 0)

    def _controller_info(self) -> ControllerInfo:
        o = self.options
        return ControllerInfo(
            serial_no=o.serial_no, sw_version=o.sw_version, status_flags=self._status()
        )

    def _sensor_info(self) -> SensorInfo:
        o = self.options
        return SensorInfo(
            nb_matrices=self.nb_matrices,
            generated_by=o.sw_version,
            serial_no=o.serial_no,
            feature_flags=0x01,  # descriptor string set
        )

    def _matrix_info(self, m: int) -> MatrixInfo:
        rows, cols = self._shapes[m]
        size = self.options.texel_size_mm
        return MatrixInfo(
            texel_width=size,
            texel_height=size,
            cells_x=cols,
            cells_y=rows,
            uid=struct.pack("<IBx", self.options.serial_no, m),
            feature_flags=0x03,  # descriptor string set, sensitivity adjustable
        )

    def _sens_info(self, m: int) -> SensitivityInfo:
        factory = self.options.factory_sensitivity
        return SensitivityInfo(adj_flags=_ADJUSTABLE, cur_sens=self._sens[m], fact_sens=factory)

    def _thr_info(self, m: int) -> ThresholdInfo:
        return ThresholdInfo(threshold=self._thr[m])

    def _mask(self, cmd: ReadMatrixMask) -> _MatrixReply:
        if cmd.dynamic:
            return lambda m: MatrixMask.from_array(np.ones(self._shapes[m], dtype=bool))
        return lambda m: MatrixMask.from_array(self._masks[m])

    def _matrix_descriptor(self, m: int) -> DescriptorString:
        rows, cols = self._shapes[m]
        return DescriptorString(text=f"matrix {m} {cols}x{rows}")

    def _reply_for_matrix(self, pid: int, m: int, build: _MatrixReply) -> None:
        if m >= self.nb_matrices:
            self._reject(pid, DsaError.E_INDEX_OUT_OF_BOUNDS)
        else:
            self._reply(pid, build(m))

    def _reject(self, pid: int, code: DsaError) -> None:
        self.stats.errors += 1
        self._reply(pid, ErrorReply(code))

    def _reply(self, pid: int, response: Response) -> None:
        if pid != PacketId.FULL_FRAME:  # an ID-0 reply would be read as a (broken) frame
            self._send(encode_response(pid, response))

    def _send(self, packet: bytes) -> None:
        self._outbox.append(packet)

    # -- frames and bookkeeping --------------------------------------------------------------

    def _frame(self, now: float, rle: bool) -> bytes:
        """One full frame sampled from the world at ``now`` (§1.5)."""
        raw = np.asarray(self._world.tactile_frame(now, self.sensitivity, self.threshold))
        if raw.shape != self._present.shape:
            raise ValueError(f"world sent {raw.shape} texels, expected {self._present.shape}")
        if raw.dtype == np.uint16:  # the sensor model's counts: np.clip's overhead is dearer
            texels = np.minimum(raw, 4095)
        else:
            texels = np.clip(raw, 0, 4095).astype(np.uint16)
        texels[self._absent] = 0
        payload = encode_frame_payload(self.clock_ms(now), texels, rle=rle, rle_breaks=self._breaks)
        self.stats.frames += 1
        return encode_packet(PacketId.FULL_FRAME, payload)

    def _sent(self, packet: bytes) -> bytes:
        self.stats.packets += 1
        self.stats.bytes += len(packet)
        return packet

    def _reset_link(self) -> None:
        self._parser = _new_parser()
        self._outbox.clear()


def _write_id(cmd: SetSensitivity | SetThreshold) -> PacketId:
    """The packet ID of a sensitivity or threshold write."""
    if isinstance(cmd, SetSensitivity):
        return PacketId.ADJUST_MATRIX_SENSITIVITY
    return PacketId.SET_MATRIX_THRESHOLD


def _store(
    current: list[_T],
    saved: list[_T],
    cmd: SetSensitivity | SetThreshold,
    value: _T,
    factory: _T,
    in_range: bool,
) -> DsaError:
    """Apply a sensitivity or threshold write (reset: the factory value; persistent: saved too)."""
    if not (cmd.reset or in_range):
        return DsaError.E_RANGE_ERROR
    new = factory if cmd.reset else value
    for m in range(len(current)) if cmd.all_matrices else (cmd.matrix,):
        current[m] = new
        if cmd.persistent:
            saved[m] = new
    return DsaError.E_SUCCESS


def _new_parser() -> PacketParser:
    # Payload-less commands carry no CRC (§1.2); no command has a long payload.
    return PacketParser(max_payload=_MAX_COMMAND_PAYLOAD, crc_when_empty=False)


def _check_masks(
    shapes: Sequence[tuple[int, int]], masks: Sequence[npt.ArrayLike] | None
) -> list[npt.NDArray[np.bool_]]:
    if masks is None:
        return [np.ones(shape, dtype=bool) for shape in shapes]
    out = [np.asarray(m, dtype=bool) for m in masks]
    if [m.shape for m in out] != list(shapes):
        raise ValueError(f"static masks {[m.shape for m in out]} do not match matrices {shapes}")
    return out


def _rle_breaks(shapes: Sequence[tuple[int, int]], mode: str) -> tuple[int, ...]:
    """Texel indices where an RLE run must restart (none, matrix starts or row starts)."""
    if mode == "none":
        return ()
    starts = texel_offsets([MatrixShape(c, r) for r, c in shapes])
    if mode == "matrix":
        return tuple(starts)
    return tuple(
        start + row * cols
        for start, (rows, cols) in zip(starts, shapes, strict=True)
        for row in range(rows)
    )
