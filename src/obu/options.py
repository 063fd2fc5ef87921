"""The flags of ``obu run`` and the settings it takes when neither a flag nor
``--config FILE.toml`` gives them (docs/architecture.md, "Command-line contracts";
:func:`hil.config.merge`)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from catc.predict import NAMES
from hil.capture.schema import OBU_MBD, OBU_MBR
from hil.config import add_can_arguments, address, non_negative, positive, web_address

__all__ = ["DEFAULTS", "GPSD_PORT", "GnssSpec", "add_arguments", "gnss_spec", "latency",
           "urgent_limit"]

#: gpsd's port.
GPSD_PORT = 2947

DEFAULTS = {
    "transport": "udp", "listen": ("127.0.0.1", 4500), "host_listen": ("127.0.0.1", 4501),
    "predictor": "hgp", "capture": None, "overwrite": False, "duration": None, "idle_exit": None,
    "warnings": None, "collect_ms": 5.0, "can_interface": "virtual", "can_channel": None,
    "can_fd": False, "progress": True, "max_tracks": 1000, "verify": "off", "trust": None,
    "verify_policy": "on-demand", "verify_queue": 2000, "verify_workers": 1,
    "verify_urgent": 2000.0, "shed_after": "off", "mbd": False,
    "web": None, "host_id": None, "signatures": "strict",
    "capture_max_mb": None, "host_source": "channel", "vehicle": "toyota-rav4-2017",
    "dbc": None, "vehicle_can_interface": "virtual", "vehicle_can_channel": None,
    "vehicle_can_fd": False, "gnss": None, "gnss_delay": 0.1, "gnss_latency": "auto",
    "time_scale": 1.0,
}


@dataclass(frozen=True)
class GnssSpec:
    """Where the fixes come from (``--gnss``): ``udp`` (host, port), ``serial`` (path,
    baud) or ``gpsd`` (host, port)."""

    kind: str
    host: str = "127.0.0.1"
    port: int = GPSD_PORT
    path: str = ""
    baud: int | None = None

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.path}" + (f"@{self.baud}" if self.baud else "")
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.kind}:{host}:{self.port}"


def urgent_limit(text: str) -> float | str:
    """``--verify-urgent`` and ``--shed-after``: ``off`` or a number above 0 (ECDSA/s,
    seconds); the argparse ``type``."""
    return "off" if text == "off" else positive(text)


def gnss_spec(text: str) -> GnssSpec:
    """``--gnss``: ``udp:HOST:PORT``, ``serial:PATH[@BAUD]`` or ``gpsd[:HOST[:PORT]]``
    (default 127.0.0.1:2947); the argparse ``type``."""
    kind, _, rest = text.partition(":")
    if kind == "udp":
        return GnssSpec("udp", *address(rest))
    if kind == "serial" and rest:
        path, at, baud = rest.partition("@")
        if at and not (baud.isdigit() and int(baud) > 0):
            raise argparse.ArgumentTypeError(f"not a baud rate: {text!r}")
        return GnssSpec("serial", path=path, baud=int(baud) if at else None)
    if kind == "gpsd":
        if not rest:
            return GnssSpec("gpsd")
        if rest.count(":") == 1 or (rest.startswith("[") and "]:" in rest):
            return GnssSpec("gpsd", *address(rest))
        return GnssSpec("gpsd", rest.strip("[]"), GPSD_PORT)  # a host alone
    raise argparse.ArgumentTypeError(
        f"not a GNSS source: {text!r} (udp:HOST:PORT, serial:PATH[@BAUD], "
        f"gpsd[:HOST[:PORT]])")


def latency(text: str) -> str | float:
    """``--gnss-latency``: ``auto`` (measured against the wheel speed) or 0..1 s."""
    if text == "auto":
        return text
    value = non_negative(text)
    if value > 1.0:
        raise argparse.ArgumentTypeError(f"a latency from 0 to 1 s, got {text}")
    return value


def temporary_id(text: str) -> int:
    """A J2735 TemporaryID (4 octets) as hex (``0x1a2b3c4d`` or ``1a2b3c4d``)."""
    try:
        value = int(text, 16)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a hex TemporaryID: {text!r}") from None
    if not 0 <= value < 2 ** 32:
        raise argparse.ArgumentTypeError(f"a TemporaryID is 4 octets: {text!r}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``obu run`` (docs/architecture.md, "Command-line contracts"); unset ones
    come from --config."""
    p.add_argument("--config", metavar="FILE.toml", help="settings file; flags override it")
    p.add_argument("--transport", choices=("udp", "can"), help="udp (default) or can")
    p.add_argument("--listen", type=address, help="UDP HOST:PORT of the RV frames "
                   "(default 127.0.0.1:4500)")
    p.add_argument("--host-listen", type=address, help="UDP HOST:PORT of the host "
                   "vehicle's frames (default 127.0.0.1:4501)")
    p.add_argument("--host-id", type=temporary_id, metavar="HEX",
                   help="the host vehicle's TemporaryID (hex, as the captures write it): "
                        "host frames of any other id are not believed (default: the first "
                        "id heard on the host channel)")
    p.add_argument("--predictor", choices=NAMES, help="tracking predictor (default hgp)")
    p.add_argument("--capture", metavar="DIR", help="capture directory (see --help)")
    p.add_argument("--capture-max-mb", type=positive, metavar="MB",
                   help="keep the OBU's capture files within MB megabytes: they are written "
                        "in segments of MB/10, and the oldest segments but the first are "
                        "deleted (the run's start and its latest minutes are kept; "
                        "captures score names what is missing); default: no cap")
    p.add_argument("--overwrite", action="store_true", default=None,
                   help="replace an OBU run already in the capture directory (refused "
                        "without)")
    p.add_argument("--duration", type=positive, metavar="S", help="stop after S s (wall clock)")
    p.add_argument("--idle-exit", type=positive, metavar="S",
                   help="stop once no frame has arrived for S s (after the first)")
    p.add_argument("--warnings", metavar="FILE", help="warning events as JSON lines here "
                   "instead of stdout")
    p.add_argument("--collect-ms", type=non_negative, help="longest wait for the RV channel to go "
                   "quiet before a step, after the frames already received are taken "
                   "(default 5)")
    p.add_argument("--max-tracks", type=int, help="most RVs tracked at once (default 1000)")
    add_can_arguments(p)
    p.add_argument("--verify", choices=("off", "log", "enforce"),
                   help="IEEE 1609.2 verification of the RV frames: off (default), log "
                        "(verify and record the verdict, track every frame) or enforce "
                        "(drop what does not verify); needs --trust")
    p.add_argument("--verify-policy", choices=("on-demand", "all"),
                   help="when --verify enforce runs each frame's ECDSA: on-demand (default: "
                        "the cheap checks on arrival, ECDSA at once for the RVs that could "
                        "warn or are new, the rest queued by threat and verified in idle "
                        "time; no warning rests on an unverified message; with spare "
                        "capacity every frame is verified) or all (every frame on arrival); "
                        "--verify log verifies all")
    p.add_argument("--verify-queue", type=int, metavar="N",
                   help="verify on demand: most frames waiting for their ECDSA; beyond, the "
                        "oldest of the lowest threat are dropped unverified and counted "
                        "(ondemand_skipped) (default 2000)")
    p.add_argument("--verify-workers", type=int, metavar="N",
                   help="verify on demand: processes (nice +10) that verify the queued "
                        "frames beside the OBU's own idle time; 0: none (default 1)")
    p.add_argument("--shed-after", type=urgent_limit, metavar="S|off",
                   help="an OBU behind real time drops the frames that waited longer than S "
                        "s for it, undecoded (shed_rv, shed_host; a host frame dropped is a "
                        "missed tick), to catch up; off: never (default)")
    p.add_argument("--verify-urgent", type=urgent_limit, metavar="N|off",
                   help="verify on demand: the ECDSA/s run at once for what frames claim of "
                        "themselves (a new RV, hard braking), all senders together, and "
                        "at most 20/s per TemporaryID; an urgent frame beyond waits first "
                        "in the queue and is withheld from its tick until verified "
                        "(ondemand_held, ondemand_withheld); off: unbounded (default 2000)")
    p.add_argument("--signatures", choices=("strict", "standard"),
                   help="signature encodings --verify accepts: strict (default: rSig x-only "
                        "and low s, the one form nobody can derive from another) or "
                        "standard (every form IEEE 1609.2 allows: rSig as a point, high s, "
                        "as real senders use; replays are caught either way)")
    p.add_argument("--trust", metavar="PATH",
                   help="trust store for --verify: a PKI directory (rve pki init: its root "
                        "is trusted, its AA known) or a root certificate .oer file")
    p.add_argument("--web", type=web_address, metavar="[HOST:]PORT",
                   help="serve the live view (a web page of the map, /api/state) here; "
                        "127.0.0.1 unless a host is named; off by default")
    p.add_argument("--mbd", action="store_true", default=None,
                   help="misbehavior detection (catc.mbd: F2MD's plausibility checks) on "
                        "every RV frame that passes verification: findings go to "
                        f"{OBU_MBD}, reports (past the reporting threshold) to {OBU_MBR}, "
                        "and a quarantined sender is not tracked")
    add_vehicle_arguments(p)
    p.add_argument("--no-progress", dest="progress", action="store_false", default=None,
                   help="no status line on stderr")


