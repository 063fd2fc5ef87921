"""The one exception type for bad input to the codecs.

Every decoder in :mod:`catc` (UPER, IEEE 1609.2, OBU log records) raises
:class:`DecodeError` for input it cannot accept, and nothing else.  Callers that
must never crash on network input (the OBU daemon) catch exactly this type,
count it by :attr:`DecodeError.reason`, and drop the frame.
"""

from __future__ import annotations

#: The reasons a decoder may give.  Daemons count drops per reason.
REASONS = (
    "truncated",  # the input ends before the structure does
    "garbage",  # the bytes do not form the structure at all
    "wrong-message-id",  # a valid MessageFrame that is not a BSM (messageId != 20)
    "out-of-range",  # a field holds a value its constraint forbids
    "unsupported",  # well-formed, but a form this codec does not handle
)


class DecodeError(ValueError):
    """Input that cannot be decoded.

    ``reason`` is one of :data:`REASONS`; ``str(err)`` is a one-line message
    naming the field or layer and what was wrong.
    """

    def __init__(self, reason: str, message: str) -> None:
        if reason not in REASONS:
            raise AssertionError(f"unknown DecodeError reason {reason!r}")
        super().__init__(f"{reason}: {message}")
        self.reason = reason


class EncodeError(ValueError):
    """A value that cannot be put on the wire (wrong type, or a raw integer outside
    its J2735 constraint).  SI values are saturated instead, as J2735 prescribes."""
