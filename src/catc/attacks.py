"""Misbehaving senders for the RVE (``rve run --attack KIND[:KEY=VALUE,...]``), with ground
truth.

The kinds follow the fault types of the public misbehavior datasets (VeReMi and its
extension, F2MD's attack types, the USDOT J3287 faulty-BSM generator):

=================  ====================================================================
``ghost``          a vehicle that does not exist, placed ``ahead`` m ahead of the host on
                   the host's own path (its lane) at ``start``, with the host's speed, then
                   braking at ``decel`` m/s²: the FCW false-alarm attack.  ``signer``
                   ``insider`` (a valid pseudonym certificate of the PKI, not used by any
                   RV) or ``outsider`` (the untrusted ``foreign`` PKI).
``sudden``         a vehicle appearing from nowhere ``distance`` m ahead of the host at
                   ``start``, at the host's speed (no braking): sudden appearance.
``sybil``          ``count`` extra ids sent by one vehicle (``vehicle``), placed along its
                   path every ``spacing`` m behind it, with its speed and heading.
``impersonate``    an insider (``signer``: its own valid pseudonym certificate) sending
                   under ``vehicle``'s TemporaryID, placed ``ahead`` m ahead of the host on
                   its path at the host's speed (0: on the host): nothing binds a BSM's id
                   to the certificate that signs it but the receiver.
``replay``         the frames of ``vehicle`` from ``delay`` s ago sent again, octet for
                   octet (with their old generation time when signed).
``offset``         ``vehicle``'s positions shifted by (``dx``, ``dy``) m east/north.
``speed``          ``vehicle``'s speed multiplied by ``factor`` and its acceleration set to
                   ``accel``: values that contradict the positions.
``unsigned``       ``vehicle``'s frames sent without a signature (``--sign`` runs).
``bad-signature``  ``vehicle``'s frames with one bit of the signature flipped.
``foreign-cert``   ``vehicle``'s frames signed by a key of the untrusted ``foreign`` PKI.
=================  ====================================================================

Every kind takes ``start`` (s after the first sample, default 5) and ``duration`` (s,
default: to the end).  ``vehicle`` defaults to the RV nearest the host at ``start``.
This module builds the fabricated BSMs and the changed values; the RVE signs, sends and
labels them (each in ``rve.schedule.jsonl`` with ``"attack": KIND``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from catc.bsm import BSM, msg_cnt, sec_mark
from catc.replay import temp_id

__all__ = [
    "FABRICATED",
    "KINDS",
    "MODIFYING",
    "SECURITY",
    "Attack",
    "Attacks",
    "Injected",
    "parse",
]

FABRICATED = ("ghost", "sudden", "sybil", "impersonate")
MODIFYING = ("offset", "speed")
SECURITY = ("unsigned", "bad-signature", "foreign-cert")
KINDS = (*FABRICATED, "replay", *MODIFYING, *SECURITY)

#: Parameters of each kind and their defaults (numbers, except ``vehicle`` and ``signer``).
PARAMS: dict[str, dict[str, Any]] = {
    "ghost": {"ahead": 20.0, "decel": 6.0, "signer": "insider"},
    "sudden": {"distance": 15.0, "signer": "insider"},
    "sybil": {"vehicle": None, "count": 3, "spacing": 8.0},
    "impersonate": {"vehicle": None, "ahead": 0.0, "signer": "insider"},
    "replay": {"vehicle": None, "delay": 3.0},
    "offset": {"vehicle": None, "dx": 0.0, "dy": 30.0},
    "speed": {"vehicle": None, "factor": 2.0, "accel": 0.0},
    "unsigned": {"vehicle": None},
    "bad-signature": {"vehicle": None},
    "foreign-cert": {"vehicle": None},
}
_COMMON = {"start": 5.0, "duration": math.inf}
_EARTH_M_PER_DEG = 111_320.0


@dataclass(frozen=True)
class Attack:
    """One ``--attack`` (parsed, defaults filled in)."""

    kind: str
    params: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, key: str) -> Any:
        return self.params[key]

    def active(self, t_rel: float) -> bool:
        return self["start"] <= t_rel < self["start"] + self["duration"]


def parse(text: str) -> Attack:
    """``KIND[:KEY=VALUE,...]`` (ValueError with one line naming what is wrong)."""
    kind, _, rest = text.partition(":")
    kind = kind.strip()
    if kind not in PARAMS:
        raise ValueError(f"--attack {text!r}: unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
    params = {**_COMMON, **PARAMS[kind]}
    for item in filter(None, (x.strip() for x in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or key not in params:
            raise ValueError(f"--attack {text!r}: {item!r} is not KEY=VALUE with KEY one of "
                             f"{', '.join(sorted(params))}")
        if key == "vehicle":
            params[key] = value
        elif key == "signer":
            if value not in ("insider", "outsider"):
                raise ValueError(f"--attack {text!r}: signer is insider or outsider")
            params[key] = value
        else:
            try:
                params[key] = float(value)
            except ValueError:
                raise ValueError(f"--attack {text!r}: {key} must be a number") from None
            if not math.isfinite(params[key]):
                raise ValueError(f"--attack {text!r}: {key} must be a finite number")
    if kind == "sybil":
        params["count"] = int(params["count"])
        if not 1 <= params["count"] <= 64:
            raise ValueError(f"--attack {text!r}: count from 1 to 64")
    if params["duration"] <= 0:
        raise ValueError(f"--attack {text!r}: duration must be > 0")
    return Attack(kind, params)


@dataclass(frozen=True)
class Injected:
    """A fabricated message: dataset time, the BSM, and its attack's label."""

    t: float
    bsm: BSM
    attack: Attack
    index: int  # which attack of the run (the order of the --attack flags)


