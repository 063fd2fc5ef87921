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
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterator

import numpy as np

from catc.bsm import BSM
from catc.cam import ContextAwareMap, MapSnapshot
from catc.mobility import MobilityTable, Track

__all__ = ["run_offline", "temp_id", "ticks", "track_bsm"]


def temp_id(vehicle_id: str) -> int:
    """The TemporaryID a vehicle is sent with: CRC-32 of its id text (32 bits)."""
    return zlib.crc32(str(vehicle_id).encode())


def _opt(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def track_bsm(track: Track, i: int, tid: int | None = None) -> BSM:
    """The BSM for sample ``i`` of ``track`` (see the module docstring for each field)."""
    t = float(track.t[i])
    return BSM(
        msg_cnt=i % 128, temp_id=temp_id(track.vehicle_id) if tid is None else tid,
        sec_mark=round(t * 1000.0) % 60_000, lat=float(track.lat[i]), lon=float(track.lon[i]),
        elev=_opt(float(track.elev[i])), speed=float(track.speed[i]),
        heading=float(track.heading[i]) % 360.0, accel_long=float(track.accel[i]),
        yaw_rate=float(track.yaw_rate[i]), length=_opt(track.length),
        width=_opt(track.width))


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
