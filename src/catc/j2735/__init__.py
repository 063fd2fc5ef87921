"""SAE J2735 BasicSafetyMessage on the wire: UPER codec, IEEE 1609.2 and OBU log containers."""

from catc.j2735.uper import (
    BSM_MESSAGE_ID,
    decode_bsm,
    decode_frame,
    encode_bsm,
    encode_frame,
    frame_message_id,
)

__all__ = [
    "BSM_MESSAGE_ID",
    "decode_bsm",
    "decode_frame",
    "encode_bsm",
    "encode_frame",
    "frame_message_id",
]