def _shift(lat: float, lon: float, east: float, north: float) -> tuple[float, float]:
    return (lat + north / _EARTH_M_PER_DEG,
            lon + east / (_EARTH_M_PER_DEG * math.cos(math.radians(lat))))


class _Path:
    """A track as a function of its arc length (lat, lon, heading by distance travelled)."""

    def __init__(self, track) -> None:
        x, y = np.asarray(track.x, float), np.asarray(track.y, float)
        step = np.hypot(np.diff(x), np.diff(y))
        self.s = np.concatenate([[0.0], np.cumsum(step)])
        self.t = np.asarray(track.t, float)
        self.lat, self.lon = np.asarray(track.lat, float), np.asarray(track.lon, float)
        self.heading = np.unwrap(np.radians(np.asarray(track.heading, float)))
        self.speed = np.asarray(track.speed, float)

    def s_at(self, t: float) -> float:
        return float(np.interp(t, self.t, self.s))

    def at(self, s: float) -> tuple[float, float, float]:
        """(lat, lon, heading °) at arc length ``s``; past either end, along the end's
        heading."""
        s_end = float(self.s[-1])
        over = s - s_end if s > s_end else min(0.0, s)
        s_in = min(max(s, 0.0), s_end)
        lat = float(np.interp(s_in, self.s, self.lat))
        lon = float(np.interp(s_in, self.s, self.lon))
        hdg = float(np.interp(s_in, self.s, self.heading))
        if over:
            lat, lon = _shift(lat, lon, over * math.sin(hdg), over * math.cos(hdg))
        return lat, lon, math.degrees(hdg) % 360.0


