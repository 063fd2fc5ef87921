"""SAE J2735 BasicSafetyMessage on the wire: UPER codec, IEEE 1609.2 and OBU log containers."""

from catc.bsm import BSM
from catc.j2735.ieee1609 import (
    Unwrapped,
    looks_like_1609,
    looks_like_wsmp,
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
    when present.  Raises :class:`catc.errors.DecodeError`."""
    if looks_like_wsmp(data):
        data, _psid = unwrap_wsmp(data)
    if looks_like_1609(data):
        u = unwrap(data)
        return u.frame, u
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
]
