"""The command-line tools as a user runs them: separate processes, exit codes, output."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from catc.records import KEYS
from tests.conftest import shared_path

VEC = "jpo-ode-bsm-vectors"


def run(module: str, *args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], input=stdin,
                          capture_output=True, timeout=120, check=False)


@pytest.mark.parametrize(("module", "command"), [("captures.cli", "decode"),
                                                 ("rve.cli", "encode"), ("obu.cli", "frame")])
def test_help_lists_subcommands(module, command):
    out = run(module, "--help")
    assert out.returncode == 0
    assert command in out.stdout.decode()
    sub = run(module, command, "--help")
    assert sub.returncode == 0 and len(sub.stdout.decode().splitlines()) > 5


@pytest.mark.parametrize("module", ["captures.cli", "rve.cli", "obu.cli"])
def test_bad_flag_is_one_line_and_exit_2(module):
    out = run(module, "--no-such-flag")
    assert out.returncode == 2
    assert len(out.stderr.decode().strip().splitlines()) == 1
    assert out.stdout == b""


def test_decode_obu_log_prints_every_bsm_with_the_contract_keys():
    out = run("captures.cli", "decode", str(shared_path(VEC, "bsmLogDuringEvent.bin")))
    assert out.returncode == 0, out.stderr
    records = [json.loads(line) for line in out.stdout.decode().splitlines()]
    assert len(records) == 222
    assert all(tuple(r) == KEYS for r in records)
    first = records[0]
    assert (first["msgCnt"], first["id"]) == (81, "31325433")
    assert 40.5 < first["lat"] < 40.6 and -105.1 < first["lon"] < -105.0


@pytest.mark.parametrize(("name", "code", "count"), [
    ("rxMsg_BSM.bin", 1, 227),            # one TravelerInformation frame is reported
    ("bsm.uper", 0, 1),                   # bare BSM, zero padded
    ("decoder-input-bsm.json", 0, 1),     # signed IEEE 1609.2 inside an ODE record
    ("BsmReceiverTest_ValidBSM.txt", 0, 1),
    ("bsm_uper1.hex", 1, 0),              # truncated frame
])
def test_decode_each_kind_of_file(name, code, count):
    out = run("captures.cli", "decode", "--full", str(shared_path(VEC, name)))
    assert out.returncode == code, out.stderr
    assert len(out.stdout.decode().splitlines()) == count
    if code:
        assert out.stderr.decode().count("\n") == 1


def test_decode_garbage_and_missing_files(tmp_path):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(bytes(range(200, 256)) * 3)
    for path in (junk, tmp_path / "missing.uper"):
        out = run("captures.cli", "decode", str(path))
        assert out.returncode == 2
        assert len(out.stderr.decode().strip().splitlines()) == 1


def test_rve_encode_then_captures_decode_round_trips(tmp_path):
    records = [{"msgCnt": i, "id": "C0FFEE01", "secMark": 1000 * i,
                "lat": round(28.6024 + 1e-5 * i, 7), "lon": -81.2001, "elev": 30.0,
                "speed": 25.0, "heading": 90.0,
                "accel_long": -3.5, "accel_lat": 0.0, "accel_vert": None, "yaw_rate": 0.0,
                "width": 1.8, "length": 4.6} for i in range(5)]
    src = "\n".join(json.dumps(r) for r in records).encode()
    enc = run("rve.cli", "encode", "--ieee1609", stdin=src)
    assert enc.returncode == 0, enc.stderr
    hex_file = tmp_path / "frames.hex"
    hex_file.write_bytes(enc.stdout)
    dec = run("captures.cli", "decode", str(hex_file))
    assert dec.returncode == 0, dec.stderr
    assert [json.loads(line) for line in dec.stdout.decode().splitlines()] == records


def test_rve_encode_bad_record_names_the_line():
    out = run("rve.cli", "encode", stdin=b'{"id": "00000001", "lat": 1}\n{"lat": 2}\n')
    assert out.returncode == 1
    assert out.stderr.decode().startswith("rve encode: line 2:")


def test_obu_frame_decodes_signed_1609_and_rejects_other_messages():
    record = json.loads(shared_path(VEC, "decoder-input-bsm.json").read_text())
    out = run("obu.cli", "frame", record["payload"]["data"]["bytes"])
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["ieee1609"] == "signed"
    tim = run("obu.cli", "frame", "001F0300")
    assert tim.returncode == 1 and b"wrong-message-id" in tim.stderr
    assert run("obu.cli", "frame", "zz").returncode == 2


def test_replay_lists_the_nyc_fcw_warning_events():
    path = shared_path("cv-pilot-samples", "nycdot-fcw-event.json")
    out = run("captures.cli", "replay", "--dataset", f"nyc:{path}", "--predictor", "ca")
    assert out.returncode == 0, out.stderr
    events = [json.loads(line) for line in out.stdout.decode().splitlines()]
    starts = [e["t"] for e in events if e["app"] == "fcw" and e["kind"] == "start"]
    assert starts and all(e["rv"] == "A305214A" for e in events)
    assert min(starts, key=abs) == pytest.approx(-2.6, abs=0.05)
    assert "160 ticks" in out.stderr.decode()


@pytest.mark.parametrize("flags", [["--per", "101"], ["--predictor", "nope"],
                                   ["--apps", "fcw,ima"], ["--host", "NOBODY"]])
def test_replay_bad_flags_are_one_line_and_exit_2(flags):
    path = shared_path("cv-pilot-samples", "nycdot-fcw-event.json")
    out = run("captures.cli", "replay", "--dataset", f"nyc:{path}", *flags)
    assert out.returncode == 2
    assert len(out.stderr.decode().strip().splitlines()) == 1, out.stderr


def test_demo_replays_the_nyc_event_through_the_wire_and_the_ca_tc():
    data = shared_path("cv-pilot-samples").parent
    out = run("captures.demo", "--data", str(data))
    assert out.returncode == 0, out.stderr
    text = out.stdout.decode()
    assert "T =  -2.6 s  FCW start on A305214A" in text
    assert "gap 34.3 m < r_w" in text


@pytest.mark.parametrize("module, argv", [
    ("obu.cli", ["run", "--duration", "nan"]),  # never stopped
    ("obu.cli", ["run", "--duration", "-5"]),
    ("obu.cli", ["run", "--idle-exit", "-1"]),
    ("obu.cli", ["run", "--collect-ms", "nan"]),
    ("rve.cli", ["run", "--speed", "inf"]),
    ("rve.cli", ["run", "--duration", "-5"]),
    ("rve.cli", ["run", "--duration", "nan"]),
    ("rve.cli", ["run", "--to", "127.0.0.1:0"]),
    ("rve.cli", ["run", "--attack", "ghost:ahead=nan"]),  # refused once the plan is made
    ("rve.cli", ["run", "--latency", "nan"]),
    ("rve.cli", ["run", "--per", "nan"]),
    ("rve.cli", ["flood", "--dataset", "x", "--to", "127.0.0.1:0"]),
    ("rve.cli", ["flood", "--dataset", "x", "--to", "127.0.0.1:9", "--rate", "inf"]),
])
def test_values_that_make_no_run_are_one_line_and_exit_2(module, argv, capsys):
    """Issue 27: these were accepted in silence (``obu run --duration nan`` never stops)."""
    import importlib

    try:
        code = importlib.import_module(module).main(argv)
    except SystemExit as stop:  # argparse's own exit
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "Traceback" not in "\n".join(err)
    assert any(x in err[-1] for x in ("finite", "above 0", "from 0", "port 0")), err[-1]


def test_an_attack_parameter_that_is_not_finite_is_refused():
    from catc.attacks import parse

    with pytest.raises(ValueError, match="ahead must be a finite number"):
        parse("ghost:ahead=nan")


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly():
    """Issue 27: ``captures score | head`` printed a BrokenPipeError traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "captures.cli", "decode", "--full",
                             str(shared_path(VEC, "bsmLogDuringEvent.bin"))],  # 640 kB
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.read(100)  # the first line or so, then the reader goes away
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 141, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def read_only_dir(tmp_path):
    """A directory nobody may create files in: mode 0555, or for root (whom permission
    bits do not stop) /sys/kernel, where sysfs refuses new files to anyone."""
    import os
    from pathlib import Path

    if os.geteuid() != 0:
        ro = tmp_path / "read-only"
        ro.mkdir(mode=0o555)
        return ro
    if not Path("/sys/kernel").is_dir():
        pytest.skip("running as root without /sys/kernel: no directory root cannot write")
    return Path("/sys/kernel")


