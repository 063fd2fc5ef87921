"""hil.transport on real sockets and buses (no mocks).

UDP runs on 127.0.0.1 and ::1.  CAN runs on python-can's ``virtual`` bus in this
process and, where a vcan interface can be created (root, SocketCAN in the kernel), on
SocketCAN with the same test bodies; ``udp_multicast`` runs between two processes inside
a network namespace that the test creates and deletes.  Every wait is bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import random
import select
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import pytest

from hil.transport import KINDS, TransportError, open_receiver, open_sender
from hil.transport.can import HOST_IDS, RV_IDS
from tests.netns_can_peer import payloads

HERE = Path(__file__).resolve().parent
SIZES = (1, 2, 7, 8, 40, 62, 63, 64, 100, 200, 777, 1500)


def run(coro, timeout: float = 20.0):
    async def bounded():
        async with asyncio.timeout(timeout):
            return await coro
    return asyncio.run(bounded())


async def collect(rx, n: int, timeout: float = 10.0) -> list:
    got = []
    async with asyncio.timeout(timeout):
        while len(got) < n:
            got.append(await rx.recv())
    return got


async def eventually(check, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.01)


def frames(n: int, seed: int) -> list[bytes]:
    rng = random.Random(seed)
    return [rng.randbytes(SIZES[i % len(SIZES)]) for i in range(n)]


def by_channel(got) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {"rv": [], "host": []}
    for r in got:
        out[r.channel].append(r.data)
    return out


def test_unknown_kind():
    assert KINDS == ("udp", "can")
    with pytest.raises(TransportError, match="unknown transport 'tcp'"):
        run(open_sender("tcp"))


# --- UDP -------------------------------------------------------------------------------

@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_udp_frames_arrive_intact_in_order_per_channel(host):
    sent = {"rv": frames(240, 1), "host": frames(60, 2)}

    async def main():
        async with await open_receiver("udp", listen=(host, 0), host_listen=(host, 0)) as rx:
            assert rx.stats["rcvbuf"] > 0
            to, host_to = rx.addresses["rv"], rx.addresses["host"]
            async with await open_sender("udp", to=to, host_to=host_to) as tx:
                for i, data in enumerate(sent["rv"]):
                    await tx.send(data)
                    if i % 4 == 0:
                        await tx.send_host(sent["host"][i // 4])
                got = await collect(rx, 300)
                assert tx.stats["frames"] == 300 and tx.stats["errors"] == 0
            assert all(r.rx_time <= time.monotonic() for r in got)
            assert by_channel(got) == sent
            assert rx.stats["rv"] == 240 and rx.stats["host"] == 60
            assert rx.stats["bytes"] == sum(map(len, sent["rv"] + sent["host"]))

    run(main())


def test_udp_oversized_datagrams_are_counted_and_dropped():
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
                raw.sendto(b"x" * 2001, rx.addresses["rv"])
                raw.sendto(b"y" * 5000, rx.addresses["host"])
                raw.sendto(b"z" * 2000, rx.addresses["rv"])
            (got,) = await collect(rx, 1)
            assert got.channel == "rv" and got.data == b"z" * 2000
            await eventually(lambda: rx.stats["oversized"] == 2)
            assert rx.stats["frames"] == 1

    run(main())


def test_udp_burst_is_not_lost_at_the_socket():
    """500 datagrams arrive while the loop cannot read: the receive buffer holds them."""
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            if rx.stats["rcvbuf"] < 4 * 2**20:
                pytest.skip(f"kernel granted a {rx.stats['rcvbuf']}-octet receive buffer "
                            "(net.core.rmem_max; SO_RCVBUFFORCE needs CAP_NET_ADMIN)")
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
                for i in range(500):  # no await: the receiver cannot read meanwhile
                    raw.sendto(i.to_bytes(2, "big") * 100, rx.addresses["rv"])
            got = await collect(rx, 500)
            assert [int.from_bytes(r.data[:2], "big") for r in got] == list(range(500))

    run(main())


def test_udp_waiting_sees_datagrams_the_loop_has_not_read_yet():
    """waiting() is True from the moment a datagram is in the socket's buffer (sendto on
    loopback returns after delivery) until recv() has handed it out, and False after."""
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            assert not rx.waiting()
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
                raw.sendto(b"rv", rx.addresses["rv"])
                assert rx.waiting()  # no await yet: still in the kernel buffer
                raw.sendto(b"host", rx.addresses["host"])
            seen = []
            while len(seen) < 2:
                seen.append((await rx.recv()).data)
                assert rx.waiting() == (len(seen) < 2)
            assert sorted(seen) == [b"host", b"rv"]
        assert not rx.waiting()  # closed

    run(main())


def test_udp_frames_come_out_in_arrival_order_across_the_channels():
    """The event loop reads one datagram per socket per pass, so with a backlog on the RV
    socket (a flood, or an OBU behind at start-up) a host frame used to be handed out
    before RV frames sent ahead of it, and the OBU stepped its tick without them; reading
    the RV socket to the end first would hand RV frames sent after it out ahead of it.
    With 3 ticks' frames waiting in the kernel, recv() gives them in the order sent."""
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            sent = []
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
                for tick in range(3):  # no await: the loop cannot read meanwhile
                    for i in range(100):
                        raw.sendto(b"rv %d %d" % (tick, i), rx.addresses["rv"])
                        sent.append(("rv", b"rv %d %d" % (tick, i)))
                    raw.sendto(b"host %d" % tick, rx.addresses["host"])
                    sent.append(("host", b"host %d" % tick))
            got = [(r.channel, r.data) for r in await collect(rx, len(sent))]
            assert got == sent

    run(main())


