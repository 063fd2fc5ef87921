"""The OBU daemon's state, and the two things that change it: a frame received
(:meth:`Obu.frame`) and a tick stepped at a host frame (:meth:`Obu.tick`), with the
tick's outputs (warnings, capture, live view).  The event loop that calls them is
:func:`obu.run.serve`."""

from __future__ import annotations

import argparse
import json
import sys
import time
from itertools import islice
from pathlib import Path
from typing import Any

from catc.apps import SafetyApps
from catc.bsm import BSM
from catc.cam import CamConfig, ContextAwareMap, MapSnapshot, SecMarkClock, warm_up
from hil.capture import schema
from hil.errors import write_error
from obu.capture import ObuCapture, Received
from obu.frames import Frames
from obu.status import RateLimitedLog, Status
from obu.tick import TICK_S, TickRule

__all__ = ["PRE_TICK_MAX_S", "PRE_TICK_SPARE_S", "Obu"]

#: Verify on demand: before a step, queued frames are verified for at most this long (s) ...
PRE_TICK_MAX_S = 0.02
#: ... and only while the tick can still be decided within its period of its host
#: frame's arrival, with the longest of the last 20 steps and this much to spare (s).
PRE_TICK_SPARE_S = 0.01


class Obu:
    """The daemon's state: the CAM, the clock, the receive path with its pending messages,
    the tick rule, the counters, the capture and the warnings' output."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        config = CamConfig(predictor=args.predictor, max_tracks=args.max_tracks)
        self.cam = ContextAwareMap(config, SafetyApps())
        # the compiled kernels and lazy imports of a tick, before the first one: at
        # the start every RV is new and verified at once, no time for one-off costs
        warm_up(config, SafetyApps())
        self.clock = SecMarkClock()
        self.gc: Any = None  # the GcPolicy, once serve() has started everything
        self.status = Status()
        self.counters = self.status.counters
        self.log = RateLimitedLog()
        self.cap = ObuCapture(Path(args.capture), args) if args.capture else None
        self.warn_out = (open(args.warnings, "a", encoding="utf-8")  # noqa: SIM115
                         if args.warnings else sys.stdout)
        self.frames = Frames(args, self.counters, self.log, self.clock, self.cap,
                             self.cam.drop)
        self.rule = TickRule(args.collect_ms)
        shed = getattr(args, "shed_after", None)
        self.shed_after = None if shed in (None, "off") else float(shed)
        self.host_arrival = 0.0  # the ticking host frame's arrival (unix s)
        self.last_frame = self.last_rv = time.monotonic()
        self.web: Any = None  # the live view's hub (obu.web.Hub) when --web is on
        self.vehicle: Any = None  # obu.vehicle.VehicleHost with --host-source vehicle

    def frame(self, channel: str, data: bytes, rx_unix: float) -> BSM | None:
        """One received frame (:meth:`obu.frames.Frames.take`): the host's BSM when it
        is a host frame that decodes (it triggers a tick), else None.

        An OBU behind real time drops what waited longer than ``--shed-after`` before it
        got to it (``shed_rv``, ``shed_host``; status ``shed``): undecoded, unverified,
        so that it catches up instead of staying behind; a host frame dropped is a tick
        not stepped, counted as a missed deadline (``deadline_misses_shed``)."""
        self.counters["frames"] += 1
        self.counters[f"frames_{channel}"] += 1
        shed = self.shed_after
        if shed is not None and time.time() - rx_unix > shed:
            self.counters[f"shed_{channel}"] += 1
            if channel == "host":
                self.counters["deadline_misses_shed"] += 1
                self.counters["deadline_misses"] += 1
            self.log("shed", f"behind real time: frames that waited over {shed:g} s dropped")
            if self.cap is not None:
                self.cap.frame(rx_unix, channel, data, "shed")
            return None
        self.last_frame = time.monotonic()
        if channel == "rv":  # any datagram, decodable or not: the channel is not quiet
            self.last_rv = self.last_frame
            self.rule.rv_frame(self.last_frame)
        return self.frames.take(channel, data, rx_unix)

    def begin(self, host: BSM) -> None:
        """Host frame ``host`` (believed: :meth:`frame` returned it) starts its tick:
        collect its frames (:mod:`obu.tick`), then :meth:`tick`."""
        self.host_arrival = self.frames.start_tick(host)
        self.rule.host_frame(time.monotonic())

    def tick(self, host: BSM) -> MapSnapshot | None:
        """Step the CAM at host frame ``host`` (:mod:`obu.tick`), after :meth:`begin`.

        A tick misses its deadline (``deadline_misses``) when its step takes longer than
        the tick period (``deadline_misses_step``) or when it is decided more than a tick
        period after its host frame arrived (``deadline_misses_late``: the OBU is behind,
        its data older than the deadline).  The lag from each message's arrival (or from
        the host frame's, for a message that came before it) to the decision is kept
        (:class:`obu.status.Lags`)."""
        now = self.clock(host.sec_mark)
        self.frames.pump()  # what the workers verified counts at this tick
        self._verify_before_step()
        due = self.frames.due(now, self.cam.config.max_future_s)
        unverified = self.frames.unverified(due)
        if self.frames.mbd is not None:  # unconfirmed newcomers raise no warning
            self.cam.apps.muted = self.frames.mbd.muted(now)
        t0 = time.perf_counter()
        try:
            snap = self.cam.step(now, host, due, unverified)
        except ValueError as err:  # time going backwards on the host channel
            self.counters["host_rejected"] += 1
            self.counters["host_backwards"] += 1
            self.log("host", f"host frame rejected: {err}")
            return None
        ms = (time.perf_counter() - t0) * 1000.0
        self.status.step_ms.append(ms)
        self.counters["ticks"] += 1
        decided = time.time()
        slow = ms > TICK_S * 1000.0
        late = decided - self.host_arrival > TICK_S
        self.counters["deadline_misses_step"] += slow
        self.counters["deadline_misses_late"] += late
        self.counters["deadline_misses"] += slow or late
        received = self.frames.received(due)
        # from arrival, or from the host frame's when the message came before it: no
        # message can be used before the host frame that ticks it (a message dated ahead
        # of the host waits for its tick by rule, not because the OBU is behind)
        start = self.host_arrival
        lags = [(decided - max(rx, start)) * 1000.0 for _, rx, _, _, _ in received
                if rx is not None]
        self.status.lag.add(lags)
        self.status.lag_recent.add(lags)
        self.status.host_lag.add([(decided - self.host_arrival) * 1000.0])
        self._outputs(snap, host, ms, decided, received)
        self.frames.new_snapshot(snap)
        if self.web is not None:
            if self.web.clients or self.web.polled:
                self._publish(snap, host)
            else:  # nobody looks yet: keep the tick, build its state on the first look
                self.web.unbuilt = lambda: self._state(snap, host)
        return snap

    def _verify_before_step(self) -> None:
        """Verify on demand: work the queue before the step, within its budget
        (:data:`PRE_TICK_MAX_S`, :data:`PRE_TICK_SPARE_S`): the frames it reaches are
        trusted at this tick."""
        if not self.frames.queued():
            return
        step_s = max(islice(reversed(self.status.step_ms), 20), default=0.0) / 1000.0
        spare = self.host_arrival + TICK_S - time.time() - step_s - PRE_TICK_SPARE_S
        budget = min(PRE_TICK_MAX_S, spare)
        if budget > 0.0:
            self.counters["ondemand_pre_tick"] += self.frames.work(
                time.monotonic() + budget, time.monotonic)

    def _publish(self, snap: MapSnapshot, host: BSM) -> None:
        """The tick's state to the live view (after the step: not in its time)."""
        self.web.publish(self._state(snap, host))

    def _state(self, snap: MapSnapshot, host: BSM) -> dict[str, Any]:
        from obu.web import tick_state

        return tick_state(snap, host.sec_mark, self.status.panel(self.cam.tentative))

    def _warn(self, text: str | None) -> None:
        """``text`` (None: nothing, a flush) to the warnings' output; a ``--warnings``
        file that cannot be written is a :class:`WriteError` that names it."""
        try:
            if text is not None:
                self.warn_out.write(text)
            self.warn_out.flush()
        except OSError as err:
            if self.warn_out is sys.stdout:
                raise
            raise write_error(err, self.args.warnings) from None

    def _outputs(self, snap: MapSnapshot, host: BSM, ms: float, decided: float,
                 received: list[Received]) -> None:
        for e in snap.events:
            rec = schema.event(e)
            self._warn(json.dumps(rec) + "\n")
            print(f"obu: {e.app.upper()} {e.kind} RV {rec['rv']} at t={rec['t']:.1f} s",
                  file=sys.stderr, flush=True)
            self.counters[f"events_{e.app}"] += 1
            if self.cap is not None:
                self.cap.event(rec)
        self._warn(None)
        self.counters["warning_ticks"] += bool(snap.warnings)
        if self.cap is None:
            return
        if not self.cap.origin_written and self.cam.frame is not None:
            f = self.cam.frame
            self.cap.write_origin([f.lat0, f.lon0, f.h0])
        self.cap.tick(snap, host.sec_mark, ms, decided, received)

    def all_counters(self, transport_stats: dict[str, int]) -> dict[str, Any]:
        """Every counter (:meth:`obu.status.Status.all_counters`), and the live view's
        (``web_``: what it refused and cut off, :mod:`obu.web`) when it is on; with
        ``--host-source vehicle`` the car's and the GNSS receiver's (``can_``, ``nmea_``,
        ``gnss_``, ``vehicle_``: :meth:`obu.vehicle.VehicleHost.all_counters`)."""
        out = self.status.all_counters(
            len(self.frames.pending), self.cam.tentative, self.cam.counters,
            transport_stats, None if self.gc is None else self.gc.counters())
        if self.frames.queue is not None:  # verify on demand: still waiting
            out["ondemand_queue"] = self.frames.queued()
        if self.web is not None:
            out.update({f"web_{k}": v for k, v in self.web.counters.items()})
        if self.vehicle is not None:
            out.update(self.vehicle.all_counters())
        return out

    def close(self, exit: str = "clean", reason: str = "",
              counters: dict[str, Any] | None = None) -> None:
        """Flush and close; ``counters`` (when given) go into the capture last, and its
        end record says how the run ended (:data:`hil.capture.schema.ENDINGS`).  A file
        that cannot be written raises (:class:`hil.errors.WriteError`) once every file is
        closed and the end record is written."""
        failure: OSError | None = None
        if self.warn_out is not sys.stdout:
            try:
                self.warn_out.close()
            except OSError as err:
                failure = write_error(err, self.args.warnings)
        if self.cap is None:
            self.frames.drain()  # the workers stop
            if failure is not None:
                raise failure
            return
        try:
            # received, never stepped (no host frame came after them): recorded all the
            # same, so that the capture has every frame the OBU received
            for r in self.frames.unticked():
                self.cap.message(r, "unticked")
            self.frames.drain()
            if counters is not None:
                self.cap.write_counters(counters)
        except OSError as err:
            failure = failure or err
        self.cap.end(exit, reason, failure, ticks=self.counters["ticks"],
                     frames=self.counters["frames"])
