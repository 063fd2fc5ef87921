"""Find the J2735 frames in a capture file of unknown format (for ``captures decode FILE``).

A pcapng capture (the RVE's ``rve.frames.pcapng``, or any capture of UDP on link types
RAW, IPv4, IPv6 or Ethernet, or of WSMP on Ethernet, ethertype 0x88DC) gives the payload
of every UDP datagram or WAVE Short Message, each unpacked like binary input below; its
``meta`` has the packet number, timestamp and UDP ports (0 for WSMP).  Binary input that
is a WSMP message (IEEE 1609.3) is unwrapped to its payload first.

Other binary input is, in this order of trial: an IEEE 1609.2 ``Ieee1609Dot2Data``
(:mod:`catc.j2735.ieee1609`), an OBU log (:mod:`catc.j2735.obulog`), else raw UPER (a
MessageFrame, or a bare BasicSafetyMessage such as the ODE's ``bsm.uper``) which the
UPER decoder judges later; its first octet must be below 0x80 (a MessageFrame's
messageId starts with zero bits, a bare BSM with a clear extension bit).

Text input is one of:

- hex: one frame per line, or one blob spread over several lines.  Each blob is
  unpacked like binary input, so hex of a 1609.2 record or of an OBU log record
  works too (the ODE's ``BsmReceiverTest_ValidBSM.txt`` is a whole bsmTx log record:
  26-octet header, then 1609.2, then the frame);
- ODE JSON (one object, an array, or JSON lines): the hex in ``payload.data.bytes``,
  else in ``metadata.asn1``.  Records with decoded values only give no frames.  The
  OBU's own ``obu.rx.jsonl.gz`` (records with ``rx_unix``; ``captures decode`` unzips it)
  gives the frame in ``hex``;
- ODE XML (``OdeAsn1Data``): the hex in ``<bytes>`` elements, else in ``<asn1>``.

Each frame comes back as an :class:`Extracted` whose ``container`` names the file's
outer format and whose ``meta`` holds ``index`` (frame number in the file),
``layers`` (outermost first), the position in the file (``line`` or ``record``) and
whatever the containers said (OBU log header fields, 1609.2 security and psid).

Torn tails: a capture its writer was killed in (or whose disk filled) may end inside a
pcapng block or a JSON line.  Given a ``torn`` list, :func:`extract_frames` returns the
frames before it and appends ``(byte offset, why)`` of where the whole part ends;
without one, a pcapng cut off raises ``DecodeError("truncated")`` and a torn JSON line
``DecodeError("garbage")``, as before.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field
from typing import Any

from catc.errors import DecodeError
from catc.j2735 import ieee1609, obulog

ACCEPTED = (
    "expected raw UPER, hex text, IEEE 1609.2 COER, an OBU .bin log, a pcapng capture, "
    "or ODE JSON/XML records carrying hex"
)
_HEX = re.compile(r"[0-9A-Fa-f\s]+")
_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f]")
_ODE_JSON_KEYS = {"metadata", "payload", "coreData"}
_ODE_XML = re.compile(r"<(OdeAsn1Data|MessageFrame|BasicSafetyMessage)\b")
_XML_HEX = {tag: re.compile(rf"<{tag}>([^<]*)</{tag}>") for tag in ("bytes", "asn1")}


@dataclass(frozen=True)
class Extracted:
    """One frame found in a file, with the container it came in."""

    frame: bytes
    container: str  # "uper" | "hex" | "ieee1609" | "obulog" | "ode-json" | "ode-xml" | "pcapng"
    meta: dict[str, Any] = field(default_factory=dict)


def _security(u: ieee1609.Unwrapped) -> dict[str, Any]:
    return {"security": u.security, "psid": u.psid, "generation_time_us": u.generation_time_us}


def _unpack(blob: bytes) -> list[tuple[bytes, dict[str, Any]]]:
    """The frames in one binary blob, each with what its containers said."""
    if ieee1609.looks_like_wsmp(blob):
        try:
            inner, psid = ieee1609.unwrap_wsmp(blob)
        except DecodeError:
            pass  # try the other readings
        else:
            return [(frame, {**meta, "layers": ["wsmp", *meta["layers"]], "wsmp_psid": psid})
                    for frame, meta in _unpack(inner)]
    if ieee1609.looks_like_1609(blob):
        try:
            u = ieee1609.unwrap(blob)
        except DecodeError:
            pass  # a bare BSM may start 03 8x as well; try the other readings
        else:
            return [(u.frame, {"layers": ["ieee1609"], **_security(u)})]
    if obulog.looks_like_obulog(blob):
        frames = []
        for i, rec in enumerate(obulog.iter_records(blob)):
            meta = {k: v for k, v in asdict(rec).items() if k not in ("payload", "frame")}
            meta.update(layers=["obulog"], record=i)
            if ieee1609.looks_like_1609(rec.payload):
                meta.update(
                    layers=["obulog", "ieee1609"], **_security(ieee1609.unwrap(rec.payload))
                )
            frames.append((rec.frame, meta))
        return frames
    if blob and blob[0] < 0x80:
        return [(blob, {"layers": ["uper"]})]
    raise DecodeError("garbage", f"unrecognised binary input; {ACCEPTED}")


def unpack_payload(blob: bytes, carrier: str) -> list[tuple[bytes, dict[str, Any]]]:
    """The frames in one transport payload (a UDP datagram, an ISO-TP transfer) that
    ``carrier`` delivered; a payload of no known kind comes back whole, for the frame
    decoder to name what is wrong with it."""
    try:
        return _unpack(blob)
    except DecodeError:
        return [(blob, {"layers": [carrier]})]


def _hex(text: str, where: str) -> bytes:
    digits = "".join(text.split())
    if not digits or not _HEX.fullmatch(digits) or len(digits) % 2:
        raise DecodeError("garbage", f"{where}: not an even number of hex digits")
    return bytes.fromhex(digits)


def _starts_frame(blob: bytes) -> bool:
    return blob[:1] == b"\x00" or ieee1609.looks_like_1609(blob) or obulog.looks_like_obulog(blob)


def _from_hex(text: str) -> list[tuple[bytes, dict[str, Any]]]:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if len(lines) > 1 and all(len("".join(line.split())) % 2 == 0 for line in lines):
        blobs = [_hex(line, f"hex line {n}") for n, line in enumerate(lines)]
        if all(_starts_frame(b) for b in blobs):
            return [(f, {**m, "line": n}) for n, b in enumerate(blobs) for f, m in _unpack(b)]
    return _unpack(_hex(text, "hex text"))


def _json_records(text: str, torn: _Torn | None = None) -> list[Any]:
    """One JSON document (a list: its items), else JSON lines.  With ``torn``
    (``[offset of the text in the file, whether the file ends inside a line]``), a last
    line cut off after whole ones ends the records, its offset appended to the list."""
    try:
        doc = json.loads(text)
        return doc if isinstance(doc, list) else [doc]
    except (ValueError, RecursionError):
        pass
    out: list[Any] = []
    lines = text.splitlines(keepends=True)
    off = torn.base if torn is not None else 0
    for n, line in enumerate(lines):
        if line.strip():
            try:
                out.append(json.loads(line))
            except (ValueError, RecursionError):
                if torn is not None and torn.open_end and out and n == len(lines) - 1:
                    torn.cuts.append((off, "last JSON line cut off"))
                    break
                raise DecodeError("garbage",
                                  f"text is not valid JSON or JSON lines; {ACCEPTED}") from None
        off += len(line.encode())
    return out


def _get(obj: Any, *keys: str) -> Any:
    for key in keys:
        obj = obj.get(key) if isinstance(obj, dict) else None
    return obj


def _from_json(text: str, torn: _Torn | None = None) -> list[tuple[bytes, dict[str, Any]]]:
    frames = []
    for n, rec in enumerate(_json_records(text, torn)):
        if isinstance(rec, dict) and "rx_unix" in rec:  # the OBU's own obu.rx.jsonl
            if isinstance(rec.get("hex"), str) and rec["hex"]:
                for f, m in _unpack(_hex(rec["hex"], f"JSON record {n} hex")):
                    frames.append((f, {**m, "line": n, "field": "hex",
                                       "rx_unix": rec["rx_unix"],
                                       "channel": rec.get("channel")}))
            continue
        if not isinstance(rec, dict) or not _ODE_JSON_KEYS & rec.keys():
            raise DecodeError("garbage", f"JSON record {n} is not an ODE record; {ACCEPTED}")
        for path in (("payload", "data", "bytes"), ("metadata", "asn1")):
            value = _get(rec, *path)
            if isinstance(value, str) and value.strip():
                where = f"JSON record {n} {'.'.join(path)}"
                for f, m in _unpack(_hex(value, where)):
                    frames.append((f, {**m, "line": n, "field": ".".join(path)}))
                break
    return frames


def _from_xml(text: str) -> list[tuple[bytes, dict[str, Any]]]:
    if not _ODE_XML.search(text):
        raise DecodeError("garbage", f"XML is not an ODE record; {ACCEPTED}")
    for tag, pattern in _XML_HEX.items():
        found = pattern.findall(text)
        if found:
            return [
                (f, {**m, "element": tag})
                for value in found
                for f, m in _unpack(_hex(value, f"XML <{tag}>"))
            ]
    return []


def as_text(data: bytes) -> str | None:
    """``data`` as UTF-8 text, or None for binary content (undecodable or control octets)."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    return None if _CONTROL.search(text) else text