def test_udp_port_in_use_is_a_one_line_error_and_leaks_nothing():
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            busy = rx.addresses["host"]
            with socket.socket() as probe:
                probe.bind(("127.0.0.1", 0))
                free = probe.getsockname()
            with pytest.raises(TransportError) as err:
                await open_receiver("udp", listen=free, host_listen=busy)
            message = str(err.value)
            assert "\n" not in message
            assert f"127.0.0.1:{busy[1]}" in message and "Address already in use" in message
            # the socket bound for `listen` before the failure was closed again
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as again:
                again.bind(free)

    run(main())


@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_udp_send_to_a_closed_port_is_counted_not_raised(host):
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        closed = probe.getsockname()[:2]

    async def main():
        tx = await open_sender("udp", to=closed, host_to=closed)
        for _ in range(5):
            await tx.send(b"bsm")
            await tx.send_host(b"hv")
            await asyncio.sleep(0.01)
        await tx.aclose()
        await tx.aclose()
        assert tx.stats["frames"] == 10
        assert tx.stats["econnrefused"] >= 1 and tx.stats["errors"] >= 1
        with pytest.raises(TransportError, match="closed"):
            await tx.send(b"late")

    run(main())


def test_udp_burst_send_many_arrives_in_order_with_a_stamp_each():
    """send_many (the RVE's 1,000 frames due at one instant): every frame arrives, in
    order, and each has the stamp taken after its send."""
    async def main():
        async with await open_receiver("udp", listen=("127.0.0.1", 0),
                                       host_listen=("127.0.0.1", 0)) as rx:
            if rx.stats["rcvbuf"] < 4 * 2**20:
                pytest.skip(f"kernel granted a {rx.stats['rcvbuf']}-octet receive buffer")
            burst = [i.to_bytes(2, "big") * 120 for i in range(1000)]
            async with await open_sender("udp", to=rx.addresses["rv"],
                                         host_to=rx.addresses["host"]) as tx:
                ticks = iter(range(10_000))
                stamps = await tx.send_many(burst, lambda: next(ticks))
                assert stamps == list(range(1000))
                assert tx.stats["frames"] == tx.stats["rv"] == 1000
                assert tx.stats["bytes"] == 240_000 and tx.stats["errors"] == 0
                got = await collect(rx, 1000)
            assert [r.data for r in got] == burst

    run(main())


