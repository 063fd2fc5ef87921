"""Mobility tables as BSM streams, and the offline CA-TC run over them.

The RVE encodes exactly these BSMs (:func:`track_bsm`); the offline simulator hands them
to :meth:`catc.cam.ContextAwareMap.step` without sockets (:func:`run_offline`).  Both use
the same rules, so a live run with zero latency and the same loss pattern sees the same
messages at the same ticks.

* TemporaryID: CRC-32 of the vehicle id (:func:`temp_id`), stable across runs.
* msgCnt: the sample index modulo 128 (J2735 MsgCount wraps at 127).
* secMark: ``round(t · 1000) mod 60000`` of the dataset time ``t`` (ms within the
  minute), which :func:`catc.cam.message_time` inverts against the HV's clock.
* Values are the track's, in SI; a track's unknown length/width (NaN) is left
  unavailable.  Brake status is not in the mobility table; ``brakes`` stays unavailable.
* Delivery: the HV ticks at its own samples; each RV message generated in ``(T_prev, T]``
  is delivered at tick ``T`` (zero latency) when the channel passes it.
* :func:`plan` is the RVE's whole send plan (rate, loss, distance, latency from
  :mod:`catc.channel`): the frame events in the order they go on the air.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from catc.bsm import BSM, msg_cnt, sec_mark
from catc.cam import ContextAwareMap, MapSnapshot
from catc.channel import ChannelConfig, schedule
from catc.mobility import MobilityTable, Track

__all__ = ["EVENT_DTYPE", "Plan", "plan", "run_offline", "simulate", "split_due", "temp_id",
           "ticks", "track_bsm"]


def temp_id(vehicle_id: str) -> int:
    """The TemporaryID a vehicle is sent with: CRC-32 of its id text (32 bits)."""
    return zlib.crc32(str(vehicle_id).encode())


def _opt(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


#: The per-sample columns of a Track that a BSM carries, in :func:`_bsm` argument order.
_BSM_COLUMNS = ("t", "lat", "lon", "elev", "speed", "heading", "accel", "yaw_rate")


def _size(track: Track) -> tuple[float | None, float | None]:
    """``(length, width)`` of a track's BSMs; None when unknown."""
    return _opt(track.length), _opt(track.width)


def _bsm(count: int, tid: int, size: tuple[float | None, float | None], t: float,
         lat: float, lon: float, elev: float, speed: float, heading: float, accel: float,
         yaw_rate: float) -> BSM:
    """The BSM of one sample of a track (:func:`_size`) from its values (Python floats)."""
    length, width = size
    return BSM(
        msg_cnt=count, temp_id=tid, sec_mark=sec_mark(t), lat=lat, lon=lon,
        elev=_opt(elev), speed=speed, heading=heading % 360.0, accel_long=accel,
        yaw_rate=yaw_rate, length=length, width=width)


def _sample(track: Track, i: int) -> list[float]:
    """Sample ``i`` of the :data:`_BSM_COLUMNS` of ``track``."""
    return [float(getattr(track, c)[i]) for c in _BSM_COLUMNS]


def track_bsm(track: Track, i: int, tid: int | None = None) -> BSM:
    """The BSM for sample ``i`` of ``track`` (see the module docstring for each field)."""
    return _bsm(msg_cnt(i), temp_id(track.vehicle_id) if tid is None else tid, _size(track),
                *_sample(track, i))


class _SampleBsms:
    """``bsm(vehicle, i, msg_cnt)``: :func:`track_bsm` of a plan's vehicle with another
    msgCnt (what :meth:`Plan.bsm` gives), from each track's columns converted to Python
    floats once (``tolist`` gives the values ``float(column[i])`` gives) instead of
    reading numpy scalars for every message."""

    def __init__(self, the_plan: Plan) -> None:
        self._plan = the_plan
        self._vehicles: dict[int, tuple] = {}

    def bsm(self, vehicle: int, i: int, msg_cnt: int) -> BSM:
        v = self._vehicles.get(vehicle)
        if v is None:
            tr = self._plan.table.tracks[self._plan.vehicles[vehicle]]
            cols = [np.asarray(getattr(tr, c), dtype=np.float64).tolist()
                    for c in _BSM_COLUMNS]
            rows = list(zip(*cols, strict=True))
            v = self._vehicles[vehicle] = (temp_id(tr.vehicle_id), _size(tr), rows)
        tid, size, rows = v
        return _bsm(msg_cnt, tid, size, *rows[i])


