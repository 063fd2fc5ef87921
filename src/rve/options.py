"""The settings of ``rve run``: its flags and their defaults (docs/architecture.md,
"Command-line contracts").

A flag left unset is ``None`` here and comes from ``--config`` or :data:`DEFAULTS`
(:func:`hil.config.run_daemon` merges them).
"""

from __future__ import annotations

import argparse

from catc.attacks import KINDS
from hil.config import add_can_arguments, destination, non_negative, percent, positive

__all__ = ["DEFAULTS", "add_arguments"]

#: Settings when neither a flag nor the config file gives them.
DEFAULTS = {
    "dataset": "scenario:highway-braking", "transport": "udp", "to": ("127.0.0.1", 4500),
    "host_to": ("127.0.0.1", 4501), "per": 0.0, "burst": 1.0, "rate": 10.0, "latency": 0.0,
    "jitter": 0.0, "seed": 0, "speed": 1.0, "asap": False, "capture": None, "overwrite": False,
    "duration": None, "host": None, "trip": None, "ieee1609": False, "distance": False,
    "can_interface": "virtual", "can_channel": None, "can_fd": False, "progress": True,
    "idm_host": None, "sign": None, "sign_workers": 1, "sign_lookahead": 1.0,
    "framing": None, "attack": None,
    "host_bus": False, "host_can_interface": "virtual", "host_can_channel": None,
    "host_can_fd": False, "radar_can_channel": None, "nmea": None,
    "vehicle": "toyota-rav4-2017", "dbc": None, "gnss_noise": 0.5, "gnss_latency": 100.0,
    "gnss_loss": 0.0, "gnss_outage": None,
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``rve run`` (docs/architecture.md, "Command-line contracts"); unset ones
    come from --config."""
    p.add_argument("--config", metavar="FILE.toml", help="settings file; flags override it")
    p.add_argument("--dataset", metavar="SPEC",
                   help="PATH, KIND:PATH or scenario:NAME (default scenario:highway-braking)")
    p.add_argument("--trip", metavar="NAME", help="which trip of a multi-trip dataset "
                   "(default the first)")
    p.add_argument("--host", metavar="ID", help="host vehicle (default: the dataset's)")
    p.add_argument("--idm-host", metavar="LEADER", help="add a synthetic host vehicle that "
                   "follows LEADER with the IDM car-following model (catc.hostsim) and use it")
    p.add_argument("--transport", choices=("udp", "can"), help="udp (default) or can")
    p.add_argument("--to", type=destination, help="UDP HOST:PORT of the RV frames "
                   "(default 127.0.0.1:4500)")
    p.add_argument("--host-to", type=destination, help="UDP HOST:PORT of the host "
                   "vehicle's frames (default 127.0.0.1:4501)")
    p.add_argument("--per", type=percent, help="packet error rate, %% (default 0)")
    p.add_argument("--burst", type=positive, help="mean burst length in messages; 1 = "
                   "independent losses (default 1)")
    p.add_argument("--rate", type=positive, help="transmission rate, 1-10 Hz (default 10)")
    p.add_argument("--latency", type=non_negative, metavar="MS", help="fixed latency, ms")
    p.add_argument("--jitter", type=non_negative, metavar="MS", help="each frame is delayed a "
                   "further U(0, jitter) ms; reordering happens")
    p.add_argument("--distance", action="store_true", default=None,
                   help="also lose messages by HV-RV distance (catc.channel curve)")
    p.add_argument("--seed", type=int, help="seed of the loss and jitter pattern")
    p.add_argument("--speed", type=positive, help="replay speed factor (default 1 = real time)")
    p.add_argument("--asap", action="store_true", default=None,
                   help="send as fast as possible (no pacing)")
    p.add_argument("--duration", type=positive, metavar="S", help="stop after S s of data")
    p.add_argument("--capture", metavar="DIR", help="capture directory (see rve run --help)")
    p.add_argument("--overwrite", action="store_true", default=None,
                   help="replace an RVE run already in the capture directory (refused "
                        "without)")
    p.add_argument("--ieee1609", action="store_true", default=None,
                   help="wrap each frame in an unsecured IEEE 1609.2 envelope "
                        "(= --framing 1609)")
    p.add_argument("--framing", choices=("uper", "1609", "wsmp"),
                   help="what goes on the wire: the bare UPER MessageFrame (default), an "
                        "IEEE 1609.2 Ieee1609Dot2Data, or that inside an IEEE 1609.3 WSMP "
                        "WAVE Short Message (PSID 0x20); --sign implies 1609")
    p.add_argument("--sign", metavar="PKI_DIR",
                   help="sign every RV's BSM as IEEE 1609.2 SignedData with a pseudonym "
                        "certificate of PKI_DIR (rve pki init); the host channel stays "
                        "unsigned")
    p.add_argument("--sign-workers", type=_count, metavar="N",
                   help="sign in N worker processes ahead of the schedule (rve.signahead; "
                        "0: in the sending loop; --asap and --attack runs always do that) "
                        f"(default {DEFAULTS['sign_workers']})")
    p.add_argument("--sign-lookahead", type=positive, metavar="S",
                   help="how far ahead of the sending loop the workers sign, s of "
                        f"schedule (default {DEFAULTS['sign_lookahead']:g})")
    p.add_argument("--attack", action="append", metavar="KIND[:KEY=VALUE,...]",
                   help=f"add a misbehaving sender (repeatable): {', '.join(KINDS)}; each "
                        "message is labelled in rve.schedule.jsonl (catc.attacks has the "
                        "parameters)")
    add_can_arguments(p)
    _add_host_bus_arguments(p)
    p.add_argument("--no-progress", dest="progress", action="store_false", default=None,
                   help="no progress line on stderr")


def _count(text: str) -> int:
    """A whole number >= 0 (argparse type)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _add_host_bus_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``--host-bus`` (:mod:`rve.hostbus`)."""
    from rve.hostbus import nmea_spec

    g = p.add_argument_group(
        "the host vehicle's own bus (--host-bus)",
        "The host's CAN frames, encoded through a vehicle profile's DBC, and NMEA 0183\n"
        "from a simulated GNSS receiver, made from the host's trajectory (or replayed\n"
        "from the dataset's recording).  With --host-bus the host's state is NOT sent as\n"
        "a BSM on the private host channel (--host-to or the host's ISO-TP id): it goes\n"
        "to the vehicle side only.")
    g.add_argument("--host-bus", action="store_true", default=None,
                   help="send the host's CAN bus and GNSS instead of its private channel")
    g.add_argument("--host-can-interface",
                   choices=("socketcan", "virtual", "udp_multicast", "slcan"),
                   help="python-can interface of the host CAN bus (default virtual), or "
                        "slcan: play a serial USB-CAN adapter (Lawicel ASCII) on a pty whose "
                        "slave the channel (a path) links to, for obu run "
                        "--vehicle-can-interface slcan")
    g.add_argument("--host-can-channel", metavar="NAME",
                   help="host CAN channel (default vcan1, catc-hil-host, 239.74.163.3 or "
                        "catc-hil-can.pty by interface)")
    g.add_argument("--host-can-fd", action="store_true", default=None,
                   help="send the host's frames as CAN FD frames")
    g.add_argument("--radar-can-channel", metavar="NAME",
                   help="a recorded dataset's bus 1 (the radar) goes here (default: not "
                        "sent)")
    g.add_argument("--nmea", type=nmea_spec, metavar="SPEC",
                   help="where the NMEA goes: udp:HOST:PORT (a datagram per epoch), "
                        "pty:PATH (PATH links to a pseudo-terminal, e.g. for gpsd) or "
                        "file:PATH (appended); default nowhere")
    g.add_argument("--vehicle", metavar="PROFILE",
                   help="vehicle profile: a shipped name or a JSON file (default "
                        "toyota-rav4-2017)")
    g.add_argument("--dbc", metavar="PATH", help="encode through this DBC instead of the "
                   "profile's own")
    g.add_argument("--gnss-noise", type=non_negative, metavar="M",
                   help="standard deviation of the position error, m (default 0.5; "
                        "Gauss-Markov, 10 s correlation time)")
    g.add_argument("--gnss-latency", type=non_negative, metavar="MS",
                   help="each fix is sent this long after its UTC epoch (default 100: a "
                        "typical receiver's, and obu run --gnss-delay's default)")
    g.add_argument("--gnss-loss", type=percent, metavar="PCT",
                   help="probability that an epoch is lost, %% (default 0)")
    g.add_argument("--gnss-outage", action="append", metavar="START:DURATION",
                   help="no fixes for DURATION s from START s after the start (repeatable)")
