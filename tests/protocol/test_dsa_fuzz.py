"""Fuzz tests for the DSACON32m PacketParser (protocols.md §1.2, §1.7).

Random bytes and damaged packet streams (bit flips, dropped bytes, truncated packets, inserted
boot-noise queries and garbage) are fed in random chunks. The parser must never raise, must
account for every byte, must keep its buffer bounded, and must deliver every packet that the
damage did not touch — in order — plus a clean packet appended after the damage.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sdh2svc.protocol import dsa
from sdh2svc.protocol.dsa import (
    BadCrc,
    BootNoise,
    GarbageSkipped,
    Oversized,
    Packet,
    PacketParser,
)

FUZZ = settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
MAX_PAYLOAD = 48
EVENT_TYPES = (Packet, BadCrc, Oversized, GarbageSkipped, BootNoise)
MARKER = dsa.encode_packet(0x14, b"marker!")  # short, so damage often leaves it pending
BOOT = b"\x1b[5n"

# Garbage biased towards the bytes that matter to the parser: preamble and boot-query bytes.
garbage = st.binary(min_size=1, max_size=24) | st.lists(
    st.sampled_from([0xAA, 0xAA, 0x00, 0x1B, 0x5B, 0x35, 0x6E, 0xFF]), min_size=1, max_size=24
).map(bytes)
packet_specs = st.tuples(
    st.integers(0, 255).filter(lambda i: i != 0xAA), st.binary(max_size=MAX_PAYLOAD - 8)
)
mutations = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 10**6), st.integers(0, 7)),
    st.tuples(st.just("drop"), st.integers(0, 10**6), st.integers(1, 6)),
    st.tuples(st.just("truncate"), st.integers(0, 10**6), st.integers(0, 10**6)),
    st.tuples(st.just("boot"), st.integers(0, 10**6), st.just(0)),
    st.tuples(st.just("garbage"), st.integers(0, 10**6), garbage),
)
cuts = st.lists(st.integers(0, 10**6), max_size=16)


@dataclass
class Segment:
    data: bytes
    intact: bool  # an untouched, valid packet that must come out


def damage(specs: list[tuple[int, bytes]], muts: list[tuple[str, int, object]]) -> list[Segment]:
    """Encode the packets and apply each mutation to one segment (or insert before it)."""
    segs = [Segment(dsa.encode_packet(pid, payload), True) for pid, payload in specs]
    for kind, where, arg in muts:
        i = where % (len(segs) + 1)
        if kind in ("boot", "garbage"):
            inserted = BOOT if kind == "boot" else arg
            assert isinstance(inserted, bytes)
            segs.insert(i, Segment(inserted, False))
            continue
        if i == len(segs):
            continue
        seg = segs[i]
        data = bytearray(seg.data)
        pos = where % len(data) if data else 0
        assert isinstance(arg, int)
        if kind == "flip" and data:
            data[pos] ^= 1 << arg
        elif kind == "drop":
            del data[pos : pos + arg]
        elif kind == "truncate":
            del data[arg % (len(data) + 1) :]
        if bytes(data) != seg.data:
            segs[i] = Segment(bytes(data), False)
    return segs


def chunked(data: bytes, points: list[int]) -> list[bytes]:
    edges = [0, *sorted({p % (len(data) + 1) for p in points}), len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


def wire_size(pkt: Packet) -> int:
    return 6 + len(pkt.payload) + (2 if pkt.payload else 0)


def run(parser: PacketParser, stream: bytes, points: list[int]) -> list[dsa.Event]:
    """Feed ``stream`` in chunks, checking the per-feed invariants; then flush."""
    events: list[dsa.Event] = []
    for chunk in chunked(stream, points):
        events += parser.feed(chunk)
        assert parser.buffered <= MAX_PAYLOAD + 8
    events += parser.flush()
    assert parser.buffered == 0
    return events


def check_accounting(parser: PacketParser, events: list[dsa.Event], total: int) -> None:
    assert all(isinstance(e, EVENT_TYPES) for e in events)
    pkts = [e for e in events if isinstance(e, Packet)]
    boots = sum(isinstance(e, BootNoise) for e in events)
    skipped = sum(e.nbytes for e in events if isinstance(e, GarbageSkipped))
    assert sum(map(wire_size, pkts)) + 4 * boots + skipped == total
    assert parser.packets == len(pkts) and parser.boot_noise == boots
    assert parser.garbage_bytes == skipped
    assert parser.crc_errors == sum(isinstance(e, BadCrc) for e in events)
    assert parser.oversized == sum(isinstance(e, Oversized) for e in events)
    assert all(len(p.payload) <= MAX_PAYLOAD for p in pkts)
    assert all(0 <= e.id <= 255 and e.id != 0xAA for e in events if isinstance(e, Packet))
    assert parser.resyncs <= sum(isinstance(e, GarbageSkipped) for e in events)


def is_subsequence(needles: list[bytes], haystack: list[bytes]) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


@FUZZ
@given(st.binary(max_size=400), cuts)
def test_random_bytes(noise: bytes, points: list[int]) -> None:
    parser = PacketParser(max_payload=MAX_PAYLOAD)
    stream = noise + MARKER
    events = run(parser, stream, points)
    check_accounting(parser, events, len(stream))
    last = [e for e in events if isinstance(e, Packet)][-1]
    assert dsa.encode_packet(last.id, last.payload) == MARKER


@FUZZ
@given(
    st.lists(packet_specs, min_size=1, max_size=8),
    st.lists(mutations, max_size=8),
    cuts,
)
def test_damaged_streams(
    specs: list[tuple[int, bytes]], muts: list[tuple[str, int, object]], points: list[int]
) -> None:
    segs = [*damage(specs, muts), Segment(MARKER, True)]
    stream = b"".join(s.data for s in segs)
    parser = PacketParser(max_payload=MAX_PAYLOAD)
    events = run(parser, stream, points)
    check_accounting(parser, events, len(stream))
    got = [dsa.encode_packet(e.id, e.payload) for e in events if isinstance(e, Packet)]
    assert got[-1] == MARKER
    assert is_subsequence([s.data for s in segs if s.intact], got)
    # inserted boot-noise queries are never mistaken for garbage while they stand alone
    lone_boots = sum(s.data == BOOT for s in segs)
    assert parser.boot_noise >= lone_boots


@FUZZ
@given(st.lists(packet_specs, min_size=1, max_size=6), st.integers(1, MAX_PAYLOAD), cuts)
def test_frames_behind_large_corrupt_header(
    specs: list[tuple[int, bytes]], announced: int, points: list[int]
) -> None:
    # A header announcing up to MAX_PAYLOAD bytes swallows the packets after it; all of them
    # must still come out once the parser has seen enough bytes (or is flushed).
    header = dsa.PREAMBLE + bytes([0x00, announced, 0x00])
    good = [dsa.encode_packet(pid, payload) for pid, payload in specs]
    stream = header + b"".join(good) + MARKER
    parser = PacketParser(max_payload=MAX_PAYLOAD)
    events = run(parser, stream, points)
    check_accounting(parser, events, len(stream))
    got = [dsa.encode_packet(e.id, e.payload) for e in events if isinstance(e, Packet)]
    assert is_subsequence([*good, MARKER], got)