_PCAPNG_SHB = 0x0A0D0D0A


def _udp_payload(packet: bytes, linktype: int) -> tuple[bytes, int, int] | None:
    """(payload, source port, destination port) of a UDP packet, or None."""
    if linktype == 1:  # Ethernet II, possibly with one 802.1Q tag
        if len(packet) < 14:
            return None
        ethertype, off = int.from_bytes(packet[12:14], "big"), 14
        if ethertype == 0x8100 and len(packet) >= 18:
            ethertype, off = int.from_bytes(packet[16:18], "big"), 18
        if ethertype == ieee1609.ETHERTYPE_WSMP:  # WAVE Short Message over the air
            return packet[off:], 0, 0
        if ethertype not in (0x0800, 0x86DD):
            return None
        packet = packet[off:]
    elif linktype not in (101, 228, 229):
        return None
    if not packet:
        return None
    version = packet[0] >> 4
    if version == 4 and len(packet) >= 20 and packet[9] == 17:
        udp = packet[(packet[0] & 0x0F) * 4:]
    elif version == 6 and len(packet) >= 40 and packet[6] == 17:
        udp = packet[40:]
    else:
        return None
    if len(udp) < 8:
        return None
    length = int.from_bytes(udp[4:6], "big")
    return (udp[8:length] if 8 <= length <= len(udp) else udp[8:],
            int.from_bytes(udp[0:2], "big"), int.from_bytes(udp[2:4], "big"))


