"""IEEE 1609.2 signing and verification throughput on one core, next to ``openssl speed``.

What is timed, on real BSMs (the first 200 RV frames of ``scenario:highway-braking``,
UPER MessageFrames as ``rve run`` sends them) and a seeded test PKI (``catc.security``:
root CA, AA, pseudonyms, all explicit P-256 certificates):

* ``sign_bsm`` with a ``digest`` signer (HashedId8; most BSMs) and with the whole
  ``certificate`` (about once a second per vehicle), one pseudonym; and with a digest
  signer and 500 pseudonyms signing in turn, as the RVE signs at 500 RVs (every
  vehicle's key and certificate in turn, nothing repeats within 500 messages);
* ``Verifier.verify`` of a digest-signed BSM whose signer is cached (the common case: one
  ECDSA verification);
* ``Verifier.verify`` of a certificate-signed BSM whose certificate is already cached
  (parsing the certificate, then one ECDSA verification);
* first-time chain verification: every message from a new pseudonym (200 of them, the
  AA already verified), so the verifier checks the pseudonym certificate under the AA
  and then the message: two ECDSA verifications each.  Each pass starts a new
  ``Verifier``, made outside the timing;
* ``Verifier.verify`` of a copy of a message it accepted: refused as ``replay`` from its
  replay cache, before the chain and ECDSA (issue 28);
* the replay cache alone (``catc.security.ReplayCache``): ``seen`` then ``add`` of a
  hash, the cache full at its cap of 200,000 (each add evicts the oldest), the per-frame
  cost that every accepted message pays; and the memory the full cache takes
  (tracemalloc);
* ``catc.j2735.ieee1609.build_signed`` alone (the COER of a digest-signed message around
  a given signature, no cryptography) and ``unwrap`` alone (parsing), both signer kinds:
  what the 1609.2 encoding adds to the ECDSA operations;
* raw ECDSA P-256 sign and verify of a 32-octet digest through ``cryptography``, the
  library ``catc.security`` calls: the floor of the rows above in this process.  Signing
  is timed with a random k (as ``openssl speed``) and, when ``sign_bsm`` signs
  deterministically (RFC 6979, cryptography >= 44 on OpenSSL >= 3.2), with that k too.

Each figure is the best pass of ``--seconds`` of passes over the messages, after one
untimed pass.  The peer is ``openssl speed -seconds N ecdsap256`` (the system OpenSSL's
hand-optimised P-256, C, no Python), run in the same invocation on the same core
(the process pins itself and the child to one CPU); the table gives ops/s, µs/op and
the ratio ours / openssl against its sign/s or verify/s.  When the ``openssl`` binary is
missing (or ``--no-peer``), its rows are skipped with the reason.

    python bench/security.py [--json] [--seconds S] [--no-peer]

Target (issue 16): signatures/s and verifications/s on one core next to
``openssl speed ecdsap256``.
"""

from __future__ import annotations

import os

# One core: nothing here is multi-threaded, but keep any BLAS from spinning up threads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402

N_MESSAGES = 200
N_VEHICLES = 500  # the round-robin signing row: as the RVE signs at 500 RVs
N_REPLAYS = 200_000  # catc.security.Verifier's default replay cache cap
SEED = "bench-security"

# OpenSSL 3.x: "256 bits ecdsa (nistp256)   0.0000s   0.0001s  41758.0  12791.0"
# (sign time, verify time, sign/s, verify/s); with -mr: "+F4:<n>:256:<sign/s>:<verify/s>".
_TABLE_LINE = re.compile(r"^\s*256 bits ecdsa \(nistp256\)\s+\S+s\s+\S+s\s+([\d.]+)\s+([\d.]+)",
                         re.MULTILINE)
_MR_LINE = re.compile(r"^\+F4:\d+:256:([\d.]+):([\d.]+)", re.MULTILINE)


