"""A CA-TC's first ticks without their one-off costs: :func:`warm_up`."""

from __future__ import annotations

from typing import Any

from catc.bsm import BSM
from catc.cam._config import CamConfig
from catc.geo import EnuFrame

__all__ = ["warm_up"]

#: the scene: lanes (m, right of the HV's), start (m ahead), speed (m/s), oncoming
_RVS = ((0.0, 30.0, 22.0, False), (0.0, 60.0, 24.0, False), (3.6, 10.0, 25.0, False),
        (-3.6, -20.0, 26.0, False), (3.6, -60.0, 27.0, False), (7.2, 120.0, 25.0, True),
        (10.8, -90.0, 23.0, True), (0.0, -40.0, 25.0, False))
_TICKS = 45
_DT = 0.1
_FRAME = EnuFrame(46.89, 16.84, 0.0)


def warm_up(config: CamConfig | None = None, apps: Any = None) -> int:
    """Run a throwaway :class:`~catc.cam.ContextAwareMap` with ``apps`` (a fresh
    :class:`catc.apps.SafetyApps`: its state is spent on the scene) through a small scene
    (eight RVs ahead, beside, behind and oncoming, messages lost in runs of up to three,
    a lead vehicle braking hard, some messages unverified), so that every compiled kernel
    of a tick is loaded (or, on a machine's first run, compiled) and every lazy import
    done before a daemon's first real tick.  Without it the first ticks of ``obu run``
    take 10-20 ms more (numba loads a kernel at its first call), just when every RV is
    new and verified at once.
    Pure: it touches nothing outside the map it makes.  The number of warnings raised
    (with the apps, the braking leader raises some: their paths are warm too)."""
    from catc.cam._map import ContextAwareMap

    cam = ContextAwareMap(config or CamConfig(), apps)
    warnings = 0
    for k in range(_TICKS):
        t = k * _DT
        # (temp id, x, y, speed, heading, accel): the HV first, then the RVs heard
        states = [(0x7FFF_FFFF, 0.0, 25.0 * t, 25.0, 0.0, 0.0)]
        for i, (x, s0, v, oncoming) in enumerate(_RVS):
            # lost in runs of up to three (none in the first three ticks: every RV
            # gets its track)
            if k > 2 and (k + i) % (i + 3) < i % 4:
                continue
            braking = i == 0 and t > 2.0
            speed = max(v - 6.0 * (t - 2.0), 4.0) if braking else v
            along = (v * t - 3.0 * (t - 2.0) ** 2) if braking else v * t
            states.append((0x1000 + 977 * i, x, s0 - along if oncoming else s0 + along,
                           speed, 180.0 if oncoming else 0.0, -6.0 if braking else 0.0))
        lat, lon, _ = _FRAME.to_geodetic([s[1] for s in states], [s[2] for s in states])
        host, *messages = [
            BSM(msg_cnt=k % 128, temp_id=tid, sec_mark=round(t * 1000.0) % 60_000,
                lat=float(la), lon=float(lo), speed=v, heading=h, accel_long=a,
                yaw_rate=0.0, length=4.8, width=1.9)
            for (tid, _, _, v, h, a), la, lo in zip(states, lat, lon, strict=True)]
        # the last RV's messages of every other tick unverified (verify on demand)
        unverified = frozenset(id(m) for m in messages[-1:] if k % 2)
        warnings += len(cam.step(t, host, messages, unverified).warnings)
    return warnings
