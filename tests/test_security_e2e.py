"""IEEE 1609.2 between the daemons: ``rve pki init``, ``rve run --sign`` and ``obu run
--verify``, as separate processes over UDP on loopback.

* A signed run into an enforcing OBU: every frame verifies, and the legitimate vehicles'
  scores equal those of the same run unsigned.
* Frames that must not pass, sent by a second process straight to the OBU's socket:
  unsigned, signed by a PKI the OBU does not trust, a flipped signature bit, a digest
  whose certificate the OBU has never seen, a stale generation time.  Each is counted
  under its reason and dropped (enforce) or tracked with its verdict (log).
* OpenSSL, not our code, verifies the RVE's signatures on the wire: the signed octets are
  cut out of the captured frames by the lengths of the 1609.2 COER layout (stated below),
  the public key comes from ``openssl ec -pubout`` of the pseudonym's key file.
* Bad flags and trust stores: one line, exit 2.
"""

from __future__ import annotations

import hashlib
import json
import random
import re
import shutil
import socket
import subprocess
import time
from pathlib import Path

import pytest

from catc.j2735 import encode_frame
from catc.j2735.sniff import extract_frames
from catc.security import load_private_pem, sign_bsm, unix_to_time64
from hil.capture import read_rx
from hil.transport.udp import free_ports
from tests.test_obu import PY, finish, rve, score, start_obu

