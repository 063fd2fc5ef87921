"""The receive fast path: a signed BSM in the layout every sender of this testbench (and
most deployed ones) uses, sliced at the offsets that layout fixes, without a stream.

:func:`fast_open` reads a frame as :func:`catc.j2735.open_envelope` does and returns the
same :class:`Unwrapped`, or None for anything it does not recognise, and then the
general parser (:func:`unwrap_wsmp`, :func:`unwrap`) reads the frame.  It never raises
and never decides that a frame is malformed: every error, and every form not below,
comes from the general parser, so errors and their reasons are the general parser's by
construction.  The layout it takes, octet for octet (COER, IEEE 1609.2-2016 §6.3; WSMP,
IEEE 1609.3-2016 §8.3), each alternative the one the general parser would take:

- optionally a WSM: N-header ``0x03`` (version 3, null networking, no extension), TPID
  ``0x00``, a one-octet p-encoded PSID (below 0x80), the WSM length in one or two
  octets (1609.3 §8.1.3), then exactly that many octets of ``Ieee1609Dot2Data``
  (octets after them are ignored, as :func:`unwrap_wsmp` does);
- ``03 81``: protocolVersion 3, ``signedData``; hashId ``00`` (sha256); the
  SignedDataPayload preamble ``40`` (``data`` only, no extension);
- ``03 80 L frame``: an unsecured ``Ieee1609Dot2Data`` (one signed layer), its length
  determinant in the short form or ``81``/``82`` and one or two length octets;
- headerInfo preamble ``40`` (generationTime only), the psid (a one-octet length of 1 to
  8, then the octets), the 8-octet generationTime;
- the signer: ``80`` and a HashedId8, or ``81 01 01`` and one certificate that was seen
  before (below);
- the signature: ``80 80`` (ecdsaNistP256Signature, rSig x-only), r, s; octets after a
  signed ``Ieee1609Dot2Data`` are ignored, as :func:`unwrap` does.

A certificate signer is taken as the octets between ``81 01 01`` and the 66 octets of
the signature, looked up among the certificates the general parser has read before
(:func:`remember`, by their octets: parsing is a function of the octets consumed, so
the same octets are the same :class:`Certificate`, and they consume exactly the octets
looked up).  The first message of each certificate therefore takes the general path; a
sender repeats its certificate once a second.  At most :data:`MAX_CERTIFICATES` are
kept, the oldest forgotten first.

What is saved (``bench/rx_path.py``): the :class:`io.BytesIO` and the one-octet reads of
the general parser, its certificate parse, and :func:`dataclasses.replace` for the WSM's
PSID.  The :class:`Unwrapped` is made without its generated ``__init__`` (15 fields set
one by one through ``object.__setattr__``, as a frozen dataclass does): its ``__dict__``
is filled at once, which gives the same object.
"""

from __future__ import annotations

from collections import OrderedDict

from catc.j2735.ieee1609._certificate import Certificate
from catc.j2735.ieee1609._data import Unwrapped

#: Certificates remembered by their octets (a few thousand RVs each repeat theirs).
MAX_CERTIFICATES = 4096
#: Octets of the shortest signed data in the layout: 03 81 00 40 03 80 00 (an empty
#: frame), 40 01 psid, generationTime, 80 and a HashedId8, 80 80 r s.
_SHORTEST = 7 + 3 + 8 + 9 + 66

_certs: OrderedDict[bytes, Certificate] = OrderedDict()
_new = object.__new__


def remember(cert: Certificate) -> None:
    """Keep ``cert`` (parsed by the general parser) for :func:`fast_open`."""
    raw = cert.raw
    if raw in _certs:
        return
    _certs[raw] = cert
    if len(_certs) > MAX_CERTIFICATES:
        _certs.popitem(last=False)


def forget() -> None:
    """Forget every certificate remembered (for tests)."""
    _certs.clear()


def fast_open(data: bytes) -> Unwrapped | None:
    """The :class:`Unwrapped` that :func:`catc.j2735.open_envelope` gives for ``data``
    when ``data`` is in the layout of the module docstring, else None."""
    if type(data) is not bytes:
        data = bytes(data)
    n = len(data)
    if n < _SHORTEST or data[0] != 0x03:
        return None
    head = data[1]
    if head == 0x81:  # Ieee1609Dot2Data signedData, no WSM around it
        p, wsmp_psid, size = data, None, n
    elif head == 0x00:  # WSM: TPID 0
        wsmp_psid = data[2]
        first = data[3]
        if wsmp_psid >= 0x80:
            return None
        if first < 0x80:
            size, start = first, 4
        elif first & 0xC0 == 0x80:
            size, start = (first & 0x3F) << 8 | data[4], 5
        else:
            return None
        if start + size > n or size < _SHORTEST or data[start] != 0x03 or data[start + 1] != 0x81:
            return None
        p = data[start:start + size]
    else:
        return None
    # p: 03 81 00 40 03 80 L frame ...; size >= _SHORTEST from here on
    if p[2] != 0x00 or p[3] != 0x40 or p[4] != 0x03 or p[5] != 0x80:
        return None
    length = p[6]
    if length < 0x80:
        fs = 7
    elif length == 0x81:
        length, fs = p[7], 8
    elif length == 0x82:
        length, fs = p[7] << 8 | p[8], 9
    else:
        return None
    h = fs + length  # headerInfo: 40, psid (2 octets at least), generationTime, then
    if h + 86 > size or p[h] != 0x40:  # a signer of 9 octets at least, a signature of 66
        return None
    psid_size = p[h + 1]
    if not 1 <= psid_size <= 8:
        return None
    g = h + 2 + psid_size
    s = g + 8  # the signer
    if s + 75 > size:
        return None
    kind = p[s]
    if kind == 0x80:
        if p[s + 9] != 0x80 or p[s + 10] != 0x80:
            return None
        signature = p[s + 11:s + 75]
        kind_name, digest, certs, unsupported = "digest", p[s + 1:s + 9], (), None
    elif kind == 0x81 and p[s + 1] == 0x01 and p[s + 2] == 0x01:
        cert = _certs.get(p[s + 3:size - 66])
        if cert is None or p[size - 66] != 0x80 or p[size - 65] != 0x80:
            return None
        signature = p[size - 64:]
        kind_name, digest, certs = "certificate", cert.hashed_id8, (cert,)
        unsupported = f"signer {cert.unsupported}" if cert.unsupported else None
    else:
        return None
    u = _new(Unwrapped)
    u.__dict__.update(
        frame=p[fs:h], security="signed", psid=int.from_bytes(p[h + 2:g], "big"),
        generation_time_us=int.from_bytes(p[g:s], "big"), hash_id="sha256",
        tbs_data=p[3:s], signer_kind=kind_name, signer_digest=digest, signer_certs=certs,
        signature=signature, signature_r_form="x-only", expiry_time_us=None,
        unsupported=unsupported, signed_layers=1, wsmp_psid=wsmp_psid)
    return u