def _from_pcapng(data: bytes, torn: _Torn | None = None) -> list[tuple[bytes, dict[str, Any]]]:
    """Every UDP payload of a pcapng file (module docstring); a last block cut off ends it
    (``torn``, else DecodeError)."""
    out: list[tuple[bytes, dict[str, Any]]] = []
    pos, order, linktypes, tsres, n = 0, "<", [], [], 0
    while pos < len(data):
        if pos + 12 > len(data):
            if torn is None:
                raise DecodeError("truncated", f"pcapng block at octet {pos} is cut off")
            torn.cuts.append((pos, "pcapng block header cut off"))
            break
        if int.from_bytes(data[pos:pos + 4], "little") == _PCAPNG_SHB:
            magic = data[pos + 8:pos + 12]
            order = "little" if magic == b"\x4d\x3c\x2b\x1a" else "big"
            linktypes, tsres = [], []
        btype = int.from_bytes(data[pos:pos + 4], order)
        total = int.from_bytes(data[pos + 4:pos + 8], order)
        if total < 12 or total % 4:
            raise DecodeError("garbage", f"pcapng block at octet {pos} has length {total}")
        if pos + total > len(data):
            if torn is None:
                raise DecodeError("truncated", f"pcapng block at octet {pos} is cut off")
            torn.cuts.append((pos, "pcapng block cut off"))
            break
        body = data[pos + 8:pos + total - 4]
        if btype == 1 and len(body) >= 8:
            linktypes.append(int.from_bytes(body[0:2], order))
            res = 6
            opt = 8
            while opt + 4 <= len(body):  # if_tsresol (option 9)
                code = int.from_bytes(body[opt:opt + 2], order)
                size = int.from_bytes(body[opt + 2:opt + 4], order)
                if code == 9 and size >= 1:
                    res = body[opt + 4] & 0x7F
                if code == 0:
                    break
                opt += 4 + size + (-size % 4)
            tsres.append(res)
        elif btype == 6 and len(body) >= 20:
            iface = int.from_bytes(body[0:4], order)
            ts = (int.from_bytes(body[4:8], order) << 32) | int.from_bytes(body[8:12], order)
            cap = int.from_bytes(body[12:16], order)
            if iface < len(linktypes):
                udp = _udp_payload(body[20:20 + cap], linktypes[iface])
                if udp is not None:
                    t = ts / 10.0 ** tsres[iface]
                    for frame, meta in unpack_payload(udp[0], "udp"):
                        out.append((frame, {**meta, "packet": n, "time": t,
                                            "udp_src": udp[1], "udp_dst": udp[2]}))
            n += 1
        pos += total
    return out


