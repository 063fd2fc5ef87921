"""The host vehicle's own CAN bus, decoded through a DBC and a vehicle profile (no I/O).

A real OBU knows its own car from the car's CAN bus (the reference paper's WSU: "an API
to enable applications to interface to the CAN bus, GPS receiver, and wireless").  What
it reads is named by a *vehicle profile* (:class:`VehicleProfile`): which message and
signals of the car's DBC feed which host-state field, with the unit conversion and the
sign convention (J2735: yaw rate positive clockwise, speeds in m/s), and the frame
checksum rule, and how often the car sends each message (``rates_hz``, which
:mod:`catc.vehicle.encode` follows when it makes a host's bus).  Adding a car is adding a
profile (a JSON file and a DBC), not code.

:class:`CanDecoder` decodes frames with a :mod:`cantools` database (the profile's own
DBC, or any full DBC a user points at): each frame is checked (known id, length, the
checksum of every message with a ``CHECKSUM`` signal) and what fails is counted by
reason and dropped, never raised.  The host-state fields it yields are the latest value
of each, with the frame time it came from.

Checksum rules (:data:`CHECKSUMS`): ``toyota``, the sum of the id's two bytes, the
length and every data byte but the last, modulo 256, in the last byte (opendbc's
``toyota_checksum``; it passes on all 51,056 checksummed frames of buses 0 and 1 of the
comma2k19 RAV4 minute, tests/test_vehicle.py).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["CHECKSUMS", "DEFAULT_RATE_HZ", "CanDecoder", "FieldRule", "VehicleProfile",
           "toyota_checksum"]


def toyota_checksum(address: int, data: bytes) -> int:
    """Toyota's frame checksum: (id high byte + id low byte + length + data[:-1]) mod 256."""
    return ((address >> 8) + (address & 0xFF) + len(data) + sum(data[:-1])) & 0xFF


#: Checksum rule name -> ``rule(address, data) -> the expected last byte``.
CHECKSUMS: dict[str, Callable[[int, bytes], int]] = {"toyota": toyota_checksum}

#: How often a message is sent when the profile does not say (Hz).
DEFAULT_RATE_HZ = 10.0

#: How a field combines the values of its signals.
_COMBINE = {"first": lambda v: v[0], "mean": lambda v: sum(v) / len(v), "sum": sum}


@dataclass(frozen=True)
class FieldRule:
    """One host-state field: ``scale * combine(signals of message) + offset``.  A signal
    whose value is a named choice (a DBC ``VAL_``) gives that name, and the field is the
    name (``combine`` ``first``, no scale)."""

    message: str
    signals: tuple[str, ...]
    combine: str = "first"
    scale: float = 1.0
    offset: float = 0.0
    unit: str = ""
    why: str = ""

    def __post_init__(self) -> None:
        if not self.signals:
            raise ValueError(f"field from {self.message}: no signals")
        if self.combine not in _COMBINE:
            raise ValueError(f"field from {self.message}: combine {self.combine!r} is not "
                             f"one of {', '.join(_COMBINE)}")
        if not (math.isfinite(self.scale) and math.isfinite(self.offset)):
            raise ValueError(f"field from {self.message}: scale and offset must be finite")


