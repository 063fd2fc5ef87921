"""``rve`` over CAN: the same check as over UDP (frames received = the schedule's undropped
messages, exactly) on every CAN bus available here: python-can's ``virtual`` bus (the RVE's
replay loop and a receiver in one process), ``udp_multicast`` between the ``rve run``
process and a receiver process inside a network namespace the test creates, and SocketCAN
``vcan`` where it can be created (not on this machine's kernel: skipped)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import select
import subprocess
import sys

import pytest

from catc.channel import ChannelConfig
from catc.j2735 import decode_frame
from catc.replay import plan, temp_id
from hil.datasets import load_table
from hil.transport import open_receiver
from rve.run import DEFAULTS, replay
from tests.conftest import shared_path
from tests.test_transport import _peer, bus, netns  # noqa: F401  (fixtures)

PER, BURST, SEED, DURATION = 0.4, 3.0, 5, 2.0


def _dataset() -> str:
    return "openacc:" + str(shared_path("openacc-zalazone", "short_setting_dynamic_part22.csv"))


def _expected(duration: float = DURATION):
    """The plan rve builds for these settings: what must arrive, by channel."""
    the_plan = plan(load_table(_dataset(), None), ChannelConfig(per=PER, burst=BURST),
                    SEED, None, duration)
    ev = the_plan.events[~the_plan.events["dropped"]]
    want_rv = sorted((temp_id(the_plan.vehicles[int(e["vehicle"])]), int(e["seq"]) % 128)
                     for e in ev if not e["host"])
    return the_plan, want_rv, int(ev["host"].sum())


def _got(frames: list[tuple[str, bytes]]) -> tuple[list, int]:
    rv = sorted((b.temp_id, b.msg_cnt) for b in (decode_frame(d) for ch, d in frames
                                                  if ch == "rv"))
    return rv, sum(1 for ch, _ in frames if ch == "host")


def replay_in_process(interface: str, channel: str, fd: bool, capture=None):
    """The RVE's replay loop (the plan of :func:`_expected`, as fast as possible) on a CAN
    bus with a receiver in this process: (counters, [(channel, frame)] received, receiver
    stats)."""
    the_plan = _expected()[0]
    args = argparse.Namespace(**DEFAULTS)
    args.transport, args.can_interface, args.can_channel, args.can_fd = "can", interface, \
        channel, fd
    args.asap, args.progress = True, False
    args.capture = None if capture is None else str(capture)

    async def main():
        got: list[tuple[str, bytes]] = []
        async with await open_receiver("can", interface=interface, channel=channel,
                                       fd=fd) as rx:
            async def pump():
                while True:
                    r = await rx.recv()
                    got.append((r.channel, r.data))

            task = asyncio.create_task(pump())
            counts = await replay(args, the_plan)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(5):
                    while len(got) < counts["sent"] + counts["host"]:
                        await asyncio.sleep(0.01)
            task.cancel()
            return counts, got, dict(rx.stats)

    return asyncio.run(asyncio.wait_for(main(), 120))


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_rve_replay_over_a_can_bus_in_one_process(bus, fd):  # noqa: F811
    interface, channel = bus
    _the_plan, want_rv, want_host = _expected()
    counts, got, stats = replay_in_process(interface, channel, fd)
    rv, host = _got(got)
    assert rv == want_rv and host == want_host
    assert counts["sent"] == len(want_rv) and counts["dropped"] > 0
    assert stats.get("errors", 0) == 0


def test_rve_process_over_udp_multicast_in_a_namespace(netns, tmp_path):  # noqa: F811
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    _the_plan, want_rv, want_host = _expected()
    count = len(want_rv) + want_host
    receiver = subprocess.Popen(
        _peer(netns, "recv", count, True), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        _ready, _, _ = select.select([receiver.stdout], [], [], 15)
        assert receiver.stdout.readline().strip() == "ready"
        rve = subprocess.run(
            ["ip", "netns", "exec", netns, sys.executable, "-m", "rve.cli", "run",
             "--dataset", _dataset(), "--transport", "can", "--can-interface",
             "udp_multicast", "--can-channel", "239.74.163.2", "--can-fd", "--per",
             str(PER * 100), "--burst", str(BURST), "--seed", str(SEED), "--duration",
             str(DURATION), "--asap", "--no-progress", "--capture", str(tmp_path)],
            capture_output=True, text=True, timeout=120)
        assert rve.returncode == 0, rve.stderr
        out, _err = receiver.communicate(timeout=60)
    finally:
        if receiver.poll() is None:
            receiver.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                receiver.wait(timeout=5)
    result = json.loads(out.strip().splitlines()[-1])
    rv, host = _got([(ch, bytes.fromhex(h)) for ch, h in result["got"]])
    assert rv == want_rv and host == want_host
    summary = json.loads(rve.stdout.strip().splitlines()[-1])
    assert summary["sent"] == len(want_rv)
    # the CAN capture holds every raw frame (python-can ASC)
    import can

    frames = list(can.ASCReader(str(tmp_path / "rve.frames.asc")))
    assert len(frames) >= count and {f.arbitration_id for f in frames} >= {0x6A0, 0x6A1}