@pytest.fixture
def bad_files(tmp_path) -> dict[str, str]:
    """The wrong files a user hands the commands, by the names the table below uses."""
    import random

    junk = tmp_path / "junk.bin"
    junk.write_bytes(random.Random(27).randbytes(4096))  # 4 kB of binary garbage
    bad_json = tmp_path / "bad.json"
    bad_json.write_text('{"rows": [1,\n  oops]}\n')
    unreadable = tmp_path / "unreadable"  # a capture whose first file reads as EIO
    unreadable.mkdir()
    (unreadable / "rve.config.json").symlink_to("/proc/self/mem")
    torn = tmp_path / "torn"  # a capture whose config is not JSON
    torn.mkdir()
    (torn / "rve.config.json").write_text('{"run_id": "x",\n')
    pki = tmp_path / "pki"  # a PKI directory whose manifest is garbage
    pki.mkdir()
    (pki / "pki.json").write_bytes(junk.read_bytes())
    listed = tmp_path / "listed"  # ... or JSON, but not an object
    listed.mkdir()
    (listed / "pki.json").write_text("[1]\n")
    return {"tmp": str(tmp_path), "junk": str(junk), "bad_json": str(bad_json),
            "unreadable": str(unreadable), "torn": str(torn), "pki": str(pki),
            "listed": str(listed), "read_only": str(read_only_dir(tmp_path))}


