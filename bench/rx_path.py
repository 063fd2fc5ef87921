"""The OBU's per-frame receive path before any ECDSA, µs/frame and frames/s on one core.

What the OBU does with each signed RV frame under verify on demand
(``obu.frames.Frames.take`` → ``Frames._on_demand``) up to the ECDSA: the WSMP and
IEEE 1609.2 parse (``catc.j2735.open_envelope``), the cheap security checks
(``catc.security.Verifier.check``: envelope, psid, a known signer, validity, freshness,
expiry, canonical encoding, replay cache) and the UPER decode of the BSM
(``catc.j2735.decode_frame``).  At 1,000 RVs that is 10,000 frames/s.

The frames are made as ``rve run --sign PKI --framing wsmp`` sends them: the BSMs of
``dense:N:scenario:highway-braking`` (N background vehicles, the RVs' events in schedule
order from ``--skip`` s of data time on, so that the first second, where every vehicle
sends its certificate, is past), each signed by its vehicle's pseudonym through
``rve.signing.Signer`` (a digest signer, the full certificate once a second and after a
new neighbour: about one frame in ten) and wrapped by ``rve.framing.wrap``, every frame
distinct.  The PKI is a seeded test PKI (``catc.security.make_pki``); the verifier trusts
its root and knows its AA, as ``obu run --trust PKI_DIR``; each frame is checked at its
generationTime + 2 ms.  One untimed pass verifies every pseudonym certificate once (the
chains are cached, as in a running OBU), and asserts that every frame passes.

Timed, each the best of ``--repeat`` passes over all frames: ``open_envelope`` alone,
``Verifier.check`` alone (on the envelopes that ``open_envelope`` returned),
``decode_frame`` alone, and the three in a row as ``Frames._on_demand`` runs them.
``--profile`` adds the cProfile of the three in a row (top functions by own time).

    python bench/rx_path.py [--json] [--frames N] [--repeat N] [--profile]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402

N_FRAMES = 3000
N_BACKGROUND = 200  # dense:N: 216 RVs, ~2,160 frames per second of data
SKIP_S = 2.0
LATENCY_US = 2000
SEED = "bench-rx-path"


def make_frames(n: int, background: int, skip_s: float):
    """(wire frames, receive Time64 of each, fraction with a certificate, the PKI, one
    certificate-signed message per pseudonym) of ``n`` signed WSMP frames as the RVE
    sends them (module docstring)."""
    from catc.channel import ChannelConfig
    from catc.j2735 import encode_frame
    from catc.replay import plan
    from catc.security import make_pki, sign_bsm, unix_to_time32, unix_to_time64
    from hil.datasets import load_table
    from hil.pki import LoadedPki
    from rve.framing import encode_event
    from rve.signing import Signer

    the_plan = plan(load_table(f"dense:{background}:scenario:highway-braking", None),
                    ChannelConfig())
    vehicles = list(the_plan.vehicles)
    now = time.time()
    pki = make_pki(len(vehicles), start_time32=unix_to_time32(now) - 3600,
                   duration_s=7 * 86400, seed=SEED)
    loaded = LoadedPki(Path("<memory>"), pki.root.raw, pki.aa.raw,
                       tuple((p.raw, p.key) for p in pki.pseudonyms))
    signer = Signer(loaded, len(vehicles), vehicles.index(the_plan.host_id))
    frames: list[bytes] = []
    rx_us: list[int] = []
    with_cert = 0
    for ev in the_plan.events:
        if ev["host"] or ev["dropped"]:
            continue
        t = float(ev["t"])
        if t < skip_s:
            signer.decide(int(ev["vehicle"]), t)  # what the RVE decided then, unsigned
            continue
        before = signer.counts["with_certificate"]
        gen_unix = now - 60.0 + t
        data, _ = encode_event(ev, the_plan, "wsmp", signer, gen_unix, None)
        with_cert += signer.counts["with_certificate"] - before
        frames.append(data)
        rx_us.append(unix_to_time64(gen_unix) + LATENCY_US)
        if len(frames) == n:
            break
    if len(frames) < n:
        raise SystemExit(f"rx_path: only {len(frames)} RV frames after {skip_s:g} s")
    frames_of_warmup = encode_frame(the_plan.bsm(the_plan.events[0]))
    # what the OBU heard before: every pseudonym's certificate once (signed ahead of the
    # timed frames, at the first one's receive time)
    warm = [sign_bsm(frames_of_warmup, p.key, p.raw, rx_us[0] - LATENCY_US - 1,
                     include_cert=True) for p in pki.pseudonyms]
    return frames, rx_us, with_cert / n, pki, warm


def best_us(fn: Callable[[], object], n: int, repeat: int) -> float:
    """Best µs per frame of ``repeat`` timed calls of ``fn`` (one pass over ``n`` frames
    each), after one untimed call."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best / n * 1e6


