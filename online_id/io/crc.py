"""CRC-8 SAE J1850, the checksum in byte 7 of every output frame.

Parameters (Rocksoft model): width 8, poly 0x1D, init 0xFF, refin false,
refout false, xorout 0xFF; the check value of ASCII ``"123456789"`` is 0x4B.
The same CRC is ``crccheck.crc.Crc8SaeJ1850`` and AUTOSAR's ``Crc_CalculateCRC8``.
"""

from __future__ import annotations

POLY = 0x1D
INIT = 0xFF
XOROUT = 0xFF
CHECK = 0x4B
"""CRC of ``b"123456789"``."""


def _make_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _make_table(POLY)


def crc8_j1850(data: bytes | bytearray | memoryview) -> int:
    """CRC-8 SAE J1850 of ``data`` (MSB first, table driven).

    Notes
    -----
    For each byte :math:`b`: :math:`crc \\leftarrow T[crc \\oplus b]` with
    :math:`T` the table of the polynomial :math:`x^8 + x^4 + x^3 + x^2 + 1`;
    the register starts at 0xFF and the result is XORed with 0xFF.
    """
    crc = INIT
    table = _TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc ^ XOROUT
