"""``rve run --sign --sign-workers N`` (:mod:`rve.signahead`): frames signed ahead of the
schedule by worker processes verify, carry the same signer decisions (full certificate
or digest, which pseudonym) as the inline path, and their generationTime is each frame's
deadline."""

from __future__ import annotations

import argparse
import asyncio
import time

import pytest

from catc.channel import ChannelConfig
from catc.j2735.ieee1609 import unwrap
from catc.replay import plan
from catc.security import Verifier, time64_to_unix
from hil.datasets import load_table
from hil.pki import init, load
from hil.transport import Sender
from rve import run as rve_run

SPEED = 4.0


class _Sink(Sender):
    """A sender that keeps what it is given: (channel, frame, wall time, monotonic)."""

    def __init__(self) -> None:
        self.local: dict = {}
        self.stats: dict = {}
        self.sent: list[tuple[str, bytes, float, float]] = []

    async def send(self, frame: bytes) -> None:
        self.sent.append(("rv", frame, time.time(), time.monotonic()))

    async def send_host(self, frame: bytes) -> None:
        self.sent.append(("host", frame, time.time(), time.monotonic()))

    async def aclose(self) -> None:
        pass


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki") / "pki"
    init(d, 20, 1.0, seed="sign-ahead", foreign=False)
    return d


def _run(pki, workers: int, monkeypatch) -> tuple[dict, list, object]:
    sink = _Sink()

    async def opened(args, on_frame):
        return sink

    monkeypatch.setattr(rve_run, "_open_sender", opened)
    args = argparse.Namespace(**dict(rve_run.DEFAULTS, sign=str(pki), speed=SPEED,
                                     progress=False, per=20.0, sign_workers=workers))
    the_plan = plan(load_table(args.dataset, None), ChannelConfig(per=0.2), 5, None, 4.0)
    lateness: list[float] = []
    counts = asyncio.run(rve_run.replay(args, the_plan, lateness))
    return counts, [s for s in sink.sent if s[0] == "rv"], the_plan


def test_frames_signed_ahead_verify_with_the_inline_path_s_decisions(pki, monkeypatch):
    inline, inline_frames, _ = _run(pki, 0, monkeypatch)
    ahead, ahead_frames, the_plan = _run(pki, 2, monkeypatch)
    assert "sign_ahead_batches" not in inline  # --sign-workers 0: inline, as before
    ticks = {float(ev["time"]) for ev in the_plan.events if not ev["host"]
             and not ev["dropped"]}
    assert ahead["sign_ahead_batches"] == len(ticks)
    assert ahead["signed"] == inline["signed"] == ahead["sent"] == len(ahead_frames) > 100
    assert ahead["with_certificate"] == inline["with_certificate"] < ahead["signed"]
    assert ahead["sign_ahead_waits"] == 0, ahead
    pki_files = load(pki)
    verifier = Verifier([pki_files.root], certificates=[pki_files.aa])
    gens = []
    for (_, a, wall, _), (_, b, _, _) in zip(ahead_frames, inline_frames, strict=True):
        ua, ub = unwrap(a), unwrap(b)
        assert ua.frame == ub.frame  # the same BSM, from the same pseudonym, the same way
        assert (ua.signer_kind, ua.signer_digest) == (ub.signer_kind, ub.signer_digest)
        assert ua.signature != ub.signature
        verdict = verifier.verify(a, ua.generation_time_us)
        assert verdict.ok, verdict.reason
        gen = time64_to_unix(ua.generation_time_us)
        assert gen <= wall + 1e-3  # never sent before its deadline (1 ms: Time64's µs)
        gens.append(gen)
    # generationTime is the deadline: start + (due - t0) / speed, to the µs
    sent = [ev for ev in the_plan.events if not ev["host"] and not ev["dropped"]]
    t0 = float(the_plan.events["time"][0])
    start = gens[0] - (float(sent[0]["time"]) - t0) / SPEED
    for ev, gen in zip(sent, gens, strict=True):
        assert gen == pytest.approx(start + (float(ev["time"]) - t0) / SPEED, abs=2e-6)
    # and the frames left at their deadlines
    late = [wall - gen for (_, _, wall, _), gen in zip(ahead_frames, gens, strict=True)]
    assert sorted(late)[len(late) // 2] < 0.05