@dataclass
class _Torn:
    """Where a file is read from (``base``: the text's first octet in it), whether it ends
    inside a line, and the cuts found: ``(byte offset, why)``."""

    cuts: list[tuple[int, str]]
    base: int = 0
    open_end: bool = True


def extract_frames(data: bytes, torn: list[tuple[int, str]] | None = None
                   ) -> list[Extracted]:
    """The frames in a capture file's content, detecting its format (see module doc).
    With ``torn`` a list, a torn tail ends the frames and ``(byte offset, why)`` of where
    the whole part ends is appended to it."""
    cut = None if torn is None else _Torn(torn)
    if len(data) >= 12 and int.from_bytes(data[:4], "little") == _PCAPNG_SHB:
        found = _from_pcapng(bytes(data), cut)
        return [Extracted(frame, "pcapng", {**meta, "layers": ["pcapng", *meta["layers"]],
                                            "index": i})
                for i, (frame, meta) in enumerate(found)]
    text = as_text(data)
    if text is None:
        found, container = _unpack(bytes(data)), None
    else:
        if cut is not None:
            cut.base = len(data) - len(data.lstrip(b"\xef\xbb\xbf \t\r\n"))
            cut.open_end = not data.endswith((b"\n", b"\r"))
        text = text.strip()
        if text[:1] in ("{", "["):
            found, container = _from_json(text, cut), "ode-json"
        elif text[:1] == "<":
            found, container = _from_xml(text), "ode-xml"
        elif text and _HEX.fullmatch(text):
            found, container = _from_hex(text), "hex"
        else:
            raise DecodeError("garbage", f"unrecognised text input; {ACCEPTED}")
    extracted = []
    for i, (frame, meta) in enumerate(found):
        layers = [container, *meta["layers"]] if container else meta["layers"]
        extracted.append(Extracted(frame, layers[0], {**meta, "layers": layers, "index": i}))
    return extracted
