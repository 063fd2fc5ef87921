"""The OBU's receive fast paths against the general code they stand in for.

* :func:`catc.j2735.ieee1609.fast_open` (inside :func:`catc.j2735.open_envelope`) against
  :func:`catc.j2735.open_envelope_general`: the same frame and the same
  :class:`Unwrapped`, field by field with the types, or the same :class:`DecodeError`
  (reason and message);
* the core-only branch of :func:`catc.j2735.decode_frame` against the BitReader path
  (the branch switched off by patching its size threshold): the same BSM (its repr, so
  enum types count) or the same error;
* :meth:`catc.security.Verifier.check` against :func:`_reference_check`, the check of
  commit 9666ef7 copied here unchanged as the oracle: the same Verdict or Checked.

On frames as ``rve run --sign`` sends them (``rve.signing.Signer``: digest signers and
certificates, WSMP and bare 1609.2 framing), hand-made variants of each field the fast
path looks at, the real signed record of the ODE vectors (skipped when absent), every
truncation of a few frames, and a few thousand seeded random byte flips.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import random
from functools import cache

import pytest

from catc.errors import DecodeError
from catc.j2735 import decode_frame, open_envelope, open_envelope_general
from catc.j2735.ieee1609 import (
    Unwrapped,
    build_signed,
    fast_open,
    remember,
    unwrap,
    wrap_unsecured,
    wrap_wsmp,
)
from catc.j2735.ieee1609 import _fast as fast_module
from catc.j2735.uper import _frame as frame_module
from catc.security import (
    P256_ORDER,
    Checked,
    Verdict,
    Verifier,
    make_pki,
    sign_bsm,
    time64_to_unix,
)
from tests.conftest import shared_path

NOW = 636_913_807_899_000  # Time64, as in tests/test_security.py
START = NOW // 1_000_000 - 86400
FLIPS = 3000
SEED = 20261206


@cache
def _pki():
    return make_pki(17, start_time32=START, duration_s=7 * 86400, seed=b"catc-rx-fastpath")


@cache
def _rve_frames() -> tuple[tuple[bytes, ...], tuple[bytes, ...]]:
    """(WSMP frames, bare 1609.2 frames) of the first 3 s of scenario:highway-braking as
    ``rve run --sign`` sends them, host frames (unsecured) included."""
    from catc.channel import ChannelConfig
    from catc.replay import plan
    from hil.datasets import load_table
    from hil.pki import LoadedPki
    from rve.framing import encode_event
    from rve.signing import Signer

    the_plan = plan(load_table("scenario:highway-braking", None), ChannelConfig())
    vehicles = list(the_plan.vehicles)
    pki = _pki()
    loaded = LoadedPki(None, pki.root.raw, pki.aa.raw,
                       tuple((p.raw, p.key) for p in pki.pseudonyms))
    out: dict[str, list[bytes]] = {"wsmp": [], "1609": []}
    for framing, frames in out.items():
        signer = Signer(loaded, len(vehicles), vehicles.index(the_plan.host_id))
        for ev in the_plan.events:
            if float(ev["t"]) >= 3.0:
                break
            data, _ = encode_event(ev, the_plan, framing, signer,
                                   time64_to_unix(NOW) + float(ev["t"]), None)
            if data is not None:
                frames.append(data)
    return tuple(out["wsmp"]), tuple(out["1609"])


def _fields(u: Unwrapped | None) -> object:
    if u is None:
        return None
    assert type(u) is Unwrapped
    return tuple((f.name, type(getattr(u, f.name)), getattr(u, f.name))
                 for f in dataclasses.fields(u))


def _opened(fn, data: bytes) -> tuple:
    try:
        frame, u = fn(data)
    except DecodeError as err:
        return ("error", err.reason, str(err))
    return ("ok", type(frame), frame, _fields(u))


def _same_open(data: bytes) -> bool:
    """``open_envelope`` and the general parser agree on ``data``, and so does
    ``fast_open`` when it takes it; whether it took it."""
    fast = fast_open(data)
    general = _opened(open_envelope_general, data)
    assert _opened(open_envelope, data) == general, data.hex()
    if fast is not None:
        assert general[0] == "ok" and general[3] == _fields(fast), data.hex()
    return fast is not None


def _decoded(frame: bytes) -> tuple:
    try:
        bsm = decode_frame(frame)
    except DecodeError as err:
        return ("error", err.reason, str(err))
    return ("ok", repr(bsm), bsm)


def _same_decode(frames: list[bytes], monkeypatch: pytest.MonkeyPatch) -> int:
    """The core-only branch and the BitReader path give the same for every frame; how
    many frames the branch took."""
    taken = []
    with monkeypatch.context() as m:
        core_bsm = frame_module.core_bsm
        m.setattr(frame_module, "core_bsm", lambda c: taken.append(1) or core_bsm(c))
        fast = [_decoded(f) for f in frames]
    with monkeypatch.context() as m:
        m.setattr(frame_module, "_HEAD_OCTETS", 1 << 30)  # the BitReader path only
        general = [_decoded(f) for f in frames]
    for f, a, b in zip(frames, fast, general, strict=True):
        assert a == b, f.hex()
    return len(taken)


_HALF_ORDER = P256_ORDER // 2


def _reference_canonical(u: Unwrapped) -> bool:
    sig = u.signature
    if u.signature_r_form != "x-only" or sig is None or len(sig) != 64:
        return False
    r, s = int.from_bytes(sig[:32], "big"), int.from_bytes(sig[32:], "big")
    return 0 < r < P256_ORDER and 0 < s <= _HALF_ORDER


def _reference_check(self: Verifier, u: Unwrapped, now_us: int) -> Verdict | Checked:
    """``Verifier.check`` of commit 9666ef7 (on an Unwrapped), the oracle."""
    from catc.security._crypto import sha256

    if u.security != "signed":
        return Verdict(False, "unsigned", u.frame)

    def fail(reason: str) -> Verdict:
        return Verdict(False, reason, u.frame, u.signer_digest)

    tbs_hash = sha256(u.tbs_data)
    if self.replays is not None and self.replays.seen(tbs_hash, now_us):
        return fail("replay")
    if u.unsupported:
        return fail("unsupported")
    if u.signed_layers > 1:
        return fail("nested")
    if u.wsmp_psid is not None and u.wsmp_psid != self.psid:
        return fail("wsmp-psid")
    if u.signer_kind == "digest":
        signer = self._lookup(u.signer_digest)
        if signer is None:
            return fail("unknown-signer")
    elif u.signer_kind == "certificate":
        signer = self._chain(u.signer_certs)
        if signer is None:
            return fail("chain")
    else:
        return Verdict(False, "unknown-signer", u.frame, None)
    if u.psid != self.psid or self.psid not in signer.cert.app_psids:
        return fail("wrong-psid")
    generation, expiry = u.generation_time_us, u.expiry_time_us
    for instant in (now_us, generation):
        if instant is not None and not (
            signer.not_before <= instant // 1_000_000 < signer.not_after
        ):
            return fail("expired")
    if (generation is None or now_us - generation > self.max_age_us
            or generation - now_us > self.max_future_us):
        return fail("stale")
    if expiry is not None and (expiry < now_us or expiry < generation):
        return fail("message-expired")
    if self.canonical_only and not _reference_canonical(u):
        return fail("non-canonical")
    return Checked(u, tbs_hash, signer, now_us, generation)


def _verifiers() -> list[tuple[Verifier, Verifier]]:
    """(for the reference, for the code) pairs, alike: strict and lax; every pseudonym
    known; a message of pseudonym 0 at NOW accepted (so that its copy is a replay)."""
    pki = _pki()
    pairs = []
    for strict in (True, False):
        pair = []
        for _ in range(2):
            v = Verifier([pki.root.raw], certificates=[pki.aa.raw], canonical_only=strict)
            for p in pki.pseudonyms:
                v.check(sign_bsm(b"\x00\x14\x00", p.key, p.raw, NOW - 5, include_cert=True),
                        NOW)
            assert v.verify(_variants()["digest"], NOW + 1000).ok
            pair.append(v)
        pairs.append(tuple(pair))
    return pairs


_INSTANTS = (2_000, 1_500_000, 2_500_000, -1_200_000, 8 * 86400 * 10**6)


def _same_check(pairs, u: Unwrapped) -> set[str]:
    """Verifier.check and the reference agree on ``u`` at several receive times; the
    reasons seen."""
    reasons = set()
    base = u.generation_time_us if u.generation_time_us is not None else NOW
    for ref, new in pairs:
        for dt in _INSTANTS:
            a, b = _reference_check(ref, u, base + dt), new.check(u, base + dt)
            assert type(a) is type(b) and a == b, (u, dt)
            reasons.add(a.reason if isinstance(a, Verdict) else "checked")
    return reasons


def _checked(datas) -> tuple[list[bytes], set[str]]:
    """The frames of ``datas`` that open, and the reasons :func:`_same_check` found for
    them (the fast and the previous ``check`` agreeing on each)."""
    pairs = _verifiers()
    frames, reasons = [], set()
    for d in datas:
        try:
            frame, u = open_envelope(d)
        except DecodeError:
            continue
        frames.append(frame)
        if u is not None:
            reasons |= _same_check(pairs, u)
    return frames, reasons


@cache
def _variants() -> dict[str, bytes]:
    """Hand-made frames, one per form the fast path looks at (module docstring of
    catc.j2735.ieee1609._fast): taken, or left to the general parser."""
    pki = _pki()
    p = pki.pseudonyms[0]
    wsmp, _ = _rve_frames()
    frame = open_envelope_general(wsmp[-1])[0]
    sig = sign_bsm(frame, p.key, p.raw, NOW, include_cert=False)[-64:]
    r, s = sig[:32], int.from_bytes(sig[32:], "big")

    def signed(signer=("digest", p.hashed_id8), signature=sig, **kw) -> bytes:
        return build_signed(kw.pop("frame", frame), psid=kw.pop("psid", 0x20),
                            generation_time_us=kw.pop("gen", NOW + 7), signer=signer,
                            signature=signature)

    digest = sign_bsm(frame, p.key, p.raw, NOW, include_cert=False)
    cert = sign_bsm(frame, p.key, p.raw, NOW + 1, include_cert=True)
    foreign = make_pki(1, start_time32=START, duration_s=7 * 86400, seed=b"x").pseudonyms[0]
    h = 7 + len(frame)  # headerInfo: after 03 81 00 40 03 80 L frame
    out = {
        "digest": digest,
        "certificate": cert,
        "wsmp digest": wrap_wsmp(digest),
        "wsmp certificate": wrap_wsmp(cert),
        "wsmp psid 0x21": wrap_wsmp(digest, 0x21),
        "wsmp psid 0x80": wrap_wsmp(digest, 0x80),  # two-octet p-encoding: general
        "wsmp trailing": wrap_wsmp(digest) + b"\x00" * 4,
        "wsmp payload trailing": wrap_wsmp(digest + b"\x01\x02"),
        "trailing": digest + b"\x01\x02",
        "certificate trailing": cert + b"\x01\x02",
        "psid 0x21": signed(psid=0x21),
        "psid 0x8000": signed(psid=0x8000),
        "psid 0": signed(psid=0),
        "high s": signed(signature=r + (P256_ORDER - s).to_bytes(32, "big")),
        "r zero": signed(signature=bytes(32) + sig[32:]),
        "r order": signed(signature=P256_ORDER.to_bytes(32, "big") + sig[32:]),
        "s zero": signed(signature=r + bytes(32)),
        "frame 128": signed(frame=frame + bytes(128 - len(frame))),
        "frame 300": signed(frame=frame + bytes(300 - len(frame))),
        "frame 0": signed(frame=b""),
        "self signer": signed(signer=("self", None)),
        "two certificates": signed(signer=("certificate", [p.raw, pki.aa.raw])),
        "unknown digest": signed(signer=("digest", bytes(8))),
        "future": signed(gen=NOW + 10**9),
        "nested": b"\x03\x81\x00\x40" + digest + digest[h:],
        "foreign certificate": sign_bsm(frame, foreign.key, foreign.raw, NOW, include_cert=True),
        "unsecured": wrap_unsecured(frame),
        "wsmp unsecured": wrap_wsmp(wrap_unsecured(frame)),
        "long length 0x81": digest[:6] + b"\x81" + digest[6:],
        "long length 0x82": digest[:6] + b"\x82\x00" + digest[6:],
        "long length 0x83": digest[:6] + b"\x83\x00\x00" + digest[6:],
    }
    # headerInfo with an expiryTime (preamble 0x60): the general parser's
    out["expiry"] = digest[:h] + b"\x60" + digest[h + 1:h + 11] + NOW.to_bytes(8, "big") \
        + digest[h + 11:]
    out["psid empty"] = digest[:h + 1] + b"\x00" + digest[h + 3:] + b"\x00"  # out-of-range
    out["psid 9 octets"] = digest[:h + 1] + b"\x09" + bytes(8) + digest[h + 2:]
    out["r compressed"] = digest[:-66] + b"\x80\x82" + digest[-64:]
    out["brainpool"] = digest[:-66] + b"\x81\x80" + digest[-64:]
    out["sha384"] = digest[:2] + b"\x01" + digest[3:]
    return out


# --- tests ----------------------------------------------------------------------------------


def test_rve_frames_take_the_fast_path_and_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    wsmp, bare = _rve_frames()
    frames = wsmp + bare
    for data in frames:  # what an OBU has heard: every certificate once
        open_envelope_general(data)
    taken = sum(_same_open(d) for d in frames)
    signed = [d for d in frames if open_envelope_general(d)[1].security == "signed"]
    kinds = {open_envelope_general(d)[1].signer_kind for d in signed}
    assert kinds == {"digest", "certificate"}
    assert taken == len(signed) > 700  # every signed frame of the RVE: fast
    inner = [open_envelope(d)[0] for d in frames]
    assert _same_decode(inner, monkeypatch) == len(inner)
    pairs = _verifiers()
    reasons = set()
    for d in signed:
        reasons |= _same_check(pairs, open_envelope(d)[1])
    assert {"checked", "stale", "expired"} <= reasons


def test_variants_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    variants = _variants()
    open_envelope_general(variants["certificate"])
    taken = {name for name, d in variants.items() if _same_open(d)}
    assert taken == {"digest", "certificate", "wsmp digest", "wsmp certificate",
                     "wsmp psid 0x21", "wsmp trailing", "wsmp payload trailing", "trailing",
                     "psid 0x21", "psid 0x8000", "psid 0", "high s", "r zero", "r order",
                     "s zero", "frame 128", "frame 300", "frame 0", "unknown digest",
                     "future", "long length 0x81", "long length 0x82"}
    frames, reasons = _checked(variants.values())
    assert {"checked", "replay", "unsupported", "nested", "wsmp-psid", "unknown-signer",
            "wrong-psid", "expired", "stale", "message-expired", "non-canonical",
            "unsigned"} <= reasons
    _same_decode(frames, monkeypatch)


def test_certificates_are_remembered_by_their_octets(monkeypatch: pytest.MonkeyPatch) -> None:
    cert = _variants()["wsmp certificate"]
    monkeypatch.setattr(fast_module, "_certs", type(fast_module._certs)())
    assert fast_open(cert) is None  # not seen yet: the general parser reads it
    open_envelope(cert)
    assert fast_open(cert) is not None
    monkeypatch.setattr(fast_module, "MAX_CERTIFICATES", 2)
    for p in _pki().pseudonyms[:4]:
        signed = sign_bsm(b"\x00\x14\x00", p.key, p.raw, NOW, include_cert=True)
        remember(unwrap(signed).signer_certs[0])
    assert len(fast_module._certs) == 2
    assert fast_open(cert) is None  # forgotten, the oldest first
    assert _same_open(cert) is False


def test_real_signed_record_agrees(monkeypatch: pytest.MonkeyPatch) -> None:
    doc = json.loads(shared_path("jpo-ode-bsm-vectors", "decoder-input-bsm.json").read_text())
    record = bytes.fromhex(doc["payload"]["data"]["bytes"])
    assert not _same_open(record)  # rSig compressed-y-0: the general parser's
    x_only = record[:-66] + b"\x80\x80" + record[-64:]
    assert x_only[-98:-66] == record[-98:-66]
    assert _same_open(x_only) and _same_open(wrap_wsmp(x_only))  # long frame length
    frames = [open_envelope(d)[0] for d in (record, x_only)]
    _same_decode(frames, monkeypatch)
    pairs = _verifiers()
    for d in (record, x_only, wrap_wsmp(x_only)):
        _same_check(pairs, open_envelope(d)[1])


def _bases() -> dict[str, bytes]:
    v = _variants()
    open_envelope_general(v["certificate"])
    wsmp, _ = _rve_frames()
    return {"wsmp digest": v["wsmp digest"], "wsmp certificate": v["wsmp certificate"],
            "digest": v["digest"], "certificate": v["certificate"], "rve": wsmp[-1]}


@pytest.mark.parametrize("name", ["wsmp digest", "wsmp certificate", "digest", "certificate"])
def test_every_truncation_agrees(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    data = _bases()[name]
    cuts = [data[:k] for k in range(len(data))]
    if name.startswith("wsmp"):  # the WSM's length right, the 1609.2 data cut
        body = data[5:] if data[3] & 0x80 else data[4:]
        cuts += [wrap_wsmp(body[:k]) for k in range(len(body))]
    assert not any(_same_open(d) for d in cuts)  # a cut frame is never the fast path's
    frames = []
    for d in cuts:
        with contextlib.suppress(DecodeError):
            frames.append(open_envelope(d)[0])
    _same_decode(frames, monkeypatch)


def test_random_flips_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = random.Random(SEED)
    bases = list(_bases().values())
    mutated = []
    for i in range(FLIPS):
        data = bytearray(bases[i % len(bases)])
        for _ in range(rng.choice((1, 1, 2, 3))):
            data[rng.randrange(len(data))] ^= rng.randrange(1, 256)
        mutated.append(bytes(data))
    taken = sum(_same_open(d) for d in mutated)
    assert taken > FLIPS // 3  # most flips land in the frame, the times, the signature
    frames, reasons = _checked(mutated)
    assert {"checked", "unknown-signer", "non-canonical", "stale"} <= reasons
    assert _same_decode(frames, monkeypatch) > FLIPS // 3
