"""SAE J2735 BasicSafetyMessage on the wire: UPER codec, IEEE 1609.2 and OBU log containers."""

import dataclasses

from catc.bsm import BSM
from catc.errors import DecodeError
from catc.j2735.ieee1609 import (
    PROTOCOL_VERSION,
    WSMP_VERSION,
    Unwrapped,
    fast_open,
    looks_like_1609,
    looks_like_wsmp,
    remember,
    unwrap,
    unwrap_wsmp,
)
from catc.j2735.uper import (
    BSM_MESSAGE_ID,
    decode_bsm,
    decode_frame,
    encode_bsm,
    encode_frame,
    frame_message_id,
)


def open_envelope(data: bytes) -> tuple[bytes, Unwrapped | None]:
    """(the MessageFrame, its IEEE 1609.2 envelope or None) of a frame as an OBU receives
    it: a WSMP WAVE Short Message (IEEE 1609.3) and an ``Ieee1609Dot2Data`` are removed
    when present, and the WSM's PSID is kept in the envelope (``wsmp_psid``) for the
    verifier.  Raises :class:`catc.errors.DecodeError`, ``unsupported`` for a WSMP
    version or a 1609.2 protocolVersion other than 3: a header of the right shape whose
    version says that nothing after it can be read (the version field of a WSMP
    N-header with TPID 0 or 1 after it; a version octet below 8 before a 1609.2 content
    tag, where a UPER MessageFrame would have a messageId of 64-66 plus a multiple of 128,
    none of them a J2735 message).

    A signed BSM in the usual layout is sliced by :func:`catc.j2735.ieee1609.fast_open`
    (the same result); anything else goes through the general parsers, which also
    remember each certificate signer for the fast path."""
    fast = fast_open(data)
    if fast is not None:
        return fast.frame, fast
    return open_envelope_general(data)


def open_envelope_general(data: bytes) -> tuple[bytes, Unwrapped | None]:
    """:func:`open_envelope` by the general parsers alone, without the fast path (what
    the tests hold the fast path to).  A certificate signer it reads is remembered for
    :func:`catc.j2735.ieee1609.fast_open`."""
    wsmp_psid = None
    if looks_like_wsmp(data):
        data, wsmp_psid = unwrap_wsmp(data)
    elif len(data) >= 4 and data[0] < 8 and data[1] in (0, 1):
        raise DecodeError("unsupported", f"WSMP version {data[0]}, not {WSMP_VERSION}")
    if looks_like_1609(data):
        u = unwrap(data)
        if u.signer_kind == "certificate":
            remember(u.signer_certs[0])
        if wsmp_psid is not None:
            u = dataclasses.replace(u, wsmp_psid=wsmp_psid)
        return u.frame, u
    if len(data) >= 2 and data[0] < 8 and 0x80 <= data[1] <= 0x84:
        raise DecodeError("unsupported",
                          f"1609.2 protocolVersion {data[0]}, not {PROTOCOL_VERSION}")
    return data, None


def decode_received(data: bytes) -> BSM:
    """A frame as an OBU receives it: WSMP and IEEE 1609.2 envelopes are removed when
    there are any, then the UPER MessageFrame is decoded.  Raises
    :class:`catc.errors.DecodeError`."""
    return decode_frame(open_envelope(data)[0])


__all__ = [
    "BSM_MESSAGE_ID",
    "decode_bsm",
    "decode_frame",
    "decode_received",
    "encode_bsm",
    "encode_frame",
    "frame_message_id",
    "open_envelope",
    "open_envelope_general",
]
