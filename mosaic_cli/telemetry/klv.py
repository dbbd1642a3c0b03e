"""MISB ST 0601 (UAS Datalink Local Set) KLV: the tags a map needs, decoded and encoded.

Only the tags below are read; the others are skipped by their BER lengths.  Every packet's
checksum (tag 1, ST 0601 section 6.5: the 16-bit sum of the packet's bytes as big-endian
words, from the first key byte through the checksum's own tag and length) is verified; a
packet that fails it is dropped and counted, never half-used.

    2  Precision Time Stamp  (uint64 microseconds since 1970)
    5  Platform Heading      6 Platform Pitch     7 Platform Roll
    13 Sensor Latitude       14 Sensor Longitude  15 Sensor True Altitude
    16 Sensor HFOV           18 Sensor Relative Azimuth
    19 Sensor Relative Elevation                  20 Sensor Relative Roll
    25 Frame Center Elevation (the ground height: height = true altitude - it)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosaic_cli.errors import BadInput
from mosaic_cli.telemetry.flight_log import FlightLog, FlightLogBuilder

UAS_LS_KEY = bytes.fromhex("060E2B34020B01010E01030101000000")
VERSION = 17

# tag -> (name, struct format, lo, hi, signed-range style); value = lo + raw * (hi - lo) / span
_INT_ERROR = {"i": -(2**31), "h": -(2**15)}


@dataclass(frozen=True)
class _Map:
    fmt: str  # struct code: B H I Q h i
    lo: float
    hi: float

    @property
    def size(self) -> int:
        return struct.calcsize(">" + self.fmt)

    @property
    def span(self) -> float:
        bits = self.size * 8
        # ST 0601 maps signed values over +-(2^(n-1) - 1), unsigned over 0..2^n - 1
        return float(2**bits - 2) if self.fmt.islower() else float(2**bits - 1)

    def decode(self, raw: bytes) -> float:
        value = struct.unpack(">" + self.fmt, raw)[0]
        if self.fmt in _INT_ERROR and value == _INT_ERROR[self.fmt]:
            return float("nan")  # the "error / no value" indicator of signed tags
        if self.fmt.islower():
            return value * (self.hi - self.lo) / self.span
        return self.lo + value * (self.hi - self.lo) / self.span

    def encode(self, value: float) -> bytes:
        if self.fmt.islower():
            if not np.isfinite(value):
                return struct.pack(">" + self.fmt, _INT_ERROR[self.fmt])
            raw = int(round(value * self.span / (self.hi - self.lo)))
            limit = 2 ** (self.size * 8 - 1) - 1
            return struct.pack(">" + self.fmt, max(-limit, min(limit, raw)))
        raw = int(round((value - self.lo) * self.span / (self.hi - self.lo)))
        return struct.pack(">" + self.fmt, max(0, min(int(self.span), raw)))


TAGS: dict[int, tuple[str, _Map]] = {
    5: ("platform_heading", _Map("H", 0.0, 360.0)),
    6: ("platform_pitch", _Map("h", -20.0, 20.0)),
    7: ("platform_roll", _Map("h", -50.0, 50.0)),
    13: ("lat", _Map("i", -90.0, 90.0)),
    14: ("lon", _Map("i", -180.0, 180.0)),
    15: ("alt", _Map("H", -900.0, 19000.0)),
    16: ("hfov", _Map("H", 0.0, 180.0)),
    18: ("sensor_azimuth", _Map("I", 0.0, 360.0)),
    19: ("sensor_elevation", _Map("i", -180.0, 180.0)),
    20: ("sensor_roll", _Map("I", 0.0, 360.0)),
    25: ("ground_alt", _Map("H", -900.0, 19000.0)),
}


def checksum(data: bytes) -> int:
    total = 0
    for i, byte in enumerate(data):
        total += byte << (8 * ((i + 1) % 2))
    return total & 0xFFFF


def _ber_length(n: int) -> bytes:
    if n < 128:
        return bytes([n])
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([0x80 | len(body)]) + body


def _read_ber(buf: bytes, pos: int) -> tuple[int, int]:
    first = buf[pos]
    if first < 128:
        return first, pos + 1
    count = first & 0x7F
    if count == 0 or count > 8 or pos + 1 + count > len(buf):
        raise ValueError("bad BER length")
    return int.from_bytes(buf[pos + 1 : pos + 1 + count], "big"), pos + 1 + count


def encode_packet(time_us: int, values: dict[str, float]) -> bytes:
    """One ST 0601 local set: timestamp, the given named values, version, checksum."""
    body = bytearray()
    body += bytes([2, 8]) + struct.pack(">Q", int(time_us))
    for tag, (name, mapping) in TAGS.items():
        if name in values and values[name] is not None:
            body += bytes([tag, mapping.size]) + mapping.encode(float(values[name]))
    body += bytes([65, 1, VERSION])
    body += bytes([1, 2])
    head = UAS_LS_KEY + _ber_length(len(body) + 2)
    return head + bytes(body) + struct.pack(">H", checksum(head + bytes(body)))


@dataclass
class KlvPacket:
    time_us: int | None
    values: dict[str, float]


def decode_stream(data: bytes) -> tuple[list[KlvPacket], int]:
    """Every UAS local set in ``data`` (a raw KLV stream): (packets, packets dropped for a
    failed checksum or a broken structure).  Other KLV keys are skipped."""
    packets: list[KlvPacket] = []
    dropped = 0
    pos = 0
    while True:
        start = data.find(UAS_LS_KEY, pos)
        if start < 0:
            return packets, dropped
        try:
            length, body_at = _read_ber(data, start + 16)
        except (ValueError, IndexError):
            dropped += 1
            pos = start + 16
            continue
        end = body_at + length
        if end > len(data) or length < 4:
            dropped += 1
            pos = start + 16
            continue
        packet = data[start:end]
        body = data[body_at:end]
        if body[-4:-2] != bytes([1, 2]) or checksum(packet[:-2]) != struct.unpack(">H", body[-2:])[0]:
            dropped += 1
            pos = start + 16
            continue
        try:
            packets.append(_decode_body(body[:-4]))
        except (ValueError, IndexError, struct.error):
            dropped += 1
        pos = end


def _decode_body(body: bytes) -> KlvPacket:
    values: dict[str, float] = {}
    time_us = None
    pos = 0
    while pos < len(body):
        tag, pos = _read_ber(body, pos)  # tags are BER-OID; all used here are < 128
        length, pos = _read_ber(body, pos)
        raw = body[pos : pos + length]
        if len(raw) != length:
            raise ValueError("truncated tag")
        pos += length
        if tag == 2 and length == 8:
            time_us = struct.unpack(">Q", raw)[0]
        elif tag in TAGS and length == TAGS[tag][1].size:
            values[TAGS[tag][0]] = TAGS[tag][1].decode(raw)
    return KlvPacket(time_us, values)


def log_from_packets(packets: list[KlvPacket], source: str, times: list[float] | None = None) -> FlightLog:
    """A ``FlightLog`` from decoded packets; ``times`` (seconds, e.g. the container's timestamps)
    take precedence over the packets' own Precision Time Stamps."""
    if not packets:
        raise BadInput(f"{source}: no MISB ST 0601 packet (UAS Datalink Local Set) in it")
    builder = FlightLogBuilder()
    stamps = [p.time_us for p in packets]
    if times is None and any(s is None for s in stamps):
        raise BadInput(f"{source}: KLV packets without a Precision Time Stamp (tag 2)")
    first = min(s for s in stamps if s is not None) if times is None else 0
    for k, p in enumerate(packets):
        v = p.values
        t = times[k] if times is not None else (p.time_us - first) / 1e6
        heading = v.get("platform_heading", 0.0)
        yaw = (heading + v.get("sensor_azimuth", 0.0)) % 360.0 if "platform_heading" in v or "sensor_azimuth" in v else None
        if yaw is not None and yaw > 180:
            yaw -= 360.0
        roll = v.get("sensor_roll")
        if roll is not None and roll > 180:
            roll -= 360.0
        height = v["alt"] - v["ground_alt"] if "alt" in v and "ground_alt" in v else None
        builder.add(t, lat=v.get("lat"), lon=v.get("lon"), alt=v.get("alt"), height=height, yaw=yaw,
                    pitch=v.get("sensor_elevation"), roll=roll, hfov=v.get("hfov"))
    return builder.build(f"{source} (MISB ST 0601 KLV)", clock_time=times is None)


def read_klv(path: str | Path) -> FlightLog:
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise BadInput(f"{p}: cannot read ({exc.strerror})") from None
    packets, dropped = decode_stream(data)
    track = log_from_packets(packets, str(p))
    if dropped:
        track.notes.append(f"{dropped} KLV packets failed their checksum and were dropped")
    return track
