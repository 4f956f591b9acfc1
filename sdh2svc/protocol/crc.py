"""The CRC-16 shared by the DSACON32m packets and the SDH2 binary frames (protocols.md §1.2.1).

A right-shifting update over a left-shifting (non-reflected) CRC-CCITT table, initial value
0xFFFF, no final XOR. It is not a catalogued CRC-16; it is implemented literally, as SDHLibrary
does. Check value over ASCII ``123456789``: 0x6EB4.

Speed: the per-byte update ``crc = (crc >> 8) ^ T[(crc ^ b) & 0xFF]`` applied to two bytes in a
row depends only on ``crc ^ (b0 | b1 << 8)`` (the 16-bit register XOR the little-endian word), so
a 65536-entry table of that double step (:data:`CRC_TABLE16`) takes a buffer a word at a time:
the same result, half the Python-level iterations (a tactile frame's packet is hundreds of
bytes, several times per frame period in fast mode).
"""

from __future__ import annotations

import sys
from array import array

import numpy as np

CRC_INIT = 0xFFFF


def _table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


CRC_TABLE: tuple[int, ...] = _table()


def _table16() -> array[int]:
    """Two per-byte steps from register ``w`` (already XORed with the word): with x its low
    and y its high byte, ``T[x] >> 8 ^ T[(y ^ T[x]) & 0xFF]``."""
    t = np.array(CRC_TABLE, dtype=np.uint32)
    w = np.arange(65536, dtype=np.uint32)
    tx = t[w & 0xFF]
    return array("H", ((tx >> 8) ^ t[((w >> 8) ^ tx) & 0xFF]).astype(np.uint16).tobytes())


CRC_TABLE16: array[int] = _table16()  # 128 KiB of u16, not 65536 int objects: cache-friendly
_SWAP = sys.byteorder != "little"


# CRCs of short byte strings already seen: a driver sends the same requests (`pos`, `m`) and
# an emulator checks them, again and again; cleared when full
_SEEN: dict[bytes, int] = {}
_SEEN_LEN, _SEEN_MAX = 48, 4096


def crc16(data: bytes | bytearray | memoryview, crc: int = CRC_INIT) -> int:
    """CRC of ``data`` continuing from ``crc`` (pass a previous result to chain chunks)."""
    n = len(data)
    if n <= _SEEN_LEN and crc == CRC_INIT and type(data) is bytes:
        seen = _SEEN.get(data)
        if seen is None:
            if len(_SEEN) >= _SEEN_MAX:
                _SEEN.clear()
            seen = _SEEN[data] = _crc16(data, n, crc)
        return seen
    return _crc16(data, n, crc)


def _crc16(data: bytes | bytearray | memoryview, n: int, crc: int) -> int:
    if n < 8:
        table = CRC_TABLE
        for b in bytes(data):
            crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
        return crc
    words = array("H", bytes(data[: n & ~1]) if n & 1 else bytes(data))
    if _SWAP:
        words.byteswap()  # the words are little-endian on the wire
    table16 = CRC_TABLE16
    for w in words:
        crc = table16[crc ^ w]
    if n & 1:
        crc = (crc >> 8) ^ CRC_TABLE[(crc ^ data[-1]) & 0xFF]
    return crc
