"""What the detector remembers between messages, bounded: each sender's accepted messages
(an LRU of at most ``max_senders`` TemporaryIDs) and the last messages it heard from it
(to recognise copies), the grid that finds a sender's neighbours, the network's message
interval and loss, and time on the senders' clocks.

A sender's clock is its secMark (ms within the UTC minute, wrapped at 60000); ``t`` is
the caller's receive clock.
"""

from __future__ import annotations

import math
from collections import OrderedDict

from catc.mbd.config import MbdConfig
from catc.mbd.geometry import scale

__all__ = ["Msg", "Sender", "Senders", "wrapped_dt"]

#: Accepted messages kept back to the anchor (a flood of messages inside ``anchor_s``).
_HISTORY = 64
_AROUND = (-1, 0, 1)
_EARLY = 256


def wrapped_dt(sm: int, sm0: int, dt_rx: float) -> float:
    """Seconds from secMark ``sm0`` to ``sm``: the reading (mod 60 s) nearest ``dt_rx``."""
    d = ((sm - sm0) % 60_000) / 1000.0
    return d + 60.0 * round((dt_rx - d) / 60.0)


class Msg:
    """An accepted message, as the checks need it: ``ts`` on the sender's clock
    (continued from its first accepted message), ``t`` the receive time, ``sm`` its
    secMark."""

    __slots__ = ("heading", "lat", "length", "lon", "sm", "speed", "t", "ts", "width")

    def __init__(self, ts: float, t: float, sm: int | None, lat: float, lon: float,
                 speed: float | None, heading: float | None, length: float | None,
                 width: float | None) -> None:
        self.ts, self.t, self.sm = ts, t, sm
        self.lat, self.lon, self.speed, self.heading = lat, lon, speed, heading
        self.length, self.width = length, width


class Sender:
    """What the detector keeps of one TemporaryID (its messages; the evidence against it
    is its signer's, :class:`catc.mbd.quarantine.Principal`)."""

    __slots__ = ("acc", "cell", "copies", "first_t", "heard_t", "hist", "min_off", "nominal",
                 "sybil", "tid")

    def __init__(self, tid: int, t: float) -> None:
        self.tid = tid
        self.first_t = t  # first heard (receive clock)
        self.heard_t = t  # last heard, accepted or not
        self.acc: Msg | None = None  # the last accepted message
        self.hist: list[Msg] = []  # accepted messages back to the anchor
        self.min_off = math.inf  # lowest (receive time - sender time) so far
        self.nominal = 0.0  # its shortest accepted interval (s; 0: none yet)
        #: the last messages heard, (msgCnt, secMark, lat, lon), oldest first
        self.copies: dict[tuple, None] = {}
        self.sybil: dict[int, int] = {}  # other id -> consecutive co-moving messages
        self.cell: tuple[int, int] | None = None