def pin_one_core() -> int | None:
    """Pin this process (and its children, openssl) to one CPU; the CPU, or None."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    return cpu


def best_rate(fn: Callable, items: Sequence, seconds: float,
              setup: Callable[[], object] | None = None) -> float:
    """Best ops/s of passes over ``items`` (``fn(item)`` or ``fn(state, item)`` with a
    ``setup()`` state made afresh, untimed, before each pass) during ``seconds`` of
    passes, after one untimed pass."""
    def one_pass() -> float:
        state = setup() if setup is not None else None
        t0 = time.perf_counter()
        if setup is None:
            for x in items:
                fn(x)
        else:
            for x in items:
                fn(state, x)
        return time.perf_counter() - t0

    one_pass()
    best, spent = float("inf"), 0.0
    while spent < seconds or best == float("inf"):
        dt = one_pass()
        best, spent = min(best, dt), spent + dt
    return len(items) / best


def real_frames(n: int) -> list[bytes]:
    """UPER MessageFrames of the first ``n`` RV events of the default scenario."""
    from catc.channel import ChannelConfig
    from catc.j2735 import encode_frame
    from catc.replay import plan
    from hil.datasets import load_table

    the_plan = plan(load_table("scenario:highway-braking", None), ChannelConfig())
    events = [ev for ev in the_plan.events if not ev["host"]][:n]
    return [encode_frame(the_plan.bsm(ev)) for ev in events]


def measure_ours(seconds: float) -> tuple[dict[str, dict], dict]:
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec, utils

    from catc.j2735.ieee1609 import PSID_BSM, build_signed, unwrap
    from catc.security import (
        ReplayCache,
        Verifier,
        make_pki,
        sign_bsm,
        unix_to_time32,
        unix_to_time64,
    )

    frames = real_frames(N_MESSAGES)
    now_unix = time.time()
    now_us = unix_to_time64(now_unix)
    gen_us = [now_us - 50_000 - 1000 * i for i in range(len(frames))]  # fresh: < 2 s old
    # the same frame at the same generationTime is the same ToBeSignedData whoever signs
    # it, and the verifier refuses a second one as a replay: every message that one
    # verifier sees gets its own generationTime (certificate rows 300 µs earlier, the
    # warm-up messages 700 µs)
    cert_gen = [g - 300 for g in gen_us]
    # pseudonym 0 signs the cached rows; 1..N_MESSAGES are the chain row's new ones; the
    # last one gets the AA verified before that row is timed; all sign in turn in one row
    pki = make_pki(max(N_MESSAGES + 2, N_VEHICLES), start_time32=unix_to_time32(now_unix) - 3600,
                   duration_s=7 * 86400, seed=SEED)
    me = pki.pseudonyms[0]
    digest_msgs = [sign_bsm(f, me.key, me.raw, g, include_cert=False)
                   for f, g in zip(frames, gen_us, strict=True)]
    cert_msgs = [sign_bsm(f, me.key, me.raw, g, include_cert=True)
                 for f, g in zip(frames, cert_gen, strict=True)]
    new_msgs = [sign_bsm(f, p.key, p.raw, g, include_cert=True)
                for f, p, g in zip(frames, pki.pseudonyms[1:N_MESSAGES + 1], gen_us, strict=True)]
    warm = sign_bsm(frames[0], pki.pseudonyms[-1].key, pki.pseudonyms[-1].raw,
                    gen_us[0] - 700, include_cert=True)
    my_warm = sign_bsm(frames[0], me.key, me.raw, gen_us[0] - 700, include_cert=True)

    def cached_verifier() -> Verifier:
        v = Verifier([pki.root.raw], certificates=[pki.aa.raw])
        assert v.verify(my_warm, now_us).ok  # the signer's certificate, once
        return v

    def replaying_verifier() -> Verifier:
        v = cached_verifier()
        assert all(v.verify(m, now_us).ok for m in digest_msgs)  # accepted once
        return v

    def fresh_verifier() -> Verifier:
        v = Verifier([pki.root.raw], certificates=[pki.aa.raw])
        assert v.verify(warm, now_us).ok  # verifies the AA; the timed pseudonyms are new
        return v

    # every message must verify, or the timing would be of a failure path
    v = cached_verifier()
    assert all(v.verify(m, now_us).ok for m in digest_msgs + cert_msgs)
    v = fresh_verifier()
    checks = v.cert_checks
    assert all(v.verify(m, now_us).ok for m in new_msgs)
    chain_ecdsa = 1 + (v.cert_checks - checks) / len(new_msgs)
    v = replaying_verifier()
    assert {v.verify(m, now_us).reason for m in digest_msgs} == {"replay"}

    def verify_ok(verifier: Verifier, m: bytes) -> None:
        verifier.verify(m, now_us)

    key = me.key
    to_sign = list(zip(frames, gen_us, strict=True))
    rows: dict[str, dict] = {}

    def row(name: str, kind: str, rate: float, ecdsa: float, what: str) -> None:
        rows[name] = {"kind": kind, "ops_per_s": rate, "us_per_op": 1e6 / rate,
                      "ecdsa_per_op": ecdsa, "what": what}

    row("sign_digest", "sign",
        best_rate(lambda fg: sign_bsm(fg[0], key, me.raw, fg[1], include_cert=False),
                  to_sign, seconds),
        1, "sign_bsm, digest signer")
    row("sign_certificate", "sign",
        best_rate(lambda fg: sign_bsm(fg[0], key, me.raw, fg[1], include_cert=True),
                  to_sign, seconds),
        1, "sign_bsm, certificate signer")
    in_turn = [(frames[k % len(frames)], gen_us[k % len(frames)], p)
               for k, p in enumerate(pki.pseudonyms[:N_VEHICLES])]
    row("sign_digest_round_robin", "sign",
        best_rate(lambda fgp: sign_bsm(fgp[0], fgp[2].key, fgp[2].raw, fgp[1],
                                       include_cert=False), in_turn, seconds),
        1, f"sign_bsm, digest signer, {N_VEHICLES} pseudonyms in turn")
    row("verify_digest_cached", "verify",
        best_rate(verify_ok, digest_msgs, seconds, cached_verifier),
        1, "verify, digest signer, certificate cached")
    row("verify_certificate_cached", "verify",
        best_rate(verify_ok, cert_msgs, seconds, cached_verifier),
        1, "verify, certificate signer, already cached")
    row("verify_new_pseudonym", "verify",
        best_rate(verify_ok, new_msgs, seconds, fresh_verifier),
        chain_ecdsa, f"verify, new pseudonym each ({N_MESSAGES}): chain check")
    row("verify_replay", "replay",
        best_rate(verify_ok, digest_msgs, seconds, replaying_verifier),
        0, "verify, a copy of an accepted message: replay")
    full, new_keys, until = replay_cache_full(now_us)

    def seen_then_add(replays: ReplayCache, key: bytes) -> None:
        if not replays.seen(key, now_us):
            replays.add(key, until, now_us)

    row("replay_cache_add", "cache", best_rate(seen_then_add, new_keys, seconds, full), 0,
        f"replay cache seen + add, full ({N_REPLAYS:,})")
    signature = digest_msgs[0][-64:]
    row("build_digest", "encode",
        best_rate(lambda fg: build_signed(fg[0], psid=PSID_BSM, generation_time_us=fg[1],
                                          signer=("digest", me.hashed_id8),
                                          signature=signature), to_sign, seconds),
        0, "build_signed alone (COER), digest signer")
    row("unwrap_digest", "parse", best_rate(unwrap, digest_msgs, seconds), 0,
        "unwrap alone, digest signer")
    row("unwrap_certificate", "parse", best_rate(unwrap, cert_msgs, seconds), 0,
        "unwrap alone, certificate signer")

    # the library floor: one prehashed ECDSA P-256 operation through cryptography
    algorithm = ec.ECDSA(utils.Prehashed(hashes.SHA256()))
    digests = [os.urandom(32) for _ in range(N_MESSAGES)]
    public = key.public_key()
    signatures = {d: key.sign(d, algorithm) for d in digests}
    row("raw_sign", "sign", best_rate(lambda d: key.sign(d, algorithm), digests, seconds), 1,
        "raw ECDSA sign (cryptography)")
    # sign_bsm signs deterministically (RFC 6979) when the library can: same input, same
    # octets.  Time that mode too, as sign_bsm uses it (openssl speed draws k at random).
    deterministic = sign_bsm(to_sign[0][0], key, me.raw, to_sign[0][1], include_cert=False) \
        == sign_bsm(to_sign[0][0], key, me.raw, to_sign[0][1], include_cert=False)
    if deterministic:
        rfc6979 = ec.ECDSA(utils.Prehashed(hashes.SHA256()), deterministic_signing=True)
        row("raw_sign_rfc6979", "sign",
            best_rate(lambda d: key.sign(d, rfc6979), digests, seconds), 1,
            "raw ECDSA sign, RFC 6979 k (as sign_bsm)")
    row("raw_verify", "verify",
        best_rate(lambda d: public.verify(signatures[d], d, algorithm), digests, seconds), 1,
        "raw ECDSA verify (cryptography)")

    from cryptography.hazmat.backends.openssl import backend

    sizes = {"replay_cache_mb_full": replay_cache_mb(now_us),
             "frame_octets": sum(map(len, frames)) / len(frames),
             "signed_digest_octets": sum(map(len, digest_msgs)) / len(digest_msgs),
             "signed_certificate_octets": sum(map(len, cert_msgs)) / len(cert_msgs),
             "cryptography_openssl": backend.openssl_version_text(),
             "sign_bsm_deterministic": deterministic}
    return rows, sizes


def replay_cache_full(now_us: int) -> tuple[Callable[[], object], list[bytes], int]:
    """A maker of ``ReplayCache``s at their cap, full of live SHA-256 hashes; as many new
    hashes to add to one (each add evicts the oldest); their end of life."""
    import hashlib

    from catc.security import ReplayCache

    until = now_us + 3_000_000
    old = [hashlib.sha256(i.to_bytes(8, "big")).digest() for i in range(N_REPLAYS)]
    new = [hashlib.sha256(b"new" + i.to_bytes(8, "big")).digest() for i in range(N_REPLAYS)]

    def full() -> ReplayCache:
        replays = ReplayCache(N_REPLAYS)
        for key in old:
            replays.add(key, until, now_us)
        return replays

    return full, new, until


def replay_cache_mb(now_us: int) -> float:
    """MB (10^6 octets) that a full ``ReplayCache`` holds, as ``tracemalloc`` counts it:
    as the verifier fills it, a new hash and a new end of life per entry."""
    import hashlib
    import tracemalloc

    from catc.security import ReplayCache

    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    replays = ReplayCache(N_REPLAYS)
    for i in range(replays.max_entries):
        replays.add(hashlib.sha256(i.to_bytes(8, "big")).digest(), now_us + 3_000_000 + i,
                    now_us)
    size = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    assert len(replays) == replays.max_entries
    return size / 1e6


def measure_openssl(seconds: float, no_peer: bool) -> dict:
    """sign/s and verify/s of ``openssl speed ecdsap256``, or {"skipped": reason}."""
    if no_peer:
        return {"skipped": "--no-peer"}
    exe = shutil.which("openssl")
    if exe is None:
        return {"skipped": "no openssl binary on PATH"}
    secs = max(1, round(seconds))
    cmd = [exe, "speed", "-seconds", str(secs), "ecdsap256"]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60 + 4 * secs)
    except (OSError, subprocess.TimeoutExpired) as err:
        return {"skipped": f"{' '.join(cmd)} failed: {err}"}
    text = out.stdout + out.stderr
    m = _TABLE_LINE.search(text) or _MR_LINE.search(text)
    if out.returncode != 0 or m is None:
        return {"skipped": f"{' '.join(cmd)}: exit {out.returncode}, no ecdsa (nistp256) "
                           f"line in: {text.strip()[-200:]!r}"}
    version = subprocess.run([exe, "version"], capture_output=True, text=True).stdout
    version = version.split(" (Library")[0].strip()
    return {"sign_per_s": float(m.group(1)), "verify_per_s": float(m.group(2)),
            "command": " ".join(["openssl", *cmd[1:]]), "version": version}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--seconds", type=float, default=3.0,
                    help="time per figure (default 3; openssl speed gets it rounded, >= 1)")
    ap.add_argument("--no-peer", action="store_true", help="skip openssl speed")
    args = ap.parse_args(argv)

    cpu = pin_one_core()
    peer = measure_openssl(args.seconds, args.no_peer)
    rows, sizes = measure_ours(args.seconds)
    for r in rows.values():
        ref = peer.get(f"{r['kind']}_per_s")
        r["openssl_per_s"] = ref
        r["ratio_to_openssl"] = r["ops_per_s"] / ref if ref else None

    result = {
        "signatures_per_s": rows["sign_digest"]["ops_per_s"],
        "verifications_per_s": rows["verify_digest_cached"]["ops_per_s"],
        "openssl": peer,
        "rows": rows,
        "messages": N_MESSAGES,
        "seconds": args.seconds,
        "cpu": cpu,
        "python": platform.python_version(),
        "machine": platform.machine(),
        **sizes,
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0

    print(f"IEEE 1609.2 ECDSA P-256 on one core (CPU {cpu}), real BSMs "
          f"({sizes['frame_octets']:.0f} octets; signed {sizes['signed_digest_octets']:.0f} "
          f"digest / {sizes['signed_certificate_octets']:.0f} certificate), best pass of "
          f"{args.seconds:g} s, Python {platform.python_version()}, "
          f"{sizes['cryptography_openssl']}")
    print(f"{'operation':<48} {'ECDSA':>5} {'ops/s':>9} {'µs/op':>8} {'openssl/s':>10} "
          f"{'ours/openssl':>12}")
    for r in rows.values():
        ref = r["openssl_per_s"]
        ref_s = f"{ref:>10,.0f}" if ref else f"{'-':>10}"
        ratio = f"{r['ratio_to_openssl']:>12.2f}" if ref else f"{'-':>12}"
        print(f"{r['what']:<48} {r['ecdsa_per_op']:>5.3g} {r['ops_per_s']:>9,.0f} "
              f"{r['us_per_op']:>8.1f} {ref_s} {ratio}")
    print(f"replay cache full ({N_REPLAYS:,} hashes): {sizes['replay_cache_mb_full']:.1f} MB")
    if "skipped" in peer:
        print(f"openssl speed ecdsap256: skipped ({peer['skipped']})")
    else:
        print(f"{peer['command']} ({peer['version']}): sign {peer['sign_per_s']:,.0f}/s "
              f"({1e6 / peer['sign_per_s']:.1f} µs), verify {peer['verify_per_s']:,.0f}/s "
              f"({1e6 / peer['verify_per_s']:.1f} µs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
