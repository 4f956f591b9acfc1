"""Sans-I/O codec throughput: the DSACON32m packet parser and the SDH2 reply parser, in MB/s."""

from __future__ import annotations

import time

import numpy as np

from sdh2svc.protocol import dsa, sdh


def _frames(n: int) -> bytes:
    """``n`` RLE frames with a moving contact blob and noise: realistic sizes (~100–300 B)."""
    rng = np.random.default_rng(1)
    out = bytearray()
    for i in range(n):
        tex = np.zeros(486, dtype=np.uint16)
        start = 84 + (i % 60)
        tex[start : start + 18] = rng.integers(200, 2000, 18)
        payload = dsa.encode_frame_payload(1000 + 33 * i, tex, rle=True)
        out += dsa.encode_packet(dsa.PacketId.FULL_FRAME, payload)
    return bytes(out)


def _throughput(feed, data: bytes, chunk: int) -> float:
    t0 = time.perf_counter()
    for i in range(0, len(data), chunk):
        feed(data[i : i + chunk])
    return len(data) / (time.perf_counter() - t0) / 1e6


def run() -> dict[str, float]:
    data = _frames(4000)
    sizes = []
    p = dsa.PacketParser()
    for ev in p.feed(data):
        assert isinstance(ev, dsa.Packet)
        sizes.append(len(ev.payload) + 8)
    out = {}
    print(f"protocol codecs ({len(data) / 1e6:.1f} MB of DSACON32m frames, "
          f"mean frame {np.mean(sizes):.0f} B)")  # fmt: skip
    for chunk in (64, 4096):
        parser = dsa.PacketParser()
        mbs = _throughput(parser.feed, data, chunk)
        out[f"dsa_{chunk}"] = mbs
        print(f"  DSACON32m parser, {chunk:5d}-byte chunks: {mbs:6.1f} MB/s "
              f"({mbs * 1e6 / 11520:6.0f}× the 115200-baud line)")  # fmt: skip
    decode = time.perf_counter()
    for ev in dsa.PacketParser().feed(data[: len(data) // 4]):
        dsa.decode_frame_payload(ev.payload, 486)
    per = (time.perf_counter() - decode) / 1000 * 1e6
    print(f"  frame decode (RLE → 486 texels): {per:6.1f} µs per frame")
    reply = sdh.encode_reply("pos", [0.0, -45.0, 0.0, -90.0, 0.0, -45.0, 0.0]) * 20000
    mbs = _throughput(sdh.ReplyParser().feed, reply, 64)
    out["sdh_ascii"] = mbs
    print(f"  SDH2 ASCII reply parser, 64-byte chunks: {mbs:6.1f} MB/s")
    binary = sdh.encode_binary_reply(sdh.BinaryCommand.POS, 0, [0.0] * 7) * 20000
    mbs = _throughput(sdh.ReplyParser().feed, binary, 64)
    out["sdh_binary"] = mbs
    print(f"  SDH2 binary reply parser, 64-byte chunks: {mbs:6.1f} MB/s")
    return out