class Senders:
    """The senders' state: an LRU of at most ``max_senders`` ids, each placed in a grid of
    ``grid_cell_m`` cells at its last accepted position."""

    def __init__(self, config: MbdConfig, max_senders: int) -> None:
        self.config = config
        self.max_senders = max_senders
        #: Each id's state, the least recently heard first.
        self.by_id: OrderedDict[int, Sender] = OrderedDict()
        self._grid: dict[int, dict[int, set[int]]] = {}  # row -> column -> ids
        self._cell_lat = self._cell_lon = 0.0  # grid cell size in degrees, set on first use
        self._last: tuple[float, float, tuple[int, int]] = (math.nan, math.nan, (0, 0))
        #: Receive time of the first message seen (None: none yet).
        self.t0: float | None = None
        #: Running mean of accepted message intervals (s; 0: none yet).
        self.interval = 0.0
        #: Running mean of the nominal interval (s; 0: none yet): each accepted interval
        #: over the messages it spans on its sender's shortest interval.
        self.nominal = 0.0
        #: The loss on the senders' secMark gaps: in-order messages heard, messages missing
        #: before them, and the gaps (bursts) they were missing in.
        self.heard = self.lost = self.bursts = 0
        #: Receive times of the first messages of the senders first heard in the first
        #: minute (at most ``_EARLY``): those first heard late count as lost before.
        self.early: list[float] = []

    def __len__(self) -> int:
        return len(self.by_id)

    def grid_entries(self) -> int:
        """Ids in the neighbour grid (bounded like the senders)."""
        return sum(len(s) for row in self._grid.values() for s in row.values())

    def get(self, tid: int, t: float) -> Sender:
        """The state of ``tid`` (new when unknown: first heard at ``t``), now the most
        recently used; the least recently used beyond ``max_senders`` are forgotten."""
        senders = self.by_id
        st = senders.get(tid)
        if st is not None:
            senders.move_to_end(tid)
            return st
        st = senders[tid] = Sender(tid, t)
        while len(senders) > self.max_senders:
            _, old = senders.popitem(last=False)
            self._ungrid(old)
        return st

    def forget(self, tid: int) -> None:
        """Drop the state of ``tid`` (its next message starts a new one)."""
        st = self.by_id.pop(tid, None)
        if st is not None:
            self._ungrid(st)

    def unheard_s(self, c: MbdConfig) -> float:
        """How long (s) a vehicle in range may go unheard, with probability
        ``c.sa_unheard_p``, given the loss measured so far (inf before any interval).

        A vehicle misses its first message with probability p (the loss rate) and each
        next one, inside a burst of mean length L, with probability q = 1 - 1/L (q = p
        for independent loss), so it is unheard for n intervals with probability about
        p q^(n-1).  p and L are counted on the senders' secMark gaps, and on the
        senders first heard after the start (within ``c.sa_warmup_max_intervals``): the
        messages they would have sent before count as lost, in one burst.  The prior is
        one lost message in one burst and one heard (an early estimate is cautious: p =
        1/2 without data); n is clamped to ``c.sa_warmup_intervals`` ..
        ``c.sa_warmup_max_intervals``."""
        nominal = self.nominal
        if not nominal:
            return math.inf
        lost, bursts = self.lost + 1, self.bursts + 1
        t0, horizon = self.t0, c.sa_warmup_max_intervals * nominal
        for t in self.early:  # first heard late: lost since the start, in one burst
            k = round((t - t0) / nominal) if t - t0 <= horizon else 0
            if k > 0:
                lost += k
                bursts += 1
        p = lost / (lost + self.heard + 1)
        q = max(p, 1.0 - bursts / lost)
        n = 1.0 + math.log(c.sa_unheard_p / p) / math.log(q) if p > c.sa_unheard_p else 1.0
        return min(max(n, c.sa_warmup_intervals), c.sa_warmup_max_intervals) * self.nominal

    def _ungrid(self, st: Sender) -> None:
        if st.cell is not None:
            i, j = st.cell
            row = self._grid.get(i)
            cell = None if row is None else row.get(j)
            if cell is not None:
                cell.discard(st.tid)
                if not cell:
                    del row[j]
                    if not row:
                        del self._grid[i]
            st.cell = None

    def _cell(self, lat: float, lon: float) -> tuple[int, int]:
        """The grid cell of ``lat``/``lon`` (the last one asked is kept: the message's
        neighbours and its acceptance ask for the same)."""
        if lat == self._last[0] and lon == self._last[1]:
            return self._last[2]
        if not self._cell_lat:
            kx, ky = scale(lat)
            self._cell_lat = self.config.grid_cell_m / ky
            self._cell_lon = self.config.grid_cell_m / max(kx, 1.0)
        cell = int(lat // self._cell_lat), int(lon // self._cell_lon)
        self._last = (lat, lon, cell)
        return cell

    def ids_near(self, lat: float, lon: float, reach: int = 1) -> list[int]:
        """Ids placed in the ``2 reach + 1`` square of cells around ``lat``/``lon``, cell
        by cell (look them up in :attr:`by_id`: the caller may be among them)."""
        i, j = self._cell(lat, lon)
        grid = self._grid
        ids: list[int] = []
        steps = _AROUND if reach == 1 else range(-reach, reach + 1)
        for di in steps:
            row = grid.get(i + di)
            if row:
                for dj in steps:
                    cell = row.get(j + dj)
                    if cell:
                        ids.extend(cell)
        return ids

    def pair_dt(self, o: Sender, t: float, sm: int | None) -> float:
        """Time (s) from ``o``'s last accepted message to a message with secMark ``sm``
        received at ``t``: on secMark (one UTC minute for all senders) when it agrees with
        the receive clock, else that."""
        m = o.acc
        dt_rx = t - m.t
        if not abs(dt_rx) < 1e9:
            return math.inf
        if sm is not None and m.sm is not None:
            d = wrapped_dt(sm, m.sm, dt_rx)
            if abs(d - dt_rx) <= self.config.max_clock_skew_s:
                return d
        return dt_rx

    def accept(self, st: Sender, m: Msg, anchor_i: int, reset: bool) -> None:
        """``m`` becomes ``st``'s reference: its history drops the ``anchor_i`` messages
        before the anchor (all of them when ``reset``: a new baseline), and the grid
        places it at ``m``."""
        if st.acc is not None and m.sm is not None and st.acc.sm is not None:
            dt = m.ts - st.acc.ts
            if 0.0 < dt <= self.config.max_time_delta_s:
                self.interval = dt if not self.interval else \
                    0.98 * self.interval + 0.02 * dt
            if dt >= self.config.min_interval_s:
                self._loss(st, dt)
        st.acc = m
        if reset:
            st.hist = [m]
        else:
            if anchor_i:
                del st.hist[:anchor_i]
            st.hist.append(m)
            if len(st.hist) > _HISTORY:
                del st.hist[:-_HISTORY]
        off = m.t - m.ts
        if off < st.min_off:
            st.min_off = off
        cell = self._cell(m.lat, m.lon)
        if cell != st.cell:
            self._ungrid(st)
            self._grid.setdefault(cell[0], {}).setdefault(cell[1], set()).add(st.tid)
            st.cell = cell

    def arrived(self, t: float) -> None:
        """A sender's first message, received at ``t``: kept for :meth:`unheard_s`."""
        if len(self.early) < _EARLY and t - self.t0 <= 60.0:
            self.early.append(t)

    def _loss(self, st: Sender, dt: float) -> None:
        """An in-order interval ``dt`` (s, secMark) of ``st``: the messages missing in it,
        on its shortest interval so far (a gap over a minute, or over 100 intervals, is a
        vehicle that was away, not loss)."""
        nominal = st.nominal
        if not nominal or dt < nominal:
            st.nominal = nominal = dt
        k = round(dt / nominal)
        if k > 100 or dt > 60.0:
            return
        self.nominal = nominal if not self.nominal else 0.98 * self.nominal + 0.02 * dt / k
        self.heard += 1
        if k > 1:
            self.lost += k - 1
            self.bursts += 1