def test_udp_send_many_to_a_closed_port_is_counted_not_raised():
    """A refused burst (ICMP port unreachable on the connected socket): counted, a stamp
    per frame, nothing raised, and the sender still sends."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        closed = probe.getsockname()[:2]

    async def main():
        tx = await open_sender("udp", to=closed, host_to=closed)
        for _ in range(3):
            stamps = await tx.send_many([b"bsm"] * 50, lambda: 0)
            assert len(stamps) == 50
            await asyncio.sleep(0.01)
        assert tx.stats["frames"] == 150
        assert tx.stats["econnrefused"] >= 1 and tx.stats["errors"] >= 1
        await tx.aclose()

    run(main())


# --- CAN: virtual bus in this process, SocketCAN where vcan can be created -------------

def _ip(*args: str) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return subprocess.CompletedProcess(args, 1, "", str(exc))


@contextlib.contextmanager
def vcan_interface():
    """A vcan interface of our own (MTU 72: CAN FD), deleted afterwards.  Where the kernel
    has no vcan the test skips with the reason, or fails inside the vcan VM
    (``CATC_REQUIRE_VCAN``, set by ``tools/vcanvm.py pytest``), where that is a bug."""
    name = f"catcvcan{os.getpid() % 100000}"
    made = _ip("link", "add", "dev", name, "type", "vcan")
    if made.returncode != 0:
        reason = f"cannot create a vcan interface: {made.stderr.strip()}"
        if os.environ.get("CATC_REQUIRE_VCAN"):
            pytest.fail(reason)
        pytest.skip(f"{reason} (make test-vcan runs the SocketCAN tests in a VM)")
    try:
        up = _ip("link", "set", "dev", name, "mtu", "72", "up")
        assert up.returncode == 0, up.stderr
        yield name
    finally:
        _ip("link", "del", "dev", name)


@pytest.fixture(params=["virtual", pytest.param("socketcan", marks=pytest.mark.socketcan)])
def bus(request):
    """(interface, channel) of a bus of our own: python-can's virtual bus, or SocketCAN on a
    vcan interface created and deleted for the test."""
    if request.param == "virtual":
        yield "virtual", f"test-{uuid.uuid4().hex}"
        return
    with vcan_interface() as name:
        yield "socketcan", name


def _pci(msg: can.Message) -> str:
    return ("SF", "FF", "CF", "FC")[msg.data[0] >> 4]


def transfers(trace: list[can.Message], fd: bool) -> list[tuple[int, list[can.Message]]]:
    """Split a bus trace into ISO-TP transfers, failing if any two interleave: from a
    First Frame to its last Consecutive Frame only that transfer's frames and its
    address's Flow Control may appear."""
    fc_of = {RV_IDS[0]: RV_IDS[1], HOST_IDS[0]: HOST_IDS[1]}
    out: list[tuple[int, list[can.Message]]] = []
    current, remaining = None, 0
    for msg in trace:
        if current is not None:
            ident, frames_ = current
            is_fc = msg.arbitration_id == fc_of[ident] and _pci(msg) == "FC"
            assert is_fc or (msg.arbitration_id == ident and _pci(msg) == "CF"), (
                f"{msg} interleaves the transfer on {ident:03X}")
            frames_.append(msg)
            if not is_fc:
                remaining -= len(msg.data) - 1
                if remaining <= 0:
                    out.append(current)
                    current = None
            continue
        assert msg.arbitration_id in fc_of, f"{msg} outside any transfer"
        if _pci(msg) == "SF":
            out.append((msg.arbitration_id, [msg]))
        else:
            assert _pci(msg) == "FF", f"{msg} outside any transfer"
            length = ((msg.data[0] & 0x0F) << 8) | msg.data[1]
            remaining = length - (len(msg.data) - 2)
            current = (msg.arbitration_id, [msg])
    assert current is None, "trace ends inside a transfer"
    return out


def test_interleave_check_catches_interleaving():
    ff = can.Message(arbitration_id=RV_IDS[0], data=bytes([0x10, 10]) + bytes(6))
    fc = can.Message(arbitration_id=RV_IDS[1], data=bytes([0x30, 0, 0]))
    cf = can.Message(arbitration_id=RV_IDS[0], data=bytes([0x21]) + bytes(7))
    sf = can.Message(arbitration_id=HOST_IDS[0], data=bytes([0x01, 9]))
    assert [len(f) for _, f in transfers([ff, fc, cf, sf], fd=False)] == [3, 1]
    with pytest.raises(AssertionError, match="interleaves"):
        transfers([ff, fc, sf, cf], fd=False)


