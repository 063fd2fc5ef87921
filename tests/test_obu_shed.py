"""An OBU behind real time catches up (``obu run --shed-after``): what waited too long is
dropped undecoded and counted, in process on the daemon's own receive path."""

from __future__ import annotations

import argparse
import time

from catc.bsm import BSM
from catc.j2735 import encode_frame
from obu.daemon import Obu
from obu.options import DEFAULTS


class _Cap:
    def __init__(self) -> None:
        self.statuses: list[tuple[str, str]] = []

    def frame(self, rx_unix, channel, data, status, **details) -> None:
        self.statuses.append((channel, status))

    def message(self, received, status, **details) -> None:
        self.statuses.append(("rv", status))

    def close(self, *args) -> None:
        pass


def _frame(temp_id: int, k: int) -> bytes:
    return encode_frame(BSM(msg_cnt=k, temp_id=temp_id, sec_mark=1000 + 100 * k, lat=42.3,
                            lon=-83.7, elev=200.0, speed=10.0, heading=0.0))


def test_frames_that_waited_too_long_are_shed_and_counted() -> None:
    args = argparse.Namespace(**{**DEFAULTS, "predictor": "ca", "shed_after": 0.5})
    obu = Obu(args)
    obu.cap = cap = _Cap()
    now = time.time()
    assert obu.frame("rv", _frame(7, 1), now - 0.9) is None  # waited 0.9 s: shed
    assert obu.frame("host", _frame(9, 1), now - 0.6) is None  # a tick not stepped
    obu.frame("rv", _frame(7, 2), now - 0.1)  # in time: taken
    host = obu.frame("host", _frame(9, 2), now)
    assert host is not None and host.temp_id == 9
    c = obu.counters
    assert c["shed_rv"] == 1 and c["shed_host"] == 1
    assert c["deadline_misses"] == c["deadline_misses_shed"] == 1
    assert cap.statuses == [("rv", "shed"), ("host", "shed")]
    assert [m.msg_cnt for m in obu.frames.pending] == [2]
    obu.cap = None
    obu.close()
    # off: nothing is ever shed
    slow = Obu(argparse.Namespace(**{**DEFAULTS, "predictor": "ca", "shed_after": "off"}))
    slow.frame("rv", _frame(7, 3), now - 60.0)
    assert not slow.counters["shed_rv"] and len(slow.frames.pending) == 1
    slow.close()
