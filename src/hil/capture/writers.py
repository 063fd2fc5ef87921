"""Capture files of the daemons: append-only and flushed, so a killed process keeps all
but its last tick.

* :class:`JsonLines`: one JSON object per line (schedules, ground truth, ticks, warnings).
  Lines are written as they come and flushed by :meth:`JsonLines.flush`, which the daemons
  call once per tick.  :class:`GzipJsonLines` is the same in one gzip stream (the OBU's
  ``obu.rx.jsonl.gz``: ~30 octets a frame where the text takes ~250): each flush ends a
  deflate block with a sync flush, so everything flushed decompresses even when the
  process is killed before the stream's end (``zcat`` then says "unexpected end of file"
  after printing all of it).  The tracks are :class:`hil.capture.tracks.TrackWriter`.
* :class:`PcapngWriter`: the UDP frames as a pcapng file (IETF draft-ietf-opsawg-pcapng:
  one Section Header Block, two Interface Description Blocks, of link types RAW (101, an
  IPv4 or IPv6 header first) and ETHERNET (1), then one Enhanced Packet Block per frame
  with a microsecond timestamp), which Wireshark and tshark open.  Each datagram is
  wrapped in the IPv4/IPv6 and UDP headers it had on the wire, with the sending socket's
  port and the UDP checksum; WAVE Short Messages (``rve run --framing wsmp``) are written
  as they go over the air, in Ethernet II frames of ethertype 0x88DC (IEEE 1609.3),
  which Wireshark dissects down to the 1609.2 signer and signature.
* CAN frames go to two text logs at once (:func:`can_log`, one :class:`CanLogs`): python-can's
  ASC (Vector's format, which CANalyzer and python-can read) and the candump log format
  (``(1700000000.123456) vcan0 6A0#0214...``, ``##<flags>`` for CAN FD) that can-utils'
  ``canplayer``/``log2asc`` and most CAN tooling read.  Both are line based and therefore
  survive a kill; BLF compresses whole blocks and would lose the tail.

A write or flush that fails (a full disk, a file size limit) raises
:class:`hil.errors.WriteError`, which names the file; :func:`finish` then flushes and
closes every other file all the same, so that each keeps what was written before.
"""

from __future__ import annotations

import ipaddress
import json
import os
import struct
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

from hil.errors import write_error

__all__ = ["CanLogs", "CaptureFile", "GzipJsonLines", "JsonLines", "PcapngWriter", "can_log",
           "claim", "ethernet", "finish", "udp_packet", "versions"]

_DAEMONS = {"rve": "an RVE", "obu": "an OBU"}


def claim(directory: Path, daemon: str, overwrite: bool) -> None:
    """Make ``directory`` (which exists) the capture of a new run of ``daemon`` (``rve``
    or ``obu``).  Where it already holds that daemon's files (``rve.*``, ``obu.*``: an
    earlier run, whose JSON lines the new one would append to) it raises
    :class:`FileExistsError` with a one-line message, or with ``overwrite`` deletes them.
    The other daemon's files are left alone: the RVE and the OBU share the directory."""
    own = sorted(p for p in directory.glob(f"{daemon}.*") if p.is_file())
    if not own:
        return
    if not overwrite:
        raise FileExistsError(
            f"{directory} already holds {_DAEMONS[daemon]} run ({own[0].name}"
            f"{f' and {len(own) - 1} more' if len(own) > 1 else ''}): give a new directory, "
            "or --overwrite to replace that run")
    for path in own:
        path.unlink()


def versions() -> dict[str, str]:
    """What a capture's config records about the software that wrote it."""
    import sys
    from importlib import metadata

    try:
        own = metadata.version("catc-hil")
    except metadata.PackageNotFoundError:
        own = "unknown"
    return {"catc-hil": own, "python": sys.version.split()[0]}


class CaptureFile:
    """A capture file opened for writing (its directory made), flushed and closed."""

    def __init__(self, path: str | os.PathLike, mode: str) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        encoding = None if "b" in mode else "utf-8"
        self._f: IO[Any] = open(self.path, mode, encoding=encoding)  # noqa: SIM115

    def _put(self, data: Any) -> None:
        try:
            self._f.write(data)
        except OSError as err:
            raise write_error(err, self.path) from None

    def flush(self) -> None:
        """Hand everything written so far to the OS (a kill -9 no longer loses it)."""
        try:
            self._f.flush()
        except OSError as err:
            raise write_error(err, self.path) from None

    def tell(self) -> int:
        """Octets in the file so far (what a capped capture counts)."""
        return self._f.tell()

    def close(self) -> None:
        """Flush and close (closed even when the flush fails)."""
        if not self._f.closed:
            try:
                self._f.close()
            except OSError as err:
                raise write_error(err, self.path) from None


class JsonLines(CaptureFile):
    """Append-only JSON lines at ``path`` (created with its directory)."""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path, "a")
        self.lines = 0
        self._size = self.path.stat().st_size

    def write(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, separators=(",", ":"), allow_nan=True) + "\n"
        self._put(line)
        self._size += len(line)  # ASCII: json.dumps escapes everything else
        self.lines += 1

    def tell(self) -> int:
        return self._size


class GzipJsonLines(CaptureFile):
    """JSON lines in one gzip stream at ``path`` (module docstring), created anew."""

    LEVEL = 6  # 1 is 15 % larger on a storm's frames for half the CPU; both are cheap

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path, "wb")
        self._z = zlib.compressobj(self.LEVEL, zlib.DEFLATED, 31)  # 31: gzip header
        self.lines = 0

    def write(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, separators=(",", ":"), allow_nan=True) + "\n"
        self._put(self._z.compress(line.encode()))
        self.lines += 1

    def flush(self) -> None:
        self._put(self._z.flush(zlib.Z_SYNC_FLUSH))
        super().flush()

    def close(self) -> None:
        if not self._f.closed:
            try:
                self._put(self._z.flush(zlib.Z_FINISH))
            finally:
                super().close()


