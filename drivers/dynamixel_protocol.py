"""Dynamixel Protocol 2.0 packets: CRC-16, byte stuffing, encoding and a stream parser.

Used by the bus emulator (the driver itself talks through the real dynamixel-sdk,
so that tests exercise the SDK's own packet code against this independent one).

Wire format (ROBOTIS e-Manual, Protocol 2.0)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | params... | CRC_L CRC_H

LEN counts INST, params and CRC after stuffing. Inside INST+params every
``FF FF FD`` is sent as ``FF FF FD FD`` so that a header never appears in the
body. The CRC (poly 0x8005, init 0, no reflection) covers everything from the
first header byte to the last (stuffed) parameter byte.
"""
from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_FACTORY_RESET = 0x06
INST_REBOOT = 0x08
INST_CLEAR = 0x10
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93

# Status packet error field (low 7 bits: a number, bit 7: hardware alert).
ERR_RESULT_FAIL = 1
ERR_INSTRUCTION = 2
ERR_CRC = 3
ERR_DATA_RANGE = 4
ERR_DATA_LENGTH = 5
ERR_DATA_LIMIT = 6
ERR_ACCESS = 7
ERR_ALERT = 0x80


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0), as the e-Manual specifies."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert FD after every FF FF FD in ``body`` (instruction + parameters)."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the FD that follows every FF FF FD in a received body."""
    out = bytearray()
    i = 0
    n = len(body)
    while i < n:
        b = body[i]
        out.append(b)
        if b == 0xFD and i + 1 < n and body[i + 1] == 0xFD and len(out) >= 3 and out[-3] == 0xFF \
                and out[-2] == 0xFF:
            i += 1  # skip the stuffed FD
        i += 1
    return bytes(out)


def encode(dxl_id: int, inst: int, params: bytes = b"") -> bytes:
    """A complete packet (instruction or, with inst=0x55, status)."""
    body = stuff(bytes([inst]) + bytes(params))
    length = len(body) + 2
    head = HEADER + bytes([dxl_id & 0xFF, length & 0xFF, length >> 8])
    pkt = head + body
    crc = crc16(pkt)
    return pkt + bytes([crc & 0xFF, crc >> 8])


def encode_status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    return encode(dxl_id, INST_STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass
class Packet:
    """A decoded packet. For a status packet ``error`` is the first parameter and
    ``params`` the rest."""

    dxl_id: int
    inst: int
    params: bytes
    crc_ok: bool = True
    raw: bytes = b""

    @property
    def error(self) -> int:
        return self.params[0] if self.inst == INST_STATUS and self.params else 0

    @property
    def data(self) -> bytes:
        return self.params[1:] if self.inst == INST_STATUS else self.params


def decode(raw: bytes) -> Packet:
    """Decode exactly one packet; raises ValueError on a malformed one."""
    packets = list(PacketParser().feed(raw))
    if len(packets) != 1:
        raise ValueError(f"expected one packet, found {len(packets)} in {raw.hex(' ')}")
    return packets[0]


class PacketParser:
    """Incremental parser: feed bytes as they arrive, get whole packets out.

    Garbage before a header is skipped. A packet with a bad CRC is still
    returned (``crc_ok=False``) so that a servo can answer it with a CRC error
    or ignore it, as it chooses.
    """

    MAX_LEN = 1024

    def __init__(self):
        self._buf = bytearray()

    def feed(self, data: bytes):
        self._buf.extend(data)
        while True:
            pkt = self._next()
            if pkt is None:
                return
            yield pkt

    def _next(self) -> Packet | None:
        buf = self._buf
        start = buf.find(HEADER[:3])
        while start >= 0 and start + 3 < len(buf) and buf[start + 3] != 0x00:
            start = buf.find(HEADER[:3], start + 1)
        if start < 0:
            # keep a possible partial header at the end
            keep = 0
            for k in (2, 1):
                if len(buf) >= k and buf[-k:] == HEADER[:k]:
                    keep = k
                    break
            del buf[:len(buf) - keep]
            return None
        del buf[:start]
        if len(buf) < 7:
            return None
        length = buf[5] | (buf[6] << 8)
        if length < 3 or length > self.MAX_LEN:
            del buf[:3]  # not a real header: resynchronise after it
            return self._next()
        total = 7 + length
        if len(buf) < total:
            return None
        raw = bytes(buf[:total])
        del buf[:total]
        crc = raw[-2] | (raw[-1] << 8)
        body = unstuff(raw[7:-2])
        return Packet(raw[4], body[0], body[1:], crc16(raw[:-2]) == crc, raw)


def u32(value: int) -> bytes:
    return (value & 0xFFFFFFFF).to_bytes(4, "little")


def to_signed(value: int, nbytes: int) -> int:
    """Two's complement of an unsigned register value (the SDK returns unsigned)."""
    bits = 8 * nbytes
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >= 1 << (bits - 1) else value