def _key(trace: list[can.Message]) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in trace]


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_can_concurrent_transfers_arrive_intact_and_never_interleave(bus, fd):
    interface, channel = bus
    sent = {"rv": frames(48, 3), "host": frames(24, 4)}
    tx_trace: list[can.Message] = []
    rx_trace: list[can.Message] = []

    async def main():
        rx = await open_receiver("can", interface=interface, channel=channel, fd=fd,
                                 on_frame=rx_trace.append)
        tx = await open_sender("can", interface=interface, channel=channel, fd=fd,
                               on_frame=tx_trace.append)
        try:
            async def pump(send, items):
                for data in items:
                    await send(data)
                    await asyncio.sleep(0)

            receiving = asyncio.create_task(collect(rx, 72))
            await asyncio.gather(pump(tx.send, sent["rv"]), pump(tx.send_host, sent["host"]))
            got = await receiving
        finally:
            await tx.aclose()
            await rx.aclose()
        assert by_channel(got) == sent
        assert tx.stats["frames"] == rx.stats["frames"] == 72
        assert tx.stats["failed"] == tx.stats["errors"] == rx.stats["errors"] == 0
        return tx.stats, rx.stats

    tx_stats, rx_stats = run(main())
    # on_frame saw every frame, in the same order on both sides, in the right direction
    assert _key(tx_trace) == _key(rx_trace)
    assert len(tx_trace) == tx_stats["can_frames"] == rx_stats["can_frames"]
    assert all(m.is_rx == (m.arbitration_id in (RV_IDS[1], HOST_IDS[1])) for m in tx_trace)
    assert all(m.is_rx == (m.arbitration_id in (RV_IDS[0], HOST_IDS[0])) for m in rx_trace)
    assert all(m.is_fd == fd and len(m.data) <= (64 if fd else 8) for m in tx_trace)
    split = transfers(tx_trace, fd)
    assert len(split) == 72
    assert sum(1 for _, f in split if len(f) > 1) >= 30  # most are multi-frame
    assert {ident for ident, _ in split} == {RV_IDS[0], HOST_IDS[0]}
    # the two senders' transfers did alternate on the bus, yet never interleaved
    switches = sum(a[0] != b[0] for a, b in itertools.pairwise(split))
    assert switches >= 10


def _raw(arbitration_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, is_extended_id=False,
                       data=data + b"\xcc" * (8 - len(data)))


def test_can_broken_transfers_are_counted_and_dropped(bus):
    interface, channel = bus
    rv, after = bytes(range(100)), [b"ok-1", bytes(300), b"ok-3"]

    async def main():
        rx = await open_receiver("can", interface=interface, channel=channel,
                                 isotp_params={"rx_consecutive_frame_timeout": 100})
        tx = await open_sender("can", interface=interface, channel=channel)
        inject = can.Bus(interface=interface, channel=channel)
        try:
            # a First Frame announcing 100 octets, then nothing: N_Cr times out
            inject.send(_raw(RV_IDS[0], bytes([0x10, 100]) + rv[:6]))
            await eventually(lambda: rx.stats.get("consecutive_frame_timeout") == 1)
            # a First Frame of 20 octets, then a Consecutive Frame numbered 2 instead of 1
            inject.send(_raw(HOST_IDS[0], bytes([0x10, 20]) + rv[:6]))
            inject.send(_raw(HOST_IDS[0], bytes([0x22]) + rv[6:13]))
            await eventually(lambda: rx.stats.get("wrong_sequence_number") == 1)
            # a First Frame longer than max_frame (2,000): refused with Flow Control overflow
            inject.send(_raw(RV_IDS[0], bytes([0x1F, 0xFF]) + rv[:6]))
            await eventually(lambda: rx.stats.get("frame_too_long") == 1)
            await eventually(lambda: tx.stats.get("overflow") == 1)  # stale, while idle
            for data in after:
                await tx.send(data)
            await tx.send_host(b"hv")
            got = await collect(rx, 4)
        finally:
            inject.shutdown()
            await tx.aclose()
            await rx.aclose()
        assert [(r.channel, r.data) for r in got] == [("rv", d) for d in after] + [("host", b"hv")]
        assert rx.stats["frames"] == 4 and rx.stats["errors"] == 3
        assert tx.stats["frames"] == 4 and tx.stats["failed"] == 0

    run(main())


