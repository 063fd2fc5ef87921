"""SAE J2735 BasicSafetyMessage on the wire: UPER codec, IEEE 1609.2 and OBU log containers."""

from catc.bsm import BSM
from catc.j2735.uper import (
    BSM_MESSAGE_ID,
    decode_bsm,
    decode_frame,
    encode_bsm,
    encode_frame,
    frame_message_id,
)


def decode_received(data: bytes) -> BSM:
    """A frame as an OBU receives it: an IEEE 1609.2 envelope is removed when there is one,
    then the UPER MessageFrame is decoded.  Raises :class:`catc.errors.DecodeError`."""
    from catc.j2735.ieee1609 import looks_like_1609, unwrap

    if looks_like_1609(data):
        data = unwrap(data).frame
    return decode_frame(data)


__all__ = [
    "BSM_MESSAGE_ID",
    "decode_bsm",
    "decode_frame",
    "decode_received",
    "encode_bsm",
    "encode_frame",
    "frame_message_id",
]
