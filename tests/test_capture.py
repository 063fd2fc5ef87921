"""Capture writers: pcapng read back block by block (an independent parser written from the
pcapng specification), JSON lines append-only and flushed, the ASC CAN log readable by
python-can."""

from __future__ import annotations

import json
import struct

import can
import pytest

from hil.capture import JsonLines, PcapngWriter, can_log, ethernet, udp_packet


def read_pcapng(data: bytes) -> tuple[list[int], list[tuple[float, bytes]]]:
    """([link type per interface], [(timestamp, packet)]) from a little-endian pcapng with
    µs timestamps; each packet is checked to name an interface that exists."""
    pos, linktype, packets = 0, [], []
    while pos < len(data):
        btype, total = struct.unpack_from("<II", data, pos)
        assert total % 4 == 0 and total >= 12
        assert struct.unpack_from("<I", data, pos + total - 4)[0] == total
        body = data[pos + 8: pos + total - 4]
        if btype == 0x0A0D0D0A:
            assert struct.unpack_from("<IHH", body)[0:3] == (0x1A2B3C4D, 1, 0)
        elif btype == 1:
            linktype.append(struct.unpack_from("<H", body)[0])
        elif btype == 6:
            iface, hi, lo, cap, orig = struct.unpack_from("<IIIII", body)
            assert cap == orig and iface < len(linktype)
            packets.append((((hi << 32) | lo) / 1e6, body[20:20 + cap]))
        pos += total
    assert pos == len(data)
    return linktype, packets


def test_pcapng_holds_every_udp_datagram_with_its_headers(tmp_path):
    w = PcapngWriter(tmp_path / "f.pcapng")
    payloads = [bytes(range(n % 256)) * (1 + n // 256) for n in (1, 40, 177, 300)]
    for i, p in enumerate(payloads):
        w.write(udp_packet(("127.0.0.1", 40000), ("127.0.0.1", 4500), p), 1.7e9 + i * 0.1)
    w.write(udp_packet(("::1", 40000), ("::1", 4501), b"six"), 1.7e9 + 1.0)
    w.write(ethernet(b"\xff" * 6, b"\x02" * 6, 0x88DC, b"\x03\x00\x20\x01x"), 1.7e9 + 2.0,
            w.ETHERNET)
    w.close()
    linktype, pkts = read_pcapng((tmp_path / "f.pcapng").read_bytes())
    assert linktype == [101, 1] and len(pkts) == 6
    for (t, pkt), p, i in zip(pkts, payloads, range(4), strict=False):
        assert t == pytest.approx(1.7e9 + i * 0.1, abs=1e-6)
        assert pkt[0] >> 4 == 4 and pkt[9] == 17  # IPv4, UDP
        sport, dport, length, _ = struct.unpack_from("!HHHH", pkt, 20)
        assert (sport, dport, length) == (40000, 4500, 8 + len(p))
        assert pkt[28:] == p
        # the IPv4 header checksum verifies, and so does the UDP checksum (RFC 768: over
        # the pseudo-header, the UDP header and the data, padded to an even length)
        def folded(octets: bytes) -> int:
            octets += b"\x00" * (len(octets) % 2)
            s = sum(struct.unpack(f"!{len(octets) // 2}H", octets))
            while s >> 16:
                s = (s & 0xFFFF) + (s >> 16)
            return s
        assert folded(pkt[:20]) == 0xFFFF
        pseudo = pkt[12:20] + struct.pack("!xBH", 17, length)
        assert pkt[26:28] != b"\x00\x00" and folded(pseudo + pkt[20:]) == 0xFFFF
    v6 = pkts[4][1]
    assert v6[0] >> 4 == 6 and v6[6] == 17 and v6[48:] == b"six"
    assert pkts[5][1] == b"\xff" * 6 + b"\x02" * 6 + b"\x88\xdc\x03\x00\x20\x01x"


def test_pcapng_is_readable_up_to_the_last_flush_while_open(tmp_path):
    w = PcapngWriter(tmp_path / "f.pcapng")
    w.write(udp_packet(("127.0.0.1", 1), ("127.0.0.1", 2), b"x" * 10), 1.0)
    w.flush()
    _, pkts = read_pcapng((tmp_path / "f.pcapng").read_bytes())
    assert len(pkts) == 1
    w.close()


def test_json_lines_append_and_flush(tmp_path):
    path = tmp_path / "cap" / "x.jsonl"
    w = JsonLines(path)
    w.write({"a": 1})
    w.flush()
    assert path.read_text() == '{"a":1}\n'
    w.write({"b": float("nan")})
    w.close()
    w2 = JsonLines(path)  # append, never truncate
    w2.write({"c": 3})
    w2.close()
    lines = path.read_text().splitlines()
    assert [list(json.loads(line)) for line in lines] == [["a"], ["b"], ["c"]]


def test_can_logs_round_trip_through_python_can_in_both_formats(tmp_path):
    log = can_log(tmp_path / "frames", channel="vcan0")
    msgs = [can.Message(timestamp=10.0 + i, arbitration_id=0x6A0, data=bytes([i] * 8),
                        is_extended_id=False) for i in range(3)]
    msgs.append(can.Message(timestamp=14.0, arbitration_id=0x6A1, data=bytes(range(64)),
                            is_fd=True, bitrate_switch=True, is_extended_id=False))
    for m in msgs:
        log.on_message_received(m)
    log.flush()  # flushed per tick: readable while the writer is still open
    lines = (tmp_path / "frames.log").read_text().splitlines()
    assert lines[0] == "(10.000000) vcan0 6A0#0000000000000000 R"  # R/T: received/sent
    assert lines[3].startswith("(14.000000) vcan0 6A1##1000102")  # FD with BRS (flags 1)
    log.stop()
    want = [(m.arbitration_id, bytes(m.data), m.is_fd) for m in msgs]
    for back in (list(can.ASCReader(str(tmp_path / "frames.asc"))),
                 list(can.CanutilsLogReader(str(tmp_path / "frames.log")))):
        assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in back] == want