def gnss_delay(text: str) -> float:
    """``--gnss-delay``: 0..5 s."""
    value = non_negative(text)
    if value > 5.0:
        raise argparse.ArgumentTypeError(f"a delay from 0 to 5 s, got {text}")
    return value


def add_vehicle_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``--host-source vehicle`` (:mod:`obu.vehicle`)."""
    p.add_argument("--host-source", choices=("channel", "vehicle"),
                   help="where the host vehicle's own state comes from: channel (default: "
                        "a ready-made BSM on the private host channel, --host-listen or "
                        "the host CAN id) or vehicle (its CAN bus and a GNSS receiver, "
                        "fused; needs --gnss)")
    p.add_argument("--vehicle", metavar="PROFILE",
                   help="vehicle profile: a shipped name or a JSON file "
                        "(default toyota-rav4-2017)")
    p.add_argument("--dbc", metavar="PATH", help="a full DBC of the car, read instead of "
                   "the profile's own")
    p.add_argument("--vehicle-can-interface",
                   choices=("socketcan", "virtual", "udp_multicast", "slcan"),
                   help="python-can interface of the car's bus (default virtual), or slcan: "
                        "a serial USB-CAN adapter (Lawicel ASCII: CANable, USBtin) at the "
                        "channel's PATH[@BAUD], or rve's on a pty")
    p.add_argument("--vehicle-can-channel", metavar="NAME",
                   help="the car's CAN channel, e.g. can0 (default per interface: can0, "
                        "catc-vehicle, 239.74.163.3, /dev/ttyACM0)")
    p.add_argument("--time-scale", type=positive, metavar="N",
                   help="with --host-source vehicle: the car's time runs N times this "
                        "process's (a bench replaying the vehicle side at rve run --speed "
                        "N); 1 on a real car (default)")
    p.add_argument("--vehicle-can-fd", action="store_true", default=None,
                   help="the car's bus is CAN FD")
    p.add_argument("--gnss", type=gnss_spec, metavar="SPEC",
                   help="the GNSS receiver: udp:HOST:PORT (NMEA datagrams), "
                        "serial:PATH[@BAUD] (NMEA on a serial device or pty) or "
                        "gpsd[:HOST[:PORT]] (gpsd's JSON; default 127.0.0.1:2947)")
    p.add_argument("--gnss-delay", type=gnss_delay, metavar="S",
                   help="how long after its UTC stamp a fix's sentences arrive, for the "
                        "clock (default 0.1: a typical receiver's, and rve run "
                        "--host-bus's; the comma2k19 u-blox's is 0.2)")
    p.add_argument("--gnss-latency", type=latency, metavar="auto|S",
                   help="how old a fix's position is when it arrives: auto (default: "
                        "0.1 s until a fit against the wheel-speed odometry is sure) or S "
                        "seconds (0..1)")
