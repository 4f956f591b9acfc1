"""The CRC-16 shared by the DSACON32m packets and the SDH2 binary frames (protocols.md §1.2.1).

A right-shifting update over a left-shifting (non-reflected) CRC-CCITT table, initial value
0xFFFF, no final XOR. It is not a catalogued CRC-16; it is implemented literally, as SDHLibrary
does. Check value over ASCII ``123456789``: 0x6EB4.
"""

from __future__ import annotations

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


def crc16(data: bytes | bytearray | memoryview, crc: int = CRC_INIT) -> int:
    """CRC of ``data`` continuing from ``crc`` (pass a previous result to chain chunks)."""
    table = CRC_TABLE
    for b in data:
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return crc