def test_can_bus_errors_are_one_line_transport_errors():
    with pytest.raises(TransportError) as err:
        run(open_receiver("can", interface="socketcan", channel="catcnone0"))
    assert "socketcan:catcnone0" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(TransportError) as err:  # not a multicast group: nothing is sent
        run(open_sender("can", interface="udp_multicast", channel="127.0.0.1"))
    assert "udp_multicast:127.0.0.1" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(TransportError, match="no_such_bus"):
        run(open_sender("can", interface="no_such_bus"))


def test_can_sender_cancelled_mid_transfer_leaves_the_bus_usable():
    """No receiver: a multi-frame transfer waits for Flow Control; cancelling it must
    abandon it so the next transfer starts clean (here it times out and is counted)."""
    channel = f"test-{uuid.uuid4().hex}"

    async def main():
        async with await open_sender("can", interface="virtual", channel=channel,
                                     isotp_params={"rx_flowcontrol_timeout": 50}) as tx:
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.02):
                    await tx.send(bytes(100))
            await tx.send(bytes(100))  # no Flow Control: N_Bs expires after 50 ms
            await tx.send(b"short")  # a Single Frame needs none
            assert tx.stats["failed"] == 1 and tx.stats["flow_control_timeout"] == 1
            assert tx.stats["frames"] == 1

    run(main())


# --- CAN over udp_multicast between two processes, in a namespace of our own -----------

@pytest.fixture
def netns():
    """A network namespace with lo up and an IPv4 multicast route on it; deleted after."""
    name = f"catc-test-{os.getpid()}"
    made = _ip("netns", "add", name)
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace: {made.stderr.strip()}")
    try:
        for args in (("link", "set", "lo", "up"), ("route", "add", "224.0.0.0/4", "dev", "lo")):
            done = _ip("-n", name, *args)
            assert done.returncode == 0, done.stderr
        yield name
    finally:
        _ip("netns", "del", name)


def _peer(netns: str, role: str, count: int, fd: bool) -> list[str]:
    cmd = ["ip", "netns", "exec", netns, sys.executable, str(HERE / "netns_can_peer.py"),
           role, "--count", str(count), "--timeout", "15"]
    return cmd + (["--fd"] if fd else [])


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_can_udp_multicast_between_two_processes(netns, fd):
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    count = 60
    receiver = subprocess.Popen(_peer(netns, "recv", count, fd), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([receiver.stdout], [], [], 15)
        line = receiver.stdout.readline() if ready else ""
        assert line.strip() == "ready", f"receiver did not start: {line!r}"
        sender = subprocess.run(_peer(netns, "send", count, fd), capture_output=True,
                                text=True, timeout=30)
        assert sender.returncode == 0, sender.stderr
        out, err = receiver.communicate(timeout=30)
        assert receiver.returncode == 0, err
    finally:
        if receiver.poll() is None:
            receiver.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                receiver.wait(timeout=5)
    result = json.loads(out.strip().splitlines()[-1])
    sent = json.loads(sender.stdout.strip().splitlines()[-1])
    assert [tuple(g) for g in result["got"]] == [(ch, d.hex()) for ch, d in payloads(count)]
    assert sent["stats"]["frames"] == count and sent["stats"]["failed"] == 0
    assert result["stats"]["errors"] == 0


def test_free_ports_are_below_the_ephemeral_range():
    """No socket gets them from bind(0) or by connecting, so a port a test hands to its
    daemons is never another test's receiver (the two run side by side under xdist)."""
    from hil.transport.udp import _ephemeral_low, free_ports

    low = _ephemeral_low()
    ports = free_ports(6) + free_ports(2, "::1")
    assert len(set(ports)) == len(ports)
    assert all(10000 <= p < low for p in ports) or low < 11000