RVE_RUN = ["rve.cli", "run", "--asap", "--no-progress", "--duration", "0.3",
           "--to", "127.0.0.1:9", "--host-to", "127.0.0.1:9"]
OBU_RUN = ["obu.cli", "run", "--duration", "0.3", "--no-progress",
           "--listen", "127.0.0.1:0", "--host-listen", "127.0.0.1:0"]


@pytest.mark.parametrize(("argv", "code", "needle"), [
    # a capture directory that cannot be made or written (the OBU's three too)
    ([*RVE_RUN, "--capture", "/proc/x"], 2, "/proc/x"),
    ([*RVE_RUN, "--capture", "{junk}/sub"], 2, "{junk}/sub"),
    ([*RVE_RUN, "--capture", "{read_only}"], 2, "{read_only}/rve."),
    ([*OBU_RUN, "--capture", "/proc/x"], 2, "/proc/x"),
    ([*OBU_RUN, "--capture", "{junk}/sub"], 2, "{junk}/sub"),
    ([*OBU_RUN, "--capture", "{read_only}"], 2, "{read_only}/obu."),
    # binary garbage and malformed JSON where JSON lines or a dataset belong
    (["rve.cli", "encode", "{junk}"], 1, "{junk}: not UTF-8 text"),
    (["rve.cli", "encode", "{bad_json}"], 1, "{bad_json}: line 1:"),
    (["rve.cli", "flood", "--dataset", "{junk}", "--to", "127.0.0.1:9"], 2, "{junk}"),
    (["rve.cli", "flood", "--trip", "nosuch", "--to", "127.0.0.1:9"], 2,
     "dataset 'scenario:highway-braking' has no trip 'nosuch'; trips: highway-braking"),
    ([*RVE_RUN, "--trip", "nosuch"], 2,
     "dataset 'scenario:highway-braking' has no trip 'nosuch'; trips: highway-braking"),
    (["captures.cli", "report", "--sweep", "{junk}", "--out", "{tmp}/r"], 2,
     "{junk}: not UTF-8 text"),
    (["captures.cli", "report", "--sweep", "{bad_json}", "--out", "{tmp}/r"], 2,
     "{bad_json}: not valid JSON: line 2 col 3"),
    # a capture that cannot be read: a file that fails with EIO, one that is not JSON
    (["captures.cli", "score", "{unreadable}"], 1,
     "{unreadable}/rve.config.json: Input/output error"),
    (["captures.cli", "plot", "{unreadable}"], 1,
     "{unreadable}/rve.config.json: Input/output error"),
    (["captures.cli", "score", "{torn}"], 2, "{torn}/rve.config.json: not valid JSON: line 2"),
    # a PKI manifest that is garbage, or JSON but not an object
    ([*RVE_RUN, "--sign", "{pki}"], 2, "{pki}/pki.json: not UTF-8 text"),
    ([*OBU_RUN, "--verify", "enforce", "--trust", "{listed}"], 2,
     "{listed}/pki.json: not a JSON object"),
    # the bound on the urgent ECDSA: a rate above 0, or off
    ([*OBU_RUN, "--verify-urgent", "0"], 2, "--verify-urgent: a number above 0, got 0"),
    ([*OBU_RUN, "--verify-urgent", "many"], 2, "--verify-urgent"),
    ([*OBU_RUN, "--shed-after", "-1"], 2, "--shed-after: a number above 0, got -1"),
])
def test_every_bad_input_is_one_line(argv, code, needle, bad_files):
    """Issue 27: each of these ended in a traceback, or in a line that named neither the
    file nor what was wrong with it."""
    out = run(*(a.format(**bad_files) for a in argv))
    err = out.stderr.decode()
    assert out.returncode == code, err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].strip(), err
    assert needle.format(**bad_files) in lines[0], lines[0]