class Attacks:
    """The attacks of one run over a :class:`catc.replay.Plan` (module docstring)."""

    #: TemporaryIDs of fabricated vehicles: 0x6A7Axxyy (xx = attack index, yy = id index).
    ID_BASE = 0x6A7A0000

    def __init__(self, attacks: list[Attack], the_plan) -> None:
        self.attacks = attacks
        self.plan = the_plan
        tracks = the_plan.table.tracks
        self.host = tracks[the_plan.host_id]
        self.t0 = float(the_plan.events["t"][0]) if len(the_plan.events) else 0.0
        self.host_path = _Path(self.host)
        self.targets: dict[int, int] = {}  # attack index -> plan vehicle index
        for k, a in enumerate(attacks):
            if "vehicle" in a.params:
                self.targets[k] = self._vehicle(a)
        self._paths: dict[int, _Path] = {}
        self._msg_cnt: dict[int, int] = {}
        #: attack index -> the TemporaryID an impersonator sends under (its vehicle's)
        self.victim_ids = {k: temp_id(the_plan.vehicles[self.targets[k]])
                           for k, a in enumerate(attacks) if a.kind == "impersonate"}

    def _vehicle(self, a: Attack) -> int:
        names = list(self.plan.vehicles)
        if a["vehicle"] is not None:
            if a["vehicle"] not in names or a["vehicle"] == self.plan.host_id:
                rvs = ", ".join(n for n in names[:12] if n != self.plan.host_id)
                raise ValueError(f"--attack {a.kind}: vehicle {a['vehicle']!r} is not an RV "
                                 f"of this run; RVs: {rvs}")
            return names.index(a["vehicle"])
        t = self.t0 + a["start"]
        hx = float(np.interp(t, self.host.t, self.host.x))
        hy = float(np.interp(t, self.host.t, self.host.y))
        best, best_d = None, math.inf
        for i, name in enumerate(names):
            tr = self.plan.table.tracks[name]
            if name == self.plan.host_id or not tr.t[0] <= t <= tr.t[-1]:
                continue
            d = math.hypot(float(np.interp(t, tr.t, tr.x)) - hx,
                           float(np.interp(t, tr.t, tr.y)) - hy)
            if d < best_d:
                best, best_d = i, d
        if best is None:
            raise ValueError(f"--attack {a.kind}: no RV is on the air at start={a['start']:g} s")
        return best

    def target(self, k: int) -> int | None:
        return self.targets.get(k)

    def _next_cnt(self, tid: int) -> int:
        n = self._msg_cnt.get(tid, -1) + 1
        self._msg_cnt[tid] = n
        return msg_cnt(n)

    def _fabricated(self, k: int, a: Attack, t: float) -> list[BSM]:
        tau = t - self.t0 - a["start"]
        host_v = float(np.interp(self.t0 + a["start"], self.host.t, self.host.speed))
        if a.kind in ("ghost", "sudden", "impersonate"):
            ahead = a["distance"] if a.kind == "sudden" else a["ahead"]
            decel = a["decel"] if a.kind == "ghost" else 0.0
            stop = host_v / decel if decel > 0 else math.inf
            tt = min(tau, stop)
            s = self.host_path.s_at(self.t0 + a["start"]) + ahead + host_v * tt \
                - 0.5 * decel * tt * tt
            v = max(0.0, host_v - decel * tau)
            lat, lon, hdg = self.host_path.at(s)
            tid = self.ID_BASE | (k << 8) if a.kind != "impersonate" \
                else self.victim_ids[k]
            return [BSM(msg_cnt=self._next_cnt(tid), temp_id=tid,
                        sec_mark=sec_mark(t), lat=lat, lon=lon, speed=v,
                        heading=hdg, accel_long=-decel if v > 0 else 0.0, yaw_rate=0.0,
                        length=4.5, width=1.8)]
        # sybil: ids along the sender's own path, behind it
        v = self.targets[k]
        path = self._paths.get(v)
        if path is None:
            path = self._paths[v] = _Path(self.plan.table.tracks[self.plan.vehicles[v]])
        if not path.t[0] <= t <= path.t[-1]:
            return []
        s = path.s_at(t)
        speed = float(np.interp(t, path.t, path.speed))
        out = []
        for j in range(a["count"]):
            lat, lon, hdg = path.at(s - (j + 1) * a["spacing"])
            tid = self.ID_BASE | (k << 8) | (j + 1)
            out.append(BSM(msg_cnt=self._next_cnt(tid), temp_id=tid,
                           sec_mark=sec_mark(t), lat=lat, lon=lon,
                           speed=speed, heading=hdg, accel_long=0.0, yaw_rate=0.0,
                           length=4.5, width=1.8))
        return out

    def injected(self, t: float) -> list[Injected]:
        """The fabricated messages generated at dataset time ``t`` (one per fabricated id
        and host sample while its attack is active)."""
        out = []
        for k, a in enumerate(self.attacks):
            if a.kind in FABRICATED and a.active(t - self.t0):
                out += [Injected(t, b, a, k) for b in self._fabricated(k, a, t)]
        return out

    def modify(self, vehicle: int, t: float, bsm: BSM) -> tuple[BSM, Attack | None]:
        """``bsm`` of plan vehicle ``vehicle`` at ``t`` as the value attacks change it."""
        for k, a in enumerate(self.attacks):
            if a.kind in MODIFYING and self.targets.get(k) == vehicle \
                    and a.active(t - self.t0):
                if a.kind == "offset" and bsm.lat is not None and bsm.lon is not None:
                    lat, lon = _shift(bsm.lat, bsm.lon, a["dx"], a["dy"])
                    return dataclasses.replace(bsm, lat=lat, lon=lon), a
                if a.kind == "speed" and bsm.speed is not None:
                    return dataclasses.replace(bsm, speed=min(163.8, bsm.speed * a["factor"]),
                                               accel_long=a["accel"]), a
        return bsm, None

    def security(self, vehicle: int, t: float) -> Attack | None:
        """The security-layer attack on plan vehicle ``vehicle``'s frame at ``t``, if any."""
        for k, a in enumerate(self.attacks):
            if a.kind in SECURITY and self.targets.get(k) == vehicle and a.active(t - self.t0):
                return a
        return None

    def replays(self, vehicle: int, t: float) -> list[Attack]:
        """Replay attacks that resend ``vehicle``'s frame of ``t - delay`` at ``t``."""
        return [a for k, a in enumerate(self.attacks)
                if a.kind == "replay" and self.targets.get(k) == vehicle
                and a.active(t - self.t0)]
