"""J2735 BSM codec throughput on one core: encode, decode and round trip, messages/s.

Two message kinds:

* core: BSMcoreData only (what most BSMs on the air carry between Part II updates);
* pathhistory: core + VehicleSafetyExtensions with 15 path-history points and a path
  prediction (the shape of the deployed WYDOT/CDOT frames in the jpo-ode vectors).

Each kind uses 1000 distinct messages built from a seeded random walk, so no cache
or branch predictor sees the same message twice in a row.  Each figure is the best
of ``--repeat`` timed passes.  The peer is asn1tools' UPER codec (a compiled ASN.1
codec in Python) on the same messages and the same ASN.1 (``catc/j2735/bsm.asn``),
shown side by side with the ratio; it is skipped when asn1tools is not installed.

    python bench/codec.py [--json] [--repeat N] [--no-peer]

Target (issue 2): at least 50,000 core-only round trips/s.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from importlib import resources

import numpy as np

from catc.bsm import BSM, BrakeStatus, PathHistory, PathHistoryPoint, PathPrediction
from catc.j2735 import decode_frame, encode_frame

N_MESSAGES = 1000
TARGET_CORE_ROUNDTRIPS = 50_000


def make_messages(kind: str, n: int = N_MESSAGES, seed: int = 1) -> list[BSM]:
    rng = np.random.default_rng(seed)
    out = []
    lat, lon, heading, speed = 41.1642, -104.8434, 90.0, 20.0
    for i in range(n):
        heading = (heading + rng.normal(0, 1)) % 360
        speed = max(0.0, speed + rng.normal(0, 0.2))
        lat += 1e-6 * rng.normal()
        lon += 1e-6 * rng.normal()
        extra = {}
        if kind == "pathhistory":
            points = tuple(PathHistoryPoint(lat_offset=-1e-5 * k * rng.random(),
                                            lon_offset=-1e-5 * k * rng.random(),
                                            elev_offset=0.1 * rng.normal(),
                                            time_offset=0.5 * k) for k in range(1, 16))
            extra = {"path_history": PathHistory(points=points),
                     "path_prediction": PathPrediction(float(rng.uniform(-500, 500)), 90.0)}
        out.append(BSM(msg_cnt=i % 128, temp_id=0x31325433, sec_mark=(i * 100) % 60000,
                       lat=lat, lon=lon, elev=1440.9, speed=speed, heading=heading,
                       accel_long=float(rng.normal(0, 1)), accel_lat=0.0, accel_vert=0.0,
                       yaw_rate=float(rng.normal(0, 2)), brakes=BrakeStatus(wheel_brakes=0),
                       width=1.9, length=5.7, **extra))
    return out


def best_rate(fn, items, repeat: int, laps: int = 5) -> float:
    """Best items/s over ``repeat`` passes, each ``laps`` times over ``items``, after one
    untimed warm-up pass."""
    for x in items:
        fn(x)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(laps):
            for x in items:
                fn(x)
        best = min(best, time.perf_counter() - t0)
    return laps * len(items) / best


def measure_ours(messages: list[BSM], repeat: int) -> dict[str, float]:
    frames = [encode_frame(m) for m in messages]
    return {
        "encode_per_s": best_rate(encode_frame, messages, repeat),
        "decode_per_s": best_rate(decode_frame, frames, repeat),
        "roundtrip_per_s": best_rate(lambda m: decode_frame(encode_frame(m)), messages, repeat),
        "frame_octets": float(np.mean([len(f) for f in frames])),
    }


def measure_peer(messages: list[BSM], repeat: int) -> dict[str, float] | None:
    try:
        import asn1tools
    except ImportError:
        return None
    spec = asn1tools.compile_string(
        resources.files("catc.j2735").joinpath("bsm.asn").read_text(), "uper")
    # The peer gets its own native input: the decoded dicts of our frames.
    values = []
    for m in messages:
        mf = spec.decode("MessageFrame", encode_frame(m))
        bsm = spec.decode("BasicSafetyMessage", mf["value"])
        for part in bsm.get("partII", ()):
            part["partII-Value"] = spec.decode("VehicleSafetyExtensions", part["partII-Value"])
        values.append(bsm)

    def encode(v: dict) -> bytes:
        bsm = dict(v)
        if "partII" in bsm:
            bsm["partII"] = [{"partII-Id": p["partII-Id"],
                              "partII-Value": spec.encode("VehicleSafetyExtensions",
                                                          p["partII-Value"])}
                             for p in bsm["partII"]]
        return spec.encode("MessageFrame", {"messageId": 20,
                                            "value": spec.encode("BasicSafetyMessage", bsm)})

    def decode(frame: bytes) -> dict:
        bsm = spec.decode("BasicSafetyMessage", spec.decode("MessageFrame", frame)["value"])
        for part in bsm.get("partII", ()):
            part["partII-Value"] = spec.decode("VehicleSafetyExtensions", part["partII-Value"])
        return bsm

    frames = [encode(v) for v in values]
    assert frames == [encode_frame(m) for m in messages], "peer and ours disagree on the bits"
    return {
        "encode_per_s": best_rate(encode, values, repeat),
        "decode_per_s": best_rate(decode, frames, repeat),
        "roundtrip_per_s": best_rate(lambda v: decode(encode(v)), values, repeat),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--repeat", type=int, default=5, help="timed passes per figure (best taken)")
    ap.add_argument("--no-peer", action="store_true", help="skip the asn1tools comparison")
    args = ap.parse_args()

    results: dict[str, dict] = {}
    for kind in ("core", "pathhistory"):
        messages = make_messages(kind)
        ours = measure_ours(messages, args.repeat)
        peer = None if args.no_peer else measure_peer(messages, args.repeat)
        results[kind] = {"ours": ours, "asn1tools": peer}

    summary = {
        "core_roundtrips_per_s": results["core"]["ours"]["roundtrip_per_s"],
        "pathhistory_roundtrips_per_s": results["pathhistory"]["ours"]["roundtrip_per_s"],
        "target_core_roundtrips_per_s": TARGET_CORE_ROUNDTRIPS,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "messages_per_kind": N_MESSAGES,
        "results": results,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0

    print(f"J2735 BSM codec, one core, {N_MESSAGES} distinct messages per kind, "
          f"best of {args.repeat} passes (Python {platform.python_version()})")
    print(f"{'kind':<12} {'operation':<10} {'catc msg/s':>12} {'asn1tools msg/s':>16} "
          f"{'ratio':>7}")
    for kind, r in results.items():
        for op in ("encode", "decode", "roundtrip"):
            ours = r["ours"][f"{op}_per_s"]
            peer = r["asn1tools"][f"{op}_per_s"] if r["asn1tools"] else None
            peer_s = f"{peer:>16,.0f}" if peer else f"{'-':>16}"
            ratio = f"{ours / peer:>6.1f}x" if peer else f"{'-':>7}"
            print(f"{kind:<12} {op:<10} {ours:>12,.0f} {peer_s} {ratio}")
        print(f"{'':<12} {'octets':<10} {r['ours']['frame_octets']:>12.1f}")
    verdict = "meets" if summary["core_roundtrips_per_s"] >= TARGET_CORE_ROUNDTRIPS else "MISSES"
    print(f"core round trips/s {summary['core_roundtrips_per_s']:,.0f} {verdict} the target "
          f"of {TARGET_CORE_ROUNDTRIPS:,}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