@dataclass(frozen=True)
class VehicleProfile:
    """A car: its name, its checksum rule, the fields read from its CAN bus, and how
    often the car sends each message (``rates_hz``, message name -> Hz; a message not
    named there is sent at :data:`DEFAULT_RATE_HZ`)."""

    name: str
    checksum: str
    fields: Mapping[str, FieldRule]
    description: str = ""
    rates_hz: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.checksum not in CHECKSUMS:
            raise ValueError(f"profile {self.name!r}: checksum {self.checksum!r} is not one "
                             f"of {', '.join(CHECKSUMS)}")
        for message, hz in self.rates_hz.items():
            if not (isinstance(hz, (int, float)) and math.isfinite(hz) and hz > 0):
                raise ValueError(f"profile {self.name!r}: rate of {message} must be a "
                                 f"number of Hz above 0, got {hz!r}")

    def rate_hz(self, message: str) -> float:
        """How often the car sends ``message`` (Hz)."""
        return float(self.rates_hz.get(message, DEFAULT_RATE_HZ))

    def messages(self) -> list[str]:
        """The messages the profile reads, in the order its fields name them."""
        return list(dict.fromkeys(rule.message for rule in self.fields.values()))

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> VehicleProfile:
        """From a profile's JSON document (ValueError, one line, for a bad one)."""
        try:
            fields = {name: FieldRule(message=f["message"], signals=tuple(f["signals"]),
                                      combine=f.get("combine", "first"),
                                      scale=float(f.get("scale", 1.0)),
                                      offset=float(f.get("offset", 0.0)),
                                      unit=f.get("unit", ""), why=f.get("why", ""))
                      for name, f in doc["fields"].items()}
            rates = doc.get("rates_hz", {})
            if not isinstance(rates, Mapping):
                raise TypeError("rates_hz: not a mapping")
            return cls(name=doc["name"], checksum=doc.get("checksum", "toyota"),
                       fields=fields, description=doc.get("description", ""),
                       rates_hz=dict(rates))
        except (KeyError, TypeError, AttributeError) as err:
            raise ValueError(f"vehicle profile: missing or malformed {err}") from None

    def check(self, db: Any) -> None:
        """ValueError (one line) unless every message and signal the profile names is in
        the cantools database ``db``."""
        for name, rule in self.fields.items():
            try:
                msg = db.get_message_by_name(rule.message)
            except KeyError:
                raise ValueError(f"profile {self.name!r}: field {name!r}: no message "
                                 f"{rule.message!r} in the DBC") from None
            have = {s.name for s in msg.signals}
            for s in rule.signals:
                if s not in have:
                    raise ValueError(f"profile {self.name!r}: field {name!r}: message "
                                     f"{rule.message} has no signal {s!r}")
        for message in self.rates_hz:
            try:
                db.get_message_by_name(message)
            except KeyError:
                raise ValueError(f"profile {self.name!r}: rates_hz: no message "
                                 f"{message!r} in the DBC") from None


@dataclass
class CanDecoder:
    """Decodes frames of the car's bus through ``db`` (a :mod:`cantools` database) for
    ``profile``: :meth:`take` one frame; :attr:`state` the latest value of each field,
    :attr:`stamps` its frame time; :attr:`counters` what was read and dropped
    (``can_frames``, ``can_unknown_id``, ``can_bad_length``, ``can_bad_checksum``,
    ``can_undecodable``, and ``can_<message>`` per decoded profile message)."""

    profile: VehicleProfile
    db: Any
    counters: Counter = field(default_factory=Counter)
    state: dict[str, Any] = field(default_factory=dict)
    stamps: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.profile.check(self.db)
        self._rule = CHECKSUMS[self.profile.checksum]
        self._by_id: dict[int, tuple[Any, list[tuple[str, FieldRule]]]] = {}
        for name, rule in self.profile.fields.items():
            msg = self.db.get_message_by_name(rule.message)
            self._by_id.setdefault(msg.frame_id, (msg, []))[1].append((name, rule))
        #: frame id -> whether its last byte is a CHECKSUM signal (every DBC message)
        self._checked: dict[int, bool] = {}

    def _checksummed(self, msg: Any) -> bool:
        c = self._checked.get(msg.frame_id)
        if c is None:
            c = self._checked[msg.frame_id] = any(
                s.name == "CHECKSUM" and s.length == 8 for s in msg.signals)
        return c

    def take(self, t: float, address: int, data: bytes) -> bool:
        """One frame at time ``t`` (s): True when it updated a field."""
        self.counters["can_frames"] += 1
        try:
            msg = self.db.get_message_by_frame_id(address)
        except KeyError:
            self.counters["can_unknown_id"] += 1
            return False
        if len(data) != msg.length:
            self.counters["can_bad_length"] += 1
            return False
        if self._checksummed(msg) and data[-1] != self._rule(address, data):
            self.counters["can_bad_checksum"] += 1
            return False
        entry = self._by_id.get(address)
        if entry is None:
            return False
        try:
            values = msg.decode(data, decode_choices=True, scaling=True)
        except Exception:
            self.counters["can_undecodable"] += 1
            return False
        self.counters[f"can_{msg.name}"] += 1
        for name, rule in entry[1]:
            raw = [values[s] for s in rule.signals]
            if any(not isinstance(v, (int, float)) for v in raw):  # a named choice
                self.state[name] = str(raw[0])
            else:
                self.state[name] = rule.scale * _COMBINE[rule.combine](
                    [float(v) for v in raw]) + rule.offset
            self.stamps[name] = t
        return True