#: ``received(vehicle_id, sample_index) -> bool``: the channel's decision for a message.
Channel = Callable[[str, int], bool]


def ticks(table: MobilityTable, host_id: str | None = None,
          received: Channel | None = None) -> Iterator[tuple[float, BSM, list[BSM]]]:
    """``(now, host_bsm, rv_messages)`` for every HV sample of ``table``.

    ``host_id`` defaults to the table's ``default_host``; ``received`` to "every message
    arrives".  RV messages are in vehicle order, then time.
    """
    host_id = host_id or table.default_host
    if host_id is None or host_id not in table.tracks:
        raise ValueError(f"table {table.name!r} has no host vehicle {host_id!r}; "
                         f"vehicles: {', '.join(table.tracks)}")
    host = table.tracks[host_id]
    others = [(vid, tr, temp_id(vid)) for vid, tr in table.tracks.items() if vid != host_id]
    host_tid = temp_id(host_id)
    prev = -math.inf
    for k in range(len(host)):
        now = float(host.t[k])
        msgs: list[BSM] = []
        for vid, tr, tid in others:
            lo = int(np.searchsorted(tr.t, prev, side="right"))
            hi = int(np.searchsorted(tr.t, now, side="right"))
            msgs += [track_bsm(tr, i, tid) for i in range(lo, hi)
                     if received is None or received(vid, i)]
        yield now, track_bsm(host, k, host_tid), msgs
        prev = now


def run_offline(table: MobilityTable, cam: ContextAwareMap, host_id: str | None = None,
                received: Channel | None = None) -> Iterator[MapSnapshot]:
    """Drive ``cam`` through ``table`` (see :func:`ticks`), yielding each snapshot."""
    for now, host, msgs in ticks(table, host_id, received):
        yield cam.step(now, host, msgs)


# --- the send plan of a replay: what goes on the air when ---------------------------------------

#: One row per frame event of a replay, sorted by ``time``: the HV's state on its own
#: channel (never lost), and every message the RVs send (delivered or dropped).
EVENT_DTYPE = np.dtype([
    ("time", np.float64),  # dataset time the frame goes out (t + delay), or t if dropped
    ("t", np.float64),  # generation time
    ("vehicle", np.int32),  # index into Plan.vehicles
    ("index", np.int64),  # sample index in the vehicle's track
    ("seq", np.int64),  # number among the vehicle's sent messages (msgCnt = seq mod 128)
    ("host", np.bool_),  # the HV channel
    ("dropped", np.bool_),
    ("cause", np.int8),  # catc.channel.CAUSES
    ("delay", np.float64),  # s; NaN when dropped
])


@dataclass(frozen=True, eq=False)
class Plan:
    """A replay's frame events (:data:`EVENT_DTYPE`) and the vehicles they refer to."""

    table: MobilityTable
    host_id: str
    vehicles: tuple[str, ...]  # names; index 0 is the host
    events: np.ndarray
    config: ChannelConfig
    seed: int

    def bsm(self, event: np.void) -> BSM:
        """The BSM of one event (msgCnt from the send sequence)."""
        tr = self.table.tracks[self.vehicles[int(event["vehicle"])]]
        return _bsm(msg_cnt(int(event["seq"])), temp_id(tr.vehicle_id), _size(tr),
                    *_sample(tr, int(event["index"])))


