"""Fault injection for emulated serial links: bit errors, dropped bytes, truncated packets.

Sans-I/O and deterministic: every decision comes from a ``random.Random`` seeded from
:class:`FaultConfig`, with separate streams for the two directions, and device→host faults are
decided per whole packet (not per transmitted chunk). The same seed and the same packets therefore
give the same faults however the event loop happens to schedule the line. Time-based faults (boot
silence, unplugging) need a clock and live in :mod:`sdh2svc.sim.endpoint`.
"""

from __future__ import annotations

import math
import random
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from enum import StrEnum


class FaultKind(StrEnum):
    """Keys of :attr:`LinkStats.faults`; each counts the unit named in its comment."""

    BIT_ERROR = "bit_error"  # device→host bits flipped
    DROP_BYTE = "drop_byte"  # device→host bytes lost (they still took line time)
    TRUNCATE_PACKET = "truncate_packet"  # packets cut short
    TRUNCATED_BYTES = "truncated_bytes"  # bytes never sent because of those cuts
    RX_BIT_ERROR = "rx_bit_error"  # host→device bits flipped
    RX_DROP_BYTE = "rx_drop_byte"  # host→device bytes lost
    DISCONNECT = "disconnect"  # disconnect() calls
    MUTED_RX_BYTE = "muted_rx_byte"  # host bytes ignored while booting or unplugged
    UNPLUGGED_TX_BYTE = "unplugged_tx_byte"  # device bytes lost while unplugged


@dataclass(frozen=True, slots=True)
class FaultConfig:
    """What goes wrong on a link. Everything is off by default.

    Rates are probabilities: per bit (``bit_error_rate``), per byte (``drop_byte_rate``) or per
    packet (``truncate_packet_rate``). They apply to device→host bytes, and bit errors and drops
    also to host→device bytes when ``host_to_device`` is set.
    """

    bit_error_rate: float = 0.0
    drop_byte_rate: float = 0.0
    truncate_packet_rate: float = 0.0
    boot_delay_s: float = 0.0
    host_to_device: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("bit_error_rate", "drop_byte_rate", "truncate_packet_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1]")
        if not self.boot_delay_s >= 0.0:
            raise ValueError("boot_delay_s must be >= 0")


@dataclass(frozen=True, slots=True)
class FaultedPacket:
    """A packet after device→host faults: ``data`` is what goes on the line (bit errors applied,
    truncation done); positions in ``dropped`` take line time but never reach the host."""

    data: bytes
    dropped: frozenset[int] = frozenset()

    def __len__(self) -> int:
        return len(self.data)

    def slice(self, start: int, stop: int) -> bytes:
        """The bytes of line positions ``start:stop`` that reach the host."""
        if not self.dropped:
            return self.data[start:stop]
        return bytes(self.data[i] for i in range(start, stop) if i not in self.dropped)


def bernoulli_positions(rng: random.Random, n: int, p: float) -> Iterator[int]:
    """Indices in ``range(n)`` each chosen with probability ``p``, ascending.

    Draws the gaps between hits from the geometric distribution, so the cost is proportional to
    the number of hits, not to ``n`` (a 100 kB packet at BER 1e-3 costs ~800 draws, not 800 000).
    """
    if p <= 0.0 or n <= 0:
        return
    log_miss = math.log1p(-p) if p < 1.0 else -math.inf
    pos = -1
    while True:
        pos += 1 + int(math.log(1.0 - rng.random()) / log_miss)
        if pos >= n:
            return
        yield pos


class FaultInjector:
    """Applies a :class:`FaultConfig` to packets and received bytes, counting into ``counts``."""

    def __init__(self, config: FaultConfig, counts: Counter[str] | None = None) -> None:
        self.config = config
        self.counts: Counter[str] = Counter() if counts is None else counts
        # One stream per direction: host input arrives at arbitrary moments and must not shift
        # the device→host fault sequence.
        self._tx_rng = random.Random(f"{config.seed}:tx")
        self._rx_rng = random.Random(f"{config.seed}:rx")
        # every rate 0: apply_tx passes packets through, drawing nothing (its count's key is
        # there all the same, as where bytes may drop)
        self._clean = not (config.truncate_packet_rate or config.bit_error_rate
                           or config.drop_byte_rate)  # fmt: skip
        if self._clean:
            self.counts[FaultKind.DROP_BYTE] += 0

    def apply_tx(self, packet: bytes) -> FaultedPacket:
        """Truncate, flip bits and mark dropped bytes in one device→host packet."""
        cfg, rng = self.config, self._tx_rng
        if self._clean:  # no rate set: nothing to draw, nothing dropped (the usual case)
            return FaultedPacket(packet)
        if packet and cfg.truncate_packet_rate and rng.random() < cfg.truncate_packet_rate:
            cut = rng.randrange(len(packet))
            self.counts[FaultKind.TRUNCATE_PACKET] += 1
            self.counts[FaultKind.TRUNCATED_BYTES] += len(packet) - cut
            packet = packet[:cut]
        data = self._flip_bits(packet, rng, FaultKind.BIT_ERROR)
        dropped = frozenset(bernoulli_positions(rng, len(data), cfg.drop_byte_rate))
        self.counts[FaultKind.DROP_BYTE] += len(dropped)
        return FaultedPacket(data, dropped)

    def apply_rx(self, data: bytes) -> bytes:
        """Host→device bytes as the device receives them (unchanged unless ``host_to_device``)."""
        cfg, rng = self.config, self._rx_rng
        if not cfg.host_to_device:
            return data
        data = self._flip_bits(data, rng, FaultKind.RX_BIT_ERROR)
        dropped = set(bernoulli_positions(rng, len(data), cfg.drop_byte_rate))
        if not dropped:
            return data
        self.counts[FaultKind.RX_DROP_BYTE] += len(dropped)
        return bytes(b for i, b in enumerate(data) if i not in dropped)

    def _flip_bits(self, data: bytes, rng: random.Random, kind: FaultKind) -> bytes:
        flips = list(bernoulli_positions(rng, 8 * len(data), self.config.bit_error_rate))
        if not flips:
            return data
        out = bytearray(data)
        for bit in flips:
            out[bit >> 3] ^= 1 << (bit & 7)
        self.counts[kind] += len(flips)
        return bytes(out)
