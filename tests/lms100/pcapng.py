"""A tiny pcapng reader for the tests: TCP payloads of Ethernet/IPv4 (or raw IPv4) captures, in file order."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class TcpSegment:
    src_port: int
    dst_port: int
    seq: int
    payload: bytes


def _ip_tcp(packet: bytes) -> TcpSegment | None:
    if len(packet) < 20 or packet[0] >> 4 != 4 or packet[9] != 6:
        return None
    ihl = (packet[0] & 0x0F) * 4
    total = struct.unpack_from(">H", packet, 2)[0]
    tcp = packet[ihl:total]
    src, dst, seq = struct.unpack_from(">HHI", tcp, 0)
    off = (tcp[12] >> 4) * 4
    return TcpSegment(src, dst, seq, bytes(tcp[off:]))


def tcp_segments(path: Path) -> list[TcpSegment]:
    """Every IPv4/TCP segment with a non-empty payload, in capture order."""
    data = path.read_bytes()
    pos = 0
    endian = "<"
    linktypes: list[int] = []
    out: list[TcpSegment] = []
    while pos + 12 <= len(data):
        btype = struct.unpack_from(endian + "I", data, pos)[0]
        if btype == 0x0A0D0D0A:  # section header: byte-order magic decides the endianness
            endian = "<" if data[pos + 8 : pos + 12] == b"\x4d\x3c\x2b\x1a" else ">"
            linktypes = []
        blen = struct.unpack_from(endian + "I", data, pos + 4)[0]
        if blen < 12 or pos + blen > len(data):
            raise ValueError(f"corrupt pcapng block at offset {pos}")
        body = data[pos + 8 : pos + blen - 4]
        if btype == 1:  # interface description
            linktypes.append(struct.unpack_from(endian + "H", body, 0)[0])
        elif btype == 6:  # enhanced packet
            iface, _th, _tl, caplen, _olen = struct.unpack_from(endian + "IIIII", body, 0)
            pkt = body[20 : 20 + caplen]
            link = linktypes[iface]
            if link == 1:  # Ethernet, maybe one VLAN tag
                ethertype = struct.unpack_from(">H", pkt, 12)[0]
                ip = pkt[14:]
                if ethertype == 0x8100:
                    ethertype = struct.unpack_from(">H", pkt, 16)[0]
                    ip = pkt[18:]
                seg = _ip_tcp(ip) if ethertype == 0x0800 else None
            elif link in (101, 228):  # raw IPv4
                seg = _ip_tcp(pkt)
            else:
                raise ValueError(f"unsupported link type {link}")
            if seg is not None and seg.payload:
                out.append(seg)
        pos += blen
    return out