def plan(table: MobilityTable, config: ChannelConfig, seed: int = 0,
         host_id: str | None = None, duration: float | None = None) -> Plan:
    """Every frame event of a replay of ``table`` through the channel ``config``.

    The HV sends every sample on its own channel with no loss and no delay; each RV's
    messages follow :func:`catc.channel.schedule` keyed by ``(seed, "TRIP/VEHICLE")``,
    with the HV–RV distance of each sample for the distance model.  Events are sorted by
    time, RV frames before the HV frame of the same instant (so a receiver that steps on
    the HV frame has the RV frames generated up to then), then by vehicle.  ``duration``
    keeps the events of the first ``duration`` seconds after the HV's first sample.
    """
    host_id = host_id or table.default_host
    if host_id is None or host_id not in table.tracks:
        raise ValueError(f"table {table.name!r} has no host vehicle {host_id!r}; "
                         f"vehicles: {', '.join(table.tracks)}")
    host = table.tracks[host_id]
    names = (host_id, *(v for v in table.tracks if v != host_id))
    parts = []
    n = len(host)
    hv = np.zeros(n, dtype=EVENT_DTYPE)
    hv["time"] = hv["t"] = host.t
    hv["index"] = hv["seq"] = np.arange(n)
    hv["host"] = True
    hv["delay"] = 0.0
    parts.append(hv)
    for k, vid in enumerate(names[1:], start=1):
        tr = table.tracks[vid]
        dist = np.hypot(tr.x - np.interp(tr.t, host.t, host.x),
                        tr.y - np.interp(tr.t, host.t, host.y))
        sch = schedule(config, seed, f"{table.name}/{vid}", tr.t, dist)
        ev = np.zeros(len(sch), dtype=EVENT_DTYPE)
        ev["t"], ev["index"], ev["seq"] = sch["t"], sch["index"], sch["seq"]
        ev["dropped"], ev["cause"], ev["delay"] = sch["dropped"], sch["cause"], sch["delay"]
        ev["time"] = np.where(sch["dropped"], sch["t"], sch["t"] + np.nan_to_num(sch["delay"]))
        ev["vehicle"] = k
        parts.append(ev)
    events = np.concatenate(parts)
    if duration is not None:
        events = events[events["t"] <= float(host.t[0]) + duration + 1e-9]
    order = np.lexsort((events["vehicle"], events["host"], events["time"]))
    return Plan(table, host_id, names, events[order], config, seed)


def simulate(the_plan: Plan, cam: ContextAwareMap, wire: bool = True
             ) -> Iterator[MapSnapshot]:
    """The offline simulator: what an OBU on the RVE's channel would compute, no sockets.

    Walks the plan's events in order; every delivered RV frame waits until the next HV
    frame, which steps ``cam`` with ``now`` from the HV's secMark clock
    (:class:`catc.cam.SecMarkClock`) and every waiting message generated by then (later
    ones wait for a later tick), exactly the rule of the live OBU.  ``wire``: each BSM
    goes through UPER encode and decode first, so its values are what a receiver gets.
    """
    from catc.cam import SecMarkClock
    from catc.j2735 import decode_frame, encode_frame

    clock = SecMarkClock()
    pending: list[BSM] = []
    bsms = _SampleBsms(the_plan)
    ev = the_plan.events
    columns = (ev[c].tolist() for c in ("dropped", "host", "vehicle", "index", "seq"))
    for dropped, host, vehicle, index, seq in zip(*columns, strict=True):
        if dropped:
            continue
        m = bsms.bsm(vehicle, index, msg_cnt(seq))  # the_plan.bsm(event)
        if wire:
            m = decode_frame(encode_frame(m))
        if not host:
            pending.append(m)
            continue
        now = clock(m.sec_mark)
        due, pending = split_due(now, pending, cam.config.max_future_s)
        yield cam.step(now, m, due)


def split_due(now: float, pending: list[BSM], future_s: float = math.inf,
              ) -> tuple[list[BSM], list[BSM]]:
    """(messages generated at or before ``now``, the rest): what a tick at ``now`` takes.
    A message without secMark is due at once (the CAM counts it as incomplete), and so is
    one more than ``future_s`` ahead of ``now`` (the CAM counts it as ``future``): held
    back, a corrupted secMark up to 30 s ahead would keep it in memory that long."""
    from catc.cam import message_time

    due: list[BSM] = []
    later: list[BSM] = []
    for p in pending:
        if p.sec_mark is None:
            due.append(p)
            continue
        ahead = message_time(now, p.sec_mark) - now
        (due if ahead <= 1e-9 or ahead > future_s else later).append(p)
    return due, later