def measure(n: int, background: int, skip_s: float, repeat: int, profile: bool) -> dict:
    from catc.j2735 import decode_frame, open_envelope
    from catc.security import Verifier

    frames, rx_us, cert_share, pki, warm = make_frames(n, background, skip_s)
    verifier = Verifier([pki.root.raw], certificates=[pki.aa.raw])
    for m in warm:  # the chains, cached as in a running OBU
        verifier.check(m, rx_us[0])
    pairs = list(zip(frames, rx_us, strict=True))
    envelopes = [open_envelope(d) for d in frames]
    checked = [verifier.check(u, now) for (_, u), now in zip(envelopes, rx_us, strict=True)]
    bad = [c.reason for c in checked if not hasattr(c, "tbs_hash")]
    if bad:
        raise SystemExit(f"rx_path: {len(bad)} frames fail the checks: {sorted(set(bad))}")
    opened = [(u, now) for (_, u), now in zip(envelopes, rx_us, strict=True)]
    inner = [f for f, _ in envelopes]
    check = verifier.check

    def parse() -> None:
        for d in frames:
            open_envelope(d)

    def checks() -> None:
        for u, now in opened:
            check(u, now)

    def decode() -> None:
        for f in inner:
            decode_frame(f)

    def all_three() -> None:
        for d, now in pairs:
            frame, u = open_envelope(d)
            check(u, now)
            decode_frame(frame)

    stages = {"open_envelope": parse, "Verifier.check": checks, "decode_frame": decode,
              "all three": all_three}
    rows = []
    for name, fn in stages.items():
        us = best_us(fn, n, repeat)
        rows.append({"stage": name, "us_per_frame": us, "frames_per_s": 1e6 / us,
                     "core_pct_at_10k": us * 10_000 / 1e6 * 100})
    result = {"rows": rows, "frames": n, "repeat": repeat, "certificate_share": cert_share,
              "octets_mean": sum(map(len, frames)) / n, "background": background,
              "python": platform.python_version(), "machine": platform.machine()}
    if profile:
        result["profile"] = profile_text(all_three)
    return result


def profile_text(fn: Callable[[], object], top: int = 25) -> str:
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    out = io.StringIO()
    pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(top)
    return out.getvalue()


def print_table(result: dict, rows: Sequence[dict]) -> None:
    print(f"OBU receive path before ECDSA: {result['frames']:,} signed WSMP frames "
          f"(mean {result['octets_mean']:.0f} octets, {result['certificate_share']:.0%} with "
          f"a certificate), best of {result['repeat']} passes, Python {result['python']}")
    print(f"{'stage':<16} {'µs/frame':>9} {'frames/s':>10} {'% core at 10k/s':>16}")
    for r in rows:
        print(f"{r['stage']:<16} {r['us_per_frame']:>9.2f} {r['frames_per_s']:>10,.0f} "
              f"{r['core_pct_at_10k']:>16.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--frames", type=int, default=N_FRAMES,
                    help="distinct frames (default %(default)s)")
    ap.add_argument("--background", type=int, default=N_BACKGROUND,
                    help="dense:N background vehicles (default %(default)s)")
    ap.add_argument("--skip", type=float, default=SKIP_S,
                    help="data seconds skipped at the start (default %(default)s)")
    ap.add_argument("--repeat", type=int, default=7, help="timed passes (default 7)")
    ap.add_argument("--profile", action="store_true",
                    help="also print the cProfile of the three stages in a row")
    args = ap.parse_args(argv)
    result = measure(args.frames, args.background, args.skip, args.repeat, args.profile)
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print_table(result, result["rows"])
    if args.profile:
        print(result["profile"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
