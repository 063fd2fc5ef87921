"""One side of the two-process ``udp_multicast`` CAN test in ``tests/test_transport.py``.

The test runs it inside the network namespace it created::

    ip netns exec NAME python tests/netns_can_peer.py recv --count N [--fd] [--timeout S]
    ip netns exec NAME python tests/netns_can_peer.py send --count N [--fd]

``recv`` prints ``ready`` once its bus is open, then one JSON line with the frames it
received (``[channel, hex]``, in order) and its counters; ``send`` sends
:func:`payloads` and prints its counters.  Every wait is bounded by ``--timeout``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import time

GROUP = "239.74.163.2"
SIZES = (1, 7, 8, 40, 62, 63, 64, 100, 150, 200, 500, 1000, 1500)


def payloads(count: int, seed: int = 7) -> list[tuple[str, bytes]]:
    """``count`` frames (channel, octets): every fifth on the host channel, sizes cycling
    through :data:`SIZES`, random contents."""
    rng = random.Random(seed)
    return [("host" if i % 5 == 4 else "rv", rng.randbytes(SIZES[i % len(SIZES)]))
            for i in range(count)]


async def _recv(args: argparse.Namespace) -> dict:
    from hil.transport import open_receiver

    got: list[list[str]] = []
    async with await open_receiver("can", interface="udp_multicast", channel=GROUP,
                                   fd=args.fd) as rx:
        print("ready", flush=True)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(args.timeout):
                while len(got) < args.count:
                    frame = await rx.recv()
                    got.append([frame.channel, frame.data.hex()])
        return {"got": got, "stats": rx.stats}


async def _send(args: argparse.Namespace) -> dict:
    from hil.transport import open_sender

    async with await open_sender("can", interface="udp_multicast", channel=GROUP,
                                 fd=args.fd) as tx:
        t0 = time.monotonic()
        async with asyncio.timeout(args.timeout):
            for channel, data in payloads(args.count):
                await (tx.send(data) if channel == "rv" else tx.send_host(data))
        return {"seconds": time.monotonic() - t0, "stats": tx.stats}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("role", choices=("send", "recv"))
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--fd", action="store_true")
    p.add_argument("--timeout", type=float, default=15.0)
    args = p.parse_args()
    result = asyncio.run(_recv(args) if args.role == "recv" else _send(args))
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
