"""The host's own state from CAN and GNSS, against comma's fused pose, on the real minute.

The OBU's host-state estimator (:class:`catc.hoststate.HostEstimator`) is fed what the
OBU would read on the comma2k19 RAV4 minute (``../shared/data/comma2k19-example``), in
the order it happened on the car's boot clock: every frame of the car bus (bus 0)
through the shipped profile's decoder (:class:`catc.vehicle.CanDecoder`, with its
checksum checks), and every u-blox fix when it was logged.  It ticks at 10 Hz of GNSS
time, as ``obu run --host-source vehicle`` does, and each tick's state is compared with
the truth at the same instant of the boot clock:

* position with comma's fused ``global_pose`` (INS/GNSS/vision, 20 Hz, interpolated);
* speed with the wheel speed (comma's processed ``speed``);
* yaw rate with the IMU gyro (its 0.2 s centred mean: the raw 100 Hz samples carry
  the road's vibration, ±1.7 deg/s from one to the next);
* heading with the pose's velocity heading.

Beside it, the peers: the raw u-blox fixes taken at the times they were logged (what an
OBU that trusts its receiver has), and the same fixes with the latency the estimator
measured taken off, and the estimator without CAN (fixes only, held between them).
``--latency S`` fixes the latency instead of measuring it; ``--drop START:DURATION``
silences the GNSS for a while (the dead reckoning alone carries it).

    python bench/host_state.py [--json] [--segment PATH] [--latency S] [--drop S:D]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from catc.geo import EnuFrame
from catc.hoststate import EstimatorConfig, HostEstimator
from catc.vehicle import CanDecoder
from hil import comma2k19
from hil.vehicle import comma2k19_can, load_profile

#: Samples of the 100 Hz gyro averaged for the yaw-rate truth (0.2 s).
GYRO_MEAN = 21
#: The u-blox's sentences were logged 0.20 s after their UTC stamps (tests/test_comma2k19.py).
GNSS_DELAY_S = 0.2
DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "comma2k19-example"


def run(segment: Path, latency: float | None = None,
        drop: tuple[float, float] | None = None, use_can: bool = True) -> dict:
    """Feed the minute to an estimator; the per-tick errors and what it learnt."""
    profile, db = load_profile("toyota-rav4-2017")
    decoder = CanDecoder(profile, db)
    frames = comma2k19_can(segment, {0: db})
    fix_t, fixes = comma2k19.ublox_fixes(segment)
    est = HostEstimator(EstimatorConfig(gnss_delay_s=GNSS_DELAY_S, latency_s=latency))
    t0 = float(fix_t[0])
    events = [(float(r["t"]), 0, i) for i, r in enumerate(frames)] if use_can else []
    events += [(float(t), 1, i) for i, t in enumerate(fix_t)
               if drop is None or not drop[0] <= float(t) - t0 < drop[0] + drop[1]]
    events.sort()
    ticks: list[tuple[float, object]] = []
    next_tick = None
    for t, kind, i in events:
        while next_tick is not None and (local := est.local_time(next_tick)) <= t:
            ticks.append((local, est.state(local)))
            next_tick += 0.1
        if kind == 0:
            r = frames[i]
            data = bytes(r["data"]).ljust(int(r["length"]), b"\0")[: int(r["length"])]
            if decoder.take(t, int(r["address"]), data):
                est.can(t, {k: decoder.state[k] for k, s in decoder.stamps.items() if s == t})
        else:
            est.fix(t, fixes[i])
            if next_tick is None:
                next_tick = math.floor(est.gnss_time(t) * 10.0 + 1.0) / 10.0
    return _errors(segment, ticks, est, fix_t, fixes, drop)


def _errors(segment: Path, ticks: list, est: HostEstimator, fix_t: np.ndarray, fixes: list,
            drop: tuple[float, float] | None) -> dict:
    p = comma2k19.pose(segment)
    wt, ws = comma2k19.wheel_speed(segment)
    gt, gz = comma2k19.gyro(segment)
    # the gyro at 100 Hz carries the road's vibration (±1.7 deg/s sample to sample):
    # compare with its 0.2 s centred mean, as KINEMATICS' own yaw rate is smoothed
    gz = np.convolve(gz, np.ones(GYRO_MEAN) / GYRO_MEAN, mode="same")
    frame = EnuFrame(float(p["lat"][0]), float(p["lon"][0]), 0.0)
    pe, pn, _ = frame.to_enu(p["lat"], p["lon"], 0.0)
    inside = [(t, s) for t, s in ticks if p["t"][0] <= t <= p["t"][-1]]
    tt = np.array([t for t, _ in inside])
    se, sn, _ = frame.to_enu(np.array([s.lat for _, s in inside]),
                             np.array([s.lon for _, s in inside]), 0.0)
    pos = np.hypot(se - np.interp(tt, p["t"], pe), sn - np.interp(tt, p["t"], pn))
    speed = np.abs(np.array([s.speed for _, s in inside]) - np.interp(tt, wt, ws))
    yaw = np.abs(np.array([s.yaw_rate for _, s in inside]) - np.interp(tt, gt, gz))
    hdg_true = np.degrees(np.unwrap(np.radians(p["heading"])))
    hdg = np.abs((np.array([s.heading for _, s in inside])
                  - np.interp(tt, p["t"], hdg_true) + 180.0) % 360.0 - 180.0)
    # the peers: the raw fixes at their logged times, and with the measured latency off
    fe, fn, _ = frame.to_enu(np.array([f.lat for f in fixes]),
                             np.array([f.lon for f in fixes]), 0.0)

    def raw(shift: float) -> np.ndarray:
        at = fix_t - shift
        ok = (at >= p["t"][0]) & (at <= p["t"][-1])
        return np.hypot(fe[ok] - np.interp(at[ok], p["t"], pe),
                        fn[ok] - np.interp(at[ok], p["t"], pn))

    out = {
        "ticks": len(inside),
        "position_m": _stats(pos), "speed_mps": _stats(speed), "yaw_rate_dps": _stats(yaw),
        "heading_deg": _stats(hdg),
        "raw_fixes_at_logged_time_m": _stats(raw(0.0)),
        "raw_fixes_minus_latency_m": _stats(raw(est.latency)),
        "latency_s": est.latency, "latency_fitted": est.latency_fitted,
        "latency_fit": est.latency_fit,
        "yaw_bias_dps": est.bias, "speed_scale": est.scale,
        "counters": dict(est.counters),
    }
    if drop is not None:
        t0 = float(fix_t[0])
        silent = (tt - t0 >= drop[0]) & (tt - t0 < drop[0] + drop[1])
        out["position_in_dropout_m"] = _stats(pos[silent])
    return out


def _stats(x: np.ndarray) -> dict[str, float]:
    if len(x) == 0:
        return {"n": 0}
    return {"n": len(x), "p50": float(np.percentile(x, 50)),
            "p95": float(np.percentile(x, 95)), "max": float(np.max(x))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segment", type=Path, default=DEFAULT)
    ap.add_argument("--latency", type=float, default=None,
                    help="the fixes' latency (s) instead of measuring it")
    ap.add_argument("--drop", default=None, metavar="START:DURATION",
                    help="no fixes from START s for DURATION s")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        seg = comma2k19.segment_of(args.segment)
    except ValueError as err:
        print(f"host_state: {err}", file=sys.stderr)
        return 2
    drop = tuple(float(x) for x in args.drop.split(":")) if args.drop else None
    rows = {"CAN + GNSS (the OBU)": run(seg, args.latency, drop),
            "GNSS only, no CAN": run(seg, args.latency, drop, use_can=False)}
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    main_row = rows["CAN + GNSS (the OBU)"]
    fit = main_row["latency_fit"]
    how = ("measured" if main_row["latency_fitted"] else
           "given" if args.latency is not None else
           "the prior; the fit, " + ("none" if fit is None else
                                     f"{fit[0]:.3f} s with standard error {fit[1]:.3f} s")
           + ", is not sure enough")
    print(f"comma2k19 minute, {main_row['ticks']} ticks at 10 Hz; latency "
          f"{main_row['latency_s']:.2f} s ({how}),"
          f" yaw-rate bias {main_row['yaw_bias_dps']:+.3f} deg/s, speed scale "
          f"{main_row['speed_scale']:.4f}")
    print(f"{'estimate':<28}{'what':<22}{'p50':>8}{'p95':>8}{'max':>8}")
    for name, r in rows.items():
        for key, what in (("position_m", "position (m)"), ("speed_mps", "speed (m/s)"),
                          ("yaw_rate_dps", "yaw rate (deg/s)"),
                          ("heading_deg", "heading (deg)"),
                          ("position_in_dropout_m", "position, dropout (m)")):
            if key in r and r[key].get("n"):
                s = r[key]
                print(f"{name:<28}{what:<22}{s['p50']:>8.3f}{s['p95']:>8.3f}{s['max']:>8.3f}")
    for key, what in (("raw_fixes_at_logged_time_m", "raw fixes at logged time"),
                      ("raw_fixes_minus_latency_m", "raw fixes minus latency")):
        s = main_row[key]
        print(f"{what:<28}{'position (m)':<22}{s['p50']:>8.3f}{s['p95']:>8.3f}{s['max']:>8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
