"""``captures view DIR``: the OBU live view's page over a finished capture.

The same page ``obu run --web`` serves (``obu.web``), in replay mode: play, pause, speed and
a time slider over the OBU's ticks, and the list of warning events (a click jumps to its
moment).  Each tick shows what the OBU tracked (``obu.tracks.bin``), its warnings
(``obu.ticks.jsonl``) and, where the capture has the RVE's ground truth
(``rve.truth.jsonl``), every vehicle's true position, on the OBU's clock and ENU frame.
``/api/state?tick=N`` returns tick N as JSON, ``/api/ticks`` the tick times and events.

    captures view DIR [--web [HOST:]PORT]      (default 127.0.0.1:8750; Ctrl-C stops it)
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from pathlib import Path

from hil.capture import (
    clock_offset,
    iter_lines,
    read_capture,
    read_json,
    read_tracks,
    schema,
    segment_files,
    truth_in_frame,
)
from hil.config import web_address

DEFAULT_PORT = 8750


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="the live view's page over a finished capture",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", type=Path, metavar="DIR", help="capture directory (obu run --capture)")
    p.add_argument("--web", type=web_address, default=("127.0.0.1", DEFAULT_PORT),
                   metavar="[HOST:]PORT", help=f"where to serve (default 127.0.0.1:{DEFAULT_PORT})")
    p.set_defaults(func=run)


def load(directory: Path):
    """The capture as an :class:`obu.web.Replay` (ValueError with the reason): the OBU's
    files, and the RVE's truth where the directory has it."""
    from obu.web import Replay

    directory = Path(directory)
    if not segment_files(directory, schema.OBU_TICKS):
        raise ValueError(f"{directory}: no {schema.OBU_TICKS} (not an obu run --capture)")
    truth = None
    counters = {}
    if (directory / schema.OBU_COUNTERS).is_file():
        counters = read_json(directory / schema.OBU_COUNTERS)
    if (directory / schema.RVE_TRUTH).is_file():
        cap = read_capture(directory, rx=False)
        offset = clock_offset(cap.truth, cap.ticks, directory)
        truth = {tid: (t + offset, x, y) for tid, (_, t, x, y)
                 in truth_in_frame(cap.truth, cap.obu_config["origin"]).items()}
        ticks, tracks, events = cap.ticks, cap.tracks, cap.events
    else:  # the OBU's files alone, segments in order
        def lines(name: str) -> list[dict]:
            return [r for _, p in segment_files(directory, name) for r in iter_lines(p)]

        ticks, tracks, events = lines(schema.OBU_TICKS), read_tracks(directory), \
            lines(schema.OBU_EVENTS)
    if not ticks:
        raise ValueError(f"{directory}: the OBU recorded no tick")
    return Replay(ticks, tracks, events, truth, counters)


async def _serve(replay, host: str, port: int) -> None:
    from obu.web import make_app, start

    runner = await start(make_app(replay=replay), host, port)
    shown = f"[{host}]" if ":" in host else host
    print(f"captures view: {len(replay)} ticks at http://{shown}:{port}/ (Ctrl-C stops)",
          file=sys.stderr, flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await runner.cleanup()


def run(args: argparse.Namespace) -> int:
    try:
        replay = load(args.dir)
    except (ValueError, OSError, KeyError) as err:
        print(f"captures view: {err}", file=sys.stderr)
        return 2
    try:
        asyncio.run(_serve(replay, *args.web))
    except OSError as err:
        print(f"captures view: cannot serve on {args.web[0]}:{args.web[1]}: {err}",
              file=sys.stderr)
        return 2
    return 0