def _checksum16(data: bytes) -> int:
    if len(data) % 2:
        data += b"\x00"
    s = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while s >> 16:
        s = (s & 0xFFFF) + (s >> 16)
    return ~s & 0xFFFF


def udp_packet(src: tuple[str, int], dst: tuple[str, int], payload: bytes) -> bytes:
    """The IPv4 or IPv6 + UDP packet that carried ``payload`` (for the pcapng capture)."""
    s_ip, d_ip = ipaddress.ip_address(src[0]), ipaddress.ip_address(dst[0])
    length = 8 + len(payload)
    if d_ip.version == 4:
        if s_ip.version != 4:
            s_ip = ipaddress.ip_address("127.0.0.1")
        ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + length, 0, 0x4000, 64, 17, 0,
                         s_ip.packed, d_ip.packed)
        ip = ip[:10] + struct.pack("!H", _checksum16(ip)) + ip[12:]
        udp = struct.pack("!HHHH", src[1], dst[1], length, 0) + payload
        pseudo = s_ip.packed + d_ip.packed + struct.pack("!xBH", 17, length)
        csum = _checksum16(pseudo + udp) or 0xFFFF
        return ip + udp[:6] + struct.pack("!H", csum) + udp[8:]
    if s_ip.version != 6:
        s_ip = ipaddress.ip_address("::1")
    udp = struct.pack("!HHHH", src[1], dst[1], length, 0) + payload
    pseudo = s_ip.packed + d_ip.packed + struct.pack("!IxxxB", length, 17)
    csum = _checksum16(pseudo + udp) or 0xFFFF
    udp = udp[:6] + struct.pack("!H", csum) + udp[8:]
    return struct.pack("!IHBB16s16s", 6 << 28, length, 17, 64, s_ip.packed, d_ip.packed) + udp


def _block(block_type: int, body: bytes) -> bytes:
    body += b"\x00" * (-len(body) % 4)
    total = len(body) + 12
    return struct.pack("<II", block_type, total) + body + struct.pack("<I", total)


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + b"\x00" * (-len(value) % 4)


def ethernet(dst: bytes, src: bytes, ethertype: int, payload: bytes) -> bytes:
    """An Ethernet II frame (no FCS), e.g. a WSMP frame with ethertype 0x88DC."""
    return bytes(dst) + bytes(src) + struct.pack("!H", ethertype) + bytes(payload)


class PcapngWriter(CaptureFile):
    """Append-only pcapng: interface 0 carries raw IP packets (link type RAW), interface 1
    Ethernet frames (link type ETHERNET: WSMP on ethertype 0x88DC);
    ``write(packet, t_unix, interface=0)``, ``flush()``."""

    LINKTYPE_RAW = 101
    LINKTYPE_ETHERNET = 1
    RAW, ETHERNET = 0, 1

    def __init__(self, path: str | os.PathLike, comment: str = "catc-hil") -> None:
        super().__init__(path, "wb")
        shb = struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1) + _option(1, comment.encode()) \
            + _option(0, b"")
        self._put(_block(0x0A0D0D0A, shb))
        for linktype in (self.LINKTYPE_RAW, self.LINKTYPE_ETHERNET):
            idb = struct.pack("<HHI", linktype, 0, 65535) + _option(9, b"\x06") \
                + _option(0, b"")
            self._put(_block(0x00000001, idb))
        self.flush()
        self.packets = 0

    def write(self, packet: bytes, t_unix: float, interface: int = 0) -> None:
        us = round(t_unix * 1e6)
        body = struct.pack("<IIIII", interface, us >> 32, us & 0xFFFFFFFF, len(packet), len(packet))
        self._put(_block(0x00000006, body + packet + b"\x00" * (-len(packet) % 4)))
        self.packets += 1


class CanLogs:
    """Every CAN frame into several python-can writers (ASC, candump log).

    ``on_message_received(msg)`` per frame (a :class:`can.Listener`'s method, so it fits the
    CAN transport's ``on_frame``), ``flush()`` per tick, ``stop()`` at the end.
    """

    def __init__(self, writers: list[Any]) -> None:
        self.writers = writers
        self.frames = 0

    def on_message_received(self, msg: Any) -> None:
        for w in self.writers:
            w.on_message_received(msg)
        self.frames += 1

    def flush(self) -> None:
        for w in self.writers:
            try:
                w.file.flush()
            except OSError as err:
                raise write_error(err, w.file.name) from None

    def stop(self) -> None:
        """Flush and close every writer, even when one fails; then raise the first
        failure."""
        first: OSError | None = None
        for w in self.writers:
            try:
                w.stop()
            except OSError as err:
                first = first or write_error(err, w.file.name)
        if first is not None:
            raise first


def can_log(stem: str | os.PathLike, channel: str) -> CanLogs:
    """``STEM.asc`` and ``STEM.log`` (candump -L format, frames named on ``channel``)."""
    import can

    Path(stem).parent.mkdir(parents=True, exist_ok=True)
    return CanLogs([can.ASCWriter(f"{stem}.asc"),
                    can.CanutilsLogWriter(f"{stem}.log", channel=channel)])


def finish(files: Iterable[Any], failure: OSError | None = None) -> OSError | None:
    """Close every file of ``files`` (writers above, :class:`CanLogs`), each after its
    flush, even when one fails, so that the others keep everything written to them; the
    first failure (``failure``, when the run already had one), or None."""
    for f in files:
        try:
            f.stop() if isinstance(f, CanLogs) else f.close()
        except OSError as err:
            failure = failure or err
    return failure
