"""``make demo``: the testbench's main job on the built-in scenario, then two real-data checks.

1. The hardware-in-the-loop run: ``obu run`` and ``rve run`` as two processes over UDP on
   loopback.  The RVE replays the built-in SUMO scenario (a platoon whose leader brakes
   hard at 20 s) at PER 50 % and 4× speed; the OBU tracks with the HGP and runs FCW,
   EEBL, BSW and LCW.  Then ``captures score`` on their capture: PTE, FCW accuracy against
   the FCW on the true states, counts, latency, and the warnings raised.
2. The NYC CV pilot's real FCW event through UPER, the CA-TC and the FCW.
3. The J2735 wire layer: every real BSM in the jpo-ode vectors decoded and re-encoded bit
   for bit, and what J2735 units cost in position.
4. The real comma2k19 minute over the vehicle path: the RVE replays the RAV4's own CAN
   bus (as a serial slcan adapter on a pty) and its u-blox fixes (NMEA over UDP), and the
   vehicles its radar tracked as RVs; the OBU reads its car (``--host-source vehicle``),
   ticks on GNSS time and runs FCW.  Then the score, and the OBU's host estimate against
   comma's fused pose at every tick.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from captures.decode import decode_any, is_message_frame
from captures.live import LiveError, run_daemons
from catc.bsm import BSM
from catc.errors import DecodeError
from catc.geo import EnuFrame
from catc.j2735 import encode_bsm, encode_frame
from catc.j2735.ieee1609 import unwrap, wrap_unsecured
from catc.j2735.sniff import extract_frames


def _reencodes(frame: bytes, bsm: BSM) -> bool:
    again = encode_frame(bsm) if is_message_frame(frame) else encode_bsm(bsm)
    return frame[:len(again)] == again


def vectors_table(vectors: Path) -> tuple[int, int]:
    """Decode every frame in every vector file; print one row a file."""
    print(f"3. Real BSMs from deployed OBUs ({vectors})")
    print(f"   {'file':<46} {'container':<10} {'frames':>6} {'BSMs':>5} {'bit-exact':>9}  "
          "rejected")
    total_bsms = total_exact = 0
    for path in sorted(vectors.iterdir()):
        if path.suffix == ".md":
            continue
        try:
            items = extract_frames(path.read_bytes())
        except DecodeError as err:
            print(f"   {path.name:<46} {'-':<10} {'-':>6} {'-':>5} {'-':>9}  {err.reason}")
            continue
        bsms = exact = 0
        rejected: Counter[str] = Counter()
        for item in items:
            try:
                bsm = decode_any(item.frame)
            except DecodeError as err:
                rejected[err.reason] += 1
                continue
            bsms += 1
            exact += _reencodes(item.frame, bsm)
        container = items[0].container if items else "values"
        why = ", ".join(f"{n} {r}" for r, n in rejected.items())
        print(f"   {path.name:<46} {container:<10} {len(items):>6} {bsms:>5} {exact:>9}  {why}")
        total_bsms += bsms
        total_exact += exact
    print(f"   {total_bsms} BSMs decoded, {total_exact} re-encoded bit for bit")
    return total_bsms, total_exact


def quantization_check(n: int = 600) -> None:
    """A vehicle on a 300 m-radius curve at 25 m/s, 10 Hz, through the whole wire path."""
    print("   A synthetic vehicle through encode → IEEE 1609.2 → unwrap → decode (60 s, 10 Hz)")
    frame = EnuFrame(28.6024, -81.2001, 30.0)
    t = np.arange(n) * 0.1
    theta = 25.0 * t / 300.0
    e, nn = 300.0 * np.sin(theta), 300.0 * (1 - np.cos(theta))
    lat, lon, h = frame.to_geodetic(e, nn, np.zeros(n))
    heading = (90.0 - np.degrees(theta)) % 360.0
    octets = 0
    t0 = time.perf_counter()
    received = []
    for i in range(n):
        bsm = BSM(msg_cnt=i % 128, temp_id=0xC0FFEE01, sec_mark=int(t[i] * 1000) % 60000,
                  lat=float(lat[i]), lon=float(lon[i]), elev=30.0, speed=25.0,
                  heading=float(heading[i]), yaw_rate=-np.degrees(25.0 / 300.0))
        wire = wrap_unsecured(encode_frame(bsm))
        octets += len(wire)
        received.append(decode_any(unwrap(wire).frame))
    elapsed = time.perf_counter() - t0
    re, rn, _ = frame.to_enu(np.array([b.lat for b in received]),
                             np.array([b.lon for b in received]), h)
    err_mm = 1000 * np.hypot(re - e, rn - nn)
    head_err = np.abs((np.array([b.heading for b in received]) - heading + 180) % 360 - 180)
    print(f"   {n} messages, {octets / n:.0f} octets each on the wire, "
          f"{n / elapsed:,.0f} msg/s through the whole path")
    print(f"   position error from J2735 units: max {err_mm.max():.1f} mm, "
          f"mean {err_mm.mean():.1f} mm; heading error max {head_err.max():.4f}°")


def nyc_fcw_event(path: Path) -> None:
    """The real FCW event through encode -> decode -> CA-TC -> FCW; print the timeline."""
    from catc.apps import SafetyApps
    from catc.cam import CamConfig, ContextAwareMap
    from catc.datasets import nyc
    from catc.j2735 import decode_frame
    from catc.replay import ticks

    print(f"2. A real FCW event from the NYC CV pilot ({path.name}): a deployed device")
    print("   warned at T = 0 s.  Its host and target BSMs, through UPER and our CA-TC + FCW:")
    table = nyc.parse(path.read_text(), path.stem)
    cam = ContextAwareMap(CamConfig(predictor="hgp", origin=table.origin), SafetyApps())
    target = next(v for v in table.tracks if v != table.default_host)
    for now, host, msgs in ticks(table):
        snap = cam.step(now, decode_frame(encode_frame(host)),
                        [decode_frame(encode_frame(m)) for m in msgs])
        for e in snap.events:
            when = e.t_start if e.kind == "start" else e.t_end
            print(f"   T = {when:+5.1f} s  {e.app.upper()} {e.kind:<5} on {target}")
        if abs(now) < 1e-6 and len(snap):
            z = snap.rv(0).zone
            w = next((w for w in snap.warnings if w.app == "fcw"), None)
            cond = (f"gap {w.range_m:.1f} m < r_w {w.threshold_m:.1f} m: FCW"
                    if w else "no FCW")
            print(f"   T =  +0.0 s  target {z.longitudinal.value}/{z.lateral.value}/"
                  f"{z.direction.value}, {abs(z.d):.2f} m off the host's path; {cond}")
    speed = table.meta["track_speed"][target]
    print(f"   The target broadcasts {table.tracks[target].speed[0]:.2f} m/s throughout while "
          f"its positions move at {float(np.median(speed)):.1f} m/s:")
    print("   a stuck speed field; with its real speed no FCW fires (docs/reference/catc.md).")


def _free_tcp_port(preferred: int) -> int:
    import socket

    for port in (preferred, 0):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise OSError("no free TCP port")


def hil_run(out: Path, per: float, speed: float, predictor: str, web: bool = True) -> int:
    """The RVE -> OBU run over UDP on loopback, then the score (module docstring, 1)."""
    from captures.score import score, table

    print(f"1. RVE -> OBU over UDP on 127.0.0.1: built-in scenario highway-braking, PER "
          f"{per:g} %, {predictor}, {speed:g}x speed (capture in {out})")
    if out.exists():
        shutil.rmtree(out)
    obu_flags = ["--predictor", predictor]
    if web:
        port = _free_tcp_port(8750)
        obu_flags += ["--web", str(port)]
        print(f"   live view of the OBU while it runs: http://127.0.0.1:{port}/ (afterwards: "
              f"captures view {out}; make demo DEMO_FLAGS=--no-web skips it)", flush=True)
    try:
        warnings = run_daemons(out, ["--per", str(per), "--speed", str(speed), "--seed", "1"],
                               obu_flags)
    except LiveError as err:
        print(f"   failed: {err}")
        return 1
    result = score(out)
    print("   " + table(result).replace("\n", "\n   "))
    print("   warning events (t = dataset s):")
    names = json.loads((out / "rve.config.json").read_text())["vehicles"]
    by_id = {v: k for k, v in names.items()}
    for line in warnings.splitlines():
        e = json.loads(line)
        if e["app"] in ("fcw", "eebl"):
            print(f"     t = {e['t']:5.1f} s  {e['app'].upper():4} {e['kind']:<5} on "
                  f"{by_id.get(e['rv'], e['rv'])}")
    from captures.plot import auto_times, load_run, stills

    the_run = load_run(out)
    pictures = stills(the_run, auto_times(the_run, most=2), out / "plots")
    print("   pictures of the run (bird's-eye views at the FCW, PTE / messages / warnings):")
    for path in pictures:
        print(f"     {path}")
    return 0


def vehicle_run(out: Path, segment: Path, speed: float, predictor: str) -> int:
    """The real minute with the host on the vehicle side (module docstring, 4)."""
    from captures.live import vehicle_flags
    from captures.score import score, table

    print(f"4. The real comma2k19 minute over the vehicle path: CAN (slcan on a pty) and "
          f"GNSS (NMEA over UDP) in, FCW out; {speed:g}x speed (capture in {out})")
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rve_flags, obu_flags = vehicle_flags(out, speed, gnss_delay=0.2)
    try:
        warnings = run_daemons(out, ["--dataset", f"comma2k19:{segment}", "--speed",
                                     str(speed), "--seed", "1", *rve_flags],
                               ["--predictor", predictor, *obu_flags])
    except LiveError as err:
        print(f"   failed: {err}")
        return 1
    result = score(out)
    print("   " + table(result).replace("\n", "\n   "))
    fcw = [json.loads(line) for line in warnings.splitlines()]
    fcw = [e for e in fcw if e["app"] == "fcw"]
    print(f"   FCW events: {len(fcw)}" + "".join(
        f"\n     t = {e['t']:5.1f} s  FCW {e['kind']:<5} on {e['rv']}" for e in fcw))
    host_vs_pose(out, segment)
    return 0


def host_vs_pose(out: Path, segment: Path) -> None:
    """The OBU's host estimate (``obu.vehicle.jsonl``) against comma's fused pose at the
    same instant, every tick."""
    from hil import comma2k19
    from hil.datasets import load_table

    meta = load_table(f"comma2k19:{segment}", None).meta
    pose = comma2k19.pose(comma2k19.segment_of(segment))
    rows = [json.loads(line) for line in (out / "obu.vehicle.jsonl").read_text().splitlines()]
    boot = np.array([r["t_gnss"] - meta["utc_base"] - meta["boot_to_trip_s"] for r in rows])
    inside = (boot >= pose["t"][0]) & (boot <= pose["t"][-1])
    frame = EnuFrame(float(pose["lat"][0]), float(pose["lon"][0]), 0.0)
    pe, pn, _ = frame.to_enu(pose["lat"], pose["lon"], 0.0)
    e, n, _ = frame.to_enu(np.array([r["lat"] for r in rows])[inside],
                           np.array([r["lon"] for r in rows])[inside], 0.0)
    err = np.hypot(e - np.interp(boot[inside], pose["t"], pe),
                   n - np.interp(boot[inside], pose["t"], pn))
    print(f"   the OBU's host from CAN + GNSS against comma's fused pose, {len(err)} ticks: "
          f"p50 {np.percentile(err, 50):.2f} m, p95 {np.percentile(err, 95):.2f} m "
          f"(the raw fixes at their logged times: 1.87 m p95; bench/host_state.py)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="captures.demo", description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"),
                    help="the shared data folder (default ../shared/data)")
    ap.add_argument("--out", type=Path, default=Path("out/demo"),
                    help="capture directory of the RVE -> OBU run (default out/demo)")
    ap.add_argument("--per", type=float, default=50.0, help="packet error rate, %% (50)")
    ap.add_argument("--speed", type=float, default=4.0, help="replay speed factor (4)")
    ap.add_argument("--predictor", default="hgp", help="the OBU's predictor (hgp)")
    ap.add_argument("--no-web", action="store_true",
                    help="no live view (obu run --web) during the run")
    args = ap.parse_args(argv)
    print("catc-hil demo: the V2X hardware-in-the-loop testbench on its built-in scenario\n")
    status = hil_run(args.out, args.per, args.speed, args.predictor, web=not args.no_web)
    print()
    event = args.data / "cv-pilot-samples" / "nycdot-fcw-event.json"
    if event.is_file():
        nyc_fcw_event(event)
    else:
        print(f"2. skipped: no NYC event at {event} (pass --data DIR)")
    print()
    vectors = args.data / "jpo-ode-bsm-vectors"
    if vectors.is_dir():
        vectors_table(vectors)
    else:
        print(f"3. skipped: no real vectors at {vectors} (pass --data DIR)")
    quantization_check()
    print()
    minute = args.data / "comma2k19-example"
    if minute.is_dir():
        status = vehicle_run(args.out.parent / "demo-vehicle", minute, args.speed,
                             args.predictor) or status
    else:
        print(f"4. skipped: no comma2k19 minute at {minute} (pass --data DIR)")
    print(f"\nTry: .venv/bin/captures view {args.out}      # the run in the browser")
    print(f"     .venv/bin/captures score {args.out}")
    print(f"     .venv/bin/captures plot {args.out} --gif")
    print("     .venv/bin/captures decode ../shared/data/jpo-ode-bsm-vectors/rxMsg_BSM.bin")
    print("     .venv/bin/captures replay --dataset nyc:" + str(event))
    print("     .venv/bin/python bench/codec.py; .venv/bin/python bench/step.py")
    return status


if __name__ == "__main__":
    sys.exit(main())