RUN = ("--per", "30", "--seed", "3", "--speed", "8", "--duration", "24")


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("pki") / "pki"
    out = subprocess.run([PY, "-m", "rve.cli", "pki", "init", str(d), "--vehicles", "20",
                          "--seed", "test"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    made = json.loads(out.stdout)
    assert made["pseudonyms"] == 20 and len(made["root"]) == 16
    assert (d / "root.oer").exists() and (d / "foreign" / "root.oer").exists()
    assert (d / "pseudonym-0.key.pem").stat().st_mode & 0o077 == 0  # private keys: 0600
    return d


def _counters(err: str) -> dict:
    return json.loads(err.strip().splitlines()[-1])["obu"]


def test_signed_run_verifies_every_frame_and_scores_like_the_unsigned_run(pki, tmp_path):
    signed, plain = tmp_path / "signed", tmp_path / "plain"
    ports = free_ports()
    # --collect-ms 30: on a loaded machine the signing RVE's last frames of a tick can
    # trail its host frame by more than the default 5 ms; both runs must step the same
    # frames at the same ticks for their scores to be equal
    # --verify-policy all: every frame verified on arrival, as this test means (on demand,
    # the default, steps frames unverified when the queue falls behind: no verdict then)
    obu = start_obu(signed, ports, "--predictor", "ca", "--verify", "enforce",
                    "--verify-policy", "all", "--trust", str(pki), "--collect-ms", "30")
    summary = rve(ports, *RUN, "--sign", str(pki), "--capture", str(signed))
    _, err = finish(obu)
    c = _counters(err)
    assert summary["signed"] == summary["sent"] == c["frames_rv"] == c["verify_ok"] > 0
    assert 0 < summary["with_certificate"] < summary["signed"]
    assert not {k for k in c if k.startswith("verify_") and k != "verify_ok"}
    ports = free_ports()
    obu = start_obu(plain, ports, "--predictor", "ca", "--collect-ms", "30")
    rve(ports, *RUN, "--capture", str(plain))
    finish(obu)
    a, b = score(signed), score(plain)
    assert a["security"] == {"ok": a["received"] + a["unticked"]} and a["rejected"] == 0
    assert a["received"] == a["sent"] == b["received"] and a["unticked"] == b["unticked"] == 0
    for key in ("pte95_m", "pte95_per_rv", "fcw_accuracy", "fcw", "warnings"):
        assert a[key] == b[key], key


def _frames(n: int, t0: float = 0.0) -> list[bytes]:
    """``n`` UPER BSM frames of one vehicle (the OBU tracks them if they pass)."""
    from catc.bsm import BSM

    return [encode_frame(BSM(msg_cnt=i % 128, temp_id=0x0BADCAFE, sec_mark=int(t0 * 1000
                                                                               + i * 100),
                             lat=42.28, lon=-83.74, elev=200.0, speed=10.0, heading=90.0))
            for i in range(n)]


def _send(ports: list[int], frames: list[bytes]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for f in frames:
            s.sendto(f, ("127.0.0.1", ports[0]))
            time.sleep(0.002)


def _attack_frames(pki: Path) -> dict[str, list[bytes]]:
    """Frames that an enforcing OBU must reject, by the reason it must give."""
    cert = (pki / "pseudonym-3.oer").read_bytes()
    key = load_private_pem((pki / "pseudonym-3.key.pem").read_bytes())
    foreign_cert = (pki / "foreign" / "pseudonym-0.oer").read_bytes()
    foreign_key = load_private_pem((pki / "foreign" / "pseudonym-0.key.pem").read_bytes())
    now = unix_to_time64(time.time())
    frames = _frames(5)

    def flip(data: bytes) -> bytes:
        return data[:-1] + bytes([data[-1] ^ 0x01])  # the last octet of sSig

    return {
        "unsigned": frames[:2],
        "chain": [sign_bsm(f, foreign_key, foreign_cert, now, include_cert=True)
                  for f in frames[:2]],
        "unknown-signer": [sign_bsm(f, key, cert, now, include_cert=False)
                           for f in frames[:2]],
        "stale": [sign_bsm(frames[0], key, cert, now - 60_000_000, include_cert=True)],
        "bad-signature": [flip(sign_bsm(frames[1], key, cert, now, include_cert=True))],
    }


@pytest.mark.parametrize("mode", ["enforce", "log"])
def test_frames_that_do_not_verify_are_counted_by_reason(pki, tmp_path, mode):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", mode, "--trust",
                    str(pki))
    attacks = _attack_frames(pki)  # signed now: fresh when they arrive
    _send(ports, [f for frames in attacks.values() for f in frames])
    # one host frame, so that log mode takes the tracked frames into a tick
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(_frames(1, 1.0)[0], ("127.0.0.1", ports[1]))
    _, err = finish(obu)
    c = _counters(err)
    want = {f"verify_{reason}": len(frames) for reason, frames in attacks.items()}
    assert {k: v for k, v in c.items() if k.startswith("verify_") and k not in
            ("verify_rejected", "verify_failed")} == want
    total = sum(want.values())
    assert c["verify_rejected" if mode == "enforce" else "verify_failed"] == total
    rx = read_rx(tmp_path)
    if mode == "enforce":
        assert [r["status"] for r in rx] == ["rejected"] * total
        assert sorted(r["verdict"] for r in rx) == sorted(
            reason for reason, frames in attacks.items() for _ in frames)
    else:  # tracked (or, if not due by the one host frame, recorded at exit): verdicts kept
        assert {r["status"] for r in rx} <= {"ok", "unticked"} and len(rx) == total
        assert sorted(r["verdict"] for r in rx) == sorted(
            reason for reason, frames in attacks.items() for _ in frames)


# --- OpenSSL verifies the RVE's wire signatures ------------------------------------------
#
# A signed BSM as the RVE sends it (IEEE 1609.2 COER): 03 81 (version, signedData), 00
# (hashId sha256), then ToBeSignedData, then the signer, then the signature.  The
# signature is 80 (ecdsaNistP256Signature) 80 (rSig x-only) + 32 octets r + 32 octets s:
# the last 66 octets.  The signer is 80 + the 8-octet digest, or 81 (certificate) 01 01
# (a SEQUENCE OF with one element) + the certificate as in the PKI's .oer file.  So the
# ToBeSignedData is what lies between offset 3 and the signer, and the data that ECDSA
# signs is SHA-256(ToBeSignedData) || SHA-256(certificate) (1609.2 §5.3.1), hashed once
# more with SHA-256 by `openssl dgst -sha256`.

def _der(r: bytes, s: bytes) -> bytes:
    def integer(v: bytes) -> bytes:
        v = v.lstrip(b"\x00") or b"\x00"
        if v[0] & 0x80:
            v = b"\x00" + v
        return b"\x02" + bytes([len(v)]) + v
    body = integer(r) + integer(s)
    return b"\x30" + bytes([len(body)]) + body


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_openssl_verifies_the_rves_signatures_on_the_wire(pki, tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    rve(ports, "--sign", str(pki), "--per", "0", "--asap", "--duration", "2", "--capture",
        str(tmp_path))
    finish(obu)
    config = json.loads((tmp_path / "rve.config.json").read_text())
    assert config["settings"]["sign"] == str(pki)
    certs = {p.read_bytes(): p for p in pki.glob("pseudonym-*.oer")}
    digests = {hashlib.sha256(c).digest()[-8:]: c for c in certs}
    captured = extract_frames((tmp_path / "rve.frames.pcapng").read_bytes())
    wire = read_rx(tmp_path)
    signed = [bytes.fromhex(r["hex"]) for r in wire]  # the RV frames as the OBU got them
    # (the OBU records a frame at the tick that takes it: the last few may have none)
    assert 0 < len(signed) <= sum(x.meta.get("security") == "signed" for x in captured)
    assert all(d[:3] == b"\x03\x81\x00" for d in signed)
    checked = {"certificate": 0, "digest": 0}
    for data in signed[:40]:
        r, s = data[-64:-32], data[-32:]
        assert data[-66:-64] == b"\x80\x80"
        if data[-66 - 9] == 0x80 and data[-66 - 8:-66] in digests:
            cert, kind, tbs = digests[data[-66 - 8:-66]], "digest", data[3:-66 - 9]
        else:
            cert = next(c for c in certs if data[:-66].endswith(b"\x81\x01\x01" + c))
            kind, tbs = "certificate", data[3:-66 - 3 - len(cert)]
        key_file = certs[cert].with_name(certs[cert].name.replace(".oer", ".key.pem"))
        pub = tmp_path / "pub.pem"
        subprocess.run(["openssl", "ec", "-in", str(key_file), "-pubout", "-out", str(pub)],
                       check=True, capture_output=True, timeout=30)
        (tmp_path / "sig.der").write_bytes(_der(r, s))
        (tmp_path / "in.bin").write_bytes(hashlib.sha256(tbs).digest()
                                          + hashlib.sha256(cert).digest())
        out = subprocess.run(["openssl", "dgst", "-sha256", "-verify", str(pub), "-signature",
                              str(tmp_path / "sig.der"), str(tmp_path / "in.bin")],
                             capture_output=True, text=True, timeout=30)
        assert out.stdout.strip() == "Verified OK", (kind, out.stdout, out.stderr)
        checked[kind] += 1
    assert checked["certificate"] > 0 and checked["digest"] > 0


@pytest.mark.parametrize(("cmd", "needle"), [
    (["obu.cli", "run", "--verify", "enforce"], "--trust"),
    (["obu.cli", "run", "--verify", "log", "--trust", "/nonexistent/pki"], "/nonexistent"),
    (["rve.cli", "run", "--sign", "/nonexistent/pki"], "/nonexistent"),
    (["rve.cli", "run", "--sign", "{pki}", "--framing", "uper"], "--framing"),
    (["rve.cli", "pki", "init", "{pki}"], "already holds a PKI"),
])
def test_security_flags_bad_input_is_one_line_and_exit_2(pki, cmd, needle):
    cmd = [c.replace("{pki}", str(pki)) for c in cmd]
    out = subprocess.run([PY, "-m", *cmd, "--duration", "1"] if "run" in cmd
                         else [PY, "-m", *cmd], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines


def test_a_pki_with_too_few_pseudonyms_is_a_one_line_error(tmp_path):
    d = tmp_path / "small"
    subprocess.run([PY, "-m", "rve.cli", "pki", "init", str(d), "--vehicles", "2"],
                   check=True, capture_output=True, timeout=60)
    out = subprocess.run([PY, "-m", "rve.cli", "run", "--sign", str(d), "--asap",
                          "--duration", "1", "--to", "127.0.0.1:9"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "pseudonym certificates for" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


# --- tshark dissects the RVE's captures ------------------------------------------------------


def _tshark(*args: str) -> str:
    tshark = shutil.which("tshark")
    if tshark is None:
        pytest.skip("tshark not installed (make test installs it)")
    return subprocess.run([tshark, *args], capture_output=True, text=True, timeout=120,
                          check=True).stdout


def test_tshark_dissects_the_rves_signed_wsmp_capture(pki, tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", "enforce",
                    "--verify-policy", "all", "--trust", str(pki))  # every frame, on arrival
    summary = rve(ports, "--sign", str(pki), "--framing", "wsmp", "--per", "0", "--asap",
                  "--duration", "2", "--capture", str(tmp_path))
    _, err = finish(obu)
    assert _counters(err)["verify_ok"] == summary["signed"] > 0  # the OBU reads WSMP too
    pcap = str(tmp_path / "rve.frames.pcapng")
    frames = re.split(r"^Frame \d+:", _tshark("-r", pcap, "-V"), flags=re.M)[1:]
    assert len(frames) == summary["sent"] + summary["host_frames"]
    signed = [f for f in frames if "content: signedData (1)" in f]
    assert len(signed) == summary["signed"]
    certs = sum("signer: certificate (1)" in f for f in signed)
    assert certs == summary["with_certificate"]
    assert sum("signer: digest (0)" in f for f in signed) == len(signed) - certs
    for text in frames:
        assert "Protocols in frame: eth:ethertype:wsmp:ieee1609dot2" in text
        assert re.search(r"PSID: psid-vehicle-to-vehicle-safety-and-awarenesss\s*\(32\)", text)
        assert "Malformed" not in text
    for text in signed:
        assert "hashId: sha256 (0)" in text and "signature: ecdsaNistP256Signature (0)" in text
    expert = _tshark("-r", pcap, "-q", "-z", "expert")
    assert not re.search(r"^(Errors|Warnings)\b", expert, flags=re.M), expert


def test_tshark_sees_real_udp_ports_and_good_checksums(tmp_path):
    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca")
    summary = rve(ports, "--per", "0", "--asap", "--duration", "1", "--capture", str(tmp_path))
    finish(obu)
    rows = [line.split("\t") for line in _tshark(
        "-r", str(tmp_path / "rve.frames.pcapng"), "-o", "udp.check_checksum:TRUE",
        "-T", "fields", "-e", "udp.srcport", "-e", "udp.dstport", "-e",
        "udp.checksum.status").splitlines()]
    assert len(rows) == summary["sent"] + summary["host_frames"]
    assert {r[1] for r in rows} == {str(p) for p in ports}
    assert all(r[0] not in ("", "0") for r in rows) and len({r[0] for r in rows}) == 2
    assert {r[2] for r in rows} == {"1"}  # 1 = Good


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def test_hostile_security_input_is_counted_and_memory_stays_bounded(pki, tmp_path):
    """10,000 distinct unknown digests, signatures cut short, certificates cut short and
    a chain longer than allowed, sent to ``obu run --verify enforce``: every frame is
    counted under its reason, the OBU keeps running and its memory stays bounded."""
    from catc.j2735.ieee1609 import build_signed

    ports = free_ports()
    obu = start_obu(tmp_path, ports, "--predictor", "ca", "--verify", "enforce", "--trust",
                    str(pki))
    frame = _frames(1)[0]
    now = unix_to_time64(time.time())
    rng = random.Random(5)
    cert = (pki / "pseudonym-4.oer").read_bytes()
    key = load_private_pem((pki / "pseudonym-4.key.pem").read_bytes())
    good = sign_bsm(frame, key, cert, now, include_cert=True)
    # a chain one longer than allowed (root -> AA -> sub-CA -> end entity: the limit is
    # three certificates with the root), both new certificates validly signed
    from catc.j2735.ieee1609 import parse_certificate
    from catc.security import Identity, issue_certificate

    aa_raw = (pki / "aa.oer").read_bytes()
    aa = Identity("aa", aa_raw, parse_certificate(aa_raw)[0],
                  load_private_pem((pki / "aa.key.pem").read_bytes()))
    validity = {"start_time32": aa.cert.start_time32, "duration_s": aa.cert.duration_s}
    sub = issue_certificate(aa, issue_psids=(0x20,), name="sub-ca", **validity)
    deep = issue_certificate(sub, app_psids=(0x20,), **validity)
    chain = [deep.raw, sub.raw]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        def send(data: bytes) -> None:
            s.sendto(data, ("127.0.0.1", ports[0]))

        send(good)
        time.sleep(0.3)
        rss0 = _rss_kb(obu.pid)
        for i in range(10_000):  # now + 1: not good's ToBeSignedData (a copy is a replay)
            send(build_signed(frame, generation_time_us=now + 1,
                              signer=("digest", rng.randbytes(8)),
                              signature=rng.randbytes(64)))
            if i % 200 == 199:
                time.sleep(0.02)  # about 10,000 frames/s, under the socket buffer
        for cut in (1, 10, 33):  # the signature cut short
            send(good[:-cut])
        for cut in range(1, 40, 7):  # the certificate cut short
            send(good[:len(good) - 66 - cut])
        send(build_signed(frame, generation_time_us=now + 1, signer=("certificate", chain),
                          signature=rng.randbytes(64)))
        time.sleep(1.0)
        rss1 = _rss_kb(obu.pid)
    assert obu.poll() is None  # still running
    _, err = finish(obu)
    c = _counters(err)
    assert c["verify_ok"] == 1 and c["verify_unknown-signer"] == 10_000
    assert c["verify_chain"] == 1
    assert c["decode_errors"] == 3 + len(range(1, 40, 7))
    assert c["frames_rv"] == 10_000 + 1 + 3 + len(range(1, 40, 7)) + 1
    assert rss1 - rss0 < 30_000, (rss0, rss1)  # kB: no per-digest state kept
