"""UPER (X.691 unaligned PER) codec for the J2735 MessageFrame carrying a BasicSafetyMessage.

The ASN.1 it implements is ``catc/j2735/bsm.asn``.  One module per part of the message:

- ``_frame``: ``MessageFrame`` and ``BasicSafetyMessage`` (the functions exported here);
- ``_core``: ``BSMcoreData``, a fixed 290-bit block read and written with one big-integer
  operation and fixed shifts, which is what makes the codec fast in pure Python;
- ``_vse``: Part II ``VehicleSafetyExtensions``, walked field by field;
- ``_part2``: the walkers that check SpecialVehicleExtensions and
  SupplementalVehicleExtensions, and the open type every Part II value is read from;
- ``_elements``: data elements the parts share (PositionalAccuracy, DDateTime, ...).

Decoding is total: for any input it returns a :class:`~catc.bsm.BSM` or raises
:class:`~catc.errors.DecodeError`.  What is decoded:

* BSMcoreData in full;
* Part II VehicleSafetyExtensions (id 0): events, pathHistory (with initialPosition
  and currGNSSstatus), pathPrediction and lights;
* Part II SpecialVehicleExtensions (id 1) and SupplementalVehicleExtensions (id 2)
  are checked against their J2735 2020 ASN.1 and kept as their octets; other Part II
  ids and regional extensions are kept as opaque octets.  So a frame carrying them
  re-encodes unchanged, with its Part II items in the order received;
* every Part II value must fill its open type: octets left over after the value
  (beyond the at most 7 bits of padding) are rejected as garbage, and so is a value
  that runs past its octets;
* extension additions (the ``...`` of an extensible SEQUENCE) are skipped, and a
  frame that has them does not re-encode bit-exactly.

OPTIONAL fields that are present but hold their "unavailable" code decode to
``None`` just like absent ones, and ``None`` encodes as absent.
"""

from catc.j2735.uper._frame import (
    BSM_MESSAGE_ID,
    decode_bsm,
    decode_frame,
    encode_bsm,
    encode_frame,
    frame_message_id,
)
from catc.j2735.uper._vse import VEHICLE_SAFETY_EXT

__all__ = [
    "BSM_MESSAGE_ID",
    "VEHICLE_SAFETY_EXT",
    "decode_bsm",
    "decode_frame",
    "encode_bsm",
    "encode_frame",
    "frame_message_id",
]