def test_every_json_error_names_its_file(tmp_path):
    """Issue 27: a JSON error said ``Expecting value: line 1 column 1 (char 0)`` and
    nothing of the file.  Each reader of a JSON file names it, with the line and column."""
    import re

    from catc.predict.bank import KernelBank
    from hil.capture import CaptureError, read_json
    from hil.errors import InputError, load_json

    torn = tmp_path / "obu.end.json"  # an end record cut short
    torn.write_text('{"exit": "clean",\n "reason": ')
    where = re.escape(f"{torn}: not valid JSON: line 2 col 12: ")
    with pytest.raises(InputError, match=f"^{where}"):
        load_json(torn)
    with pytest.raises(CaptureError, match=f"^{where}"):
        read_json(torn)
    torn.write_text("[1, 2]")
    with pytest.raises(CaptureError, match=f"^{re.escape(str(torn))}: not a JSON object"):
        read_json(torn)
    with pytest.raises(ValueError, match=r"^bank\.json: not valid JSON: line 1 col 1: "):
        KernelBank.from_json("nope", "bank.json")


def limited(size: int):
    """A ``preexec_fn`` that caps the files the child writes at ``size`` bytes
    (RLIMIT_FSIZE, SIGXFSZ ignored): a write past it fails with EFBIG, as one on a full
    disk fails with ENOSPC, without a mount to make and remove."""
    import resource
    import signal

    def cap() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))

    return cap


def assert_flushed(directory, failed: str) -> None:
    """Every JSON-lines file of ``directory`` holds whole lines but ``failed``, which the
    writes filled up to the limit; the end record says the run ended in that error."""
    from pathlib import Path

    for path in Path(directory).glob("*.jsonl"):
        text = path.read_text()
        if path.name != failed:
            assert text.endswith("\n") and all(map(json.loads, text.splitlines())), path
    end = json.loads(next(Path(directory).glob("*.end.json")).read_text())
    assert end["exit"] == "error" and failed in end["reason"], end


def test_a_full_disk_during_rve_run_is_one_line_and_keeps_what_was_written(tmp_path):
    """Issue 27: a capture write that fails mid-run (here EFBIG; ENOSPC alike) printed
    ``[Errno 27] File too large`` without a file, exit 2, and no end record."""
    cap = tmp_path / "cap"
    out = subprocess.run([sys.executable, "-m", "rve.cli", "run", "--asap", "--no-progress",
                          "--to", "127.0.0.1:9", "--host-to", "127.0.0.1:9",
                          "--capture", str(cap)], capture_output=True, timeout=60,
                         preexec_fn=limited(64 * 1024), check=False)
    err = out.stderr.decode()
    assert out.returncode == 1 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"rve run: {cap}/rve."), err
    failed = lines[0].split(": ")[1].rpartition("/")[2]
    assert "File too large" in lines[0] and (cap / failed).stat().st_size == 64 * 1024
    assert_flushed(cap, failed)


def test_a_full_disk_during_obu_run_is_one_line_and_keeps_what_was_written(tmp_path):
    """The OBU's side of the test above: its capture fills up while an RVE sends."""
    from hil.transport.udp import free_ports, wait_bound

    cap = tmp_path / "cap"
    ports = free_ports()
    obu = subprocess.Popen([sys.executable, "-m", "obu.cli", "run", "--no-progress",
                            "--listen", f"127.0.0.1:{ports[0]}", "--host-listen",
                            f"127.0.0.1:{ports[1]}", "--capture", str(cap),
                            "--idle-exit", "1", "--duration", "30"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           preexec_fn=limited(64 * 1024))
    try:
        assert wait_bound(ports[:2], alive=lambda: obu.poll() is None)
        # 40 s of data: the compact capture (obu.tracks.bin, obu.rx.jsonl.gz) writes a
        # tenth of what JSON lines did, and the ticks' 64 kB must fill
        run("rve.cli", "run", "--asap", "--no-progress", "--duration", "40",
            "--to", f"127.0.0.1:{ports[0]}", "--host-to", f"127.0.0.1:{ports[1]}")
        err = obu.communicate(timeout=30)[1].decode()
    finally:
        if obu.poll() is None:
            obu.kill()
    assert obu.returncode == 1 and "Traceback" not in err, err
    # the warnings' log lines ("obu: FCW start ..."), then the one line of the error
    lines = [line for line in err.strip().splitlines() if not line.startswith("obu: ")]
    assert len(lines) == 1 and lines[0].startswith(f"obu run: {cap}/obu."), err
    failed = lines[0].split(": ")[1].rpartition("/")[2]
    assert "File too large" in lines[0] and (cap / failed).stat().st_size == 64 * 1024
    assert_flushed(cap, failed)
