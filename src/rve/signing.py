"""IEEE 1609.2 signing of the RVs' BSMs (``rve run --sign PKI_DIR``): one pseudonym
certificate of the PKI per remote vehicle, and the attackers' identities.

The host vehicle's channel stays unsigned.  :mod:`catc.security` builds the SignedData;
this module decides who signs with which certificate, and when the full certificate goes
in place of its digest.
"""

from __future__ import annotations

import argparse
from typing import Any

from catc.replay import Plan

__all__ = ["Signer", "make_signer"]


class Signer:
    """IEEE 1609.2 signing of the RVs' BSMs (``--sign``), one pseudonym per vehicle.

    The signer is the full certificate in a vehicle's first BSM, then at least once per
    second of data time, and in its next BSM after a vehicle it has not heard before
    starts sending (SAE J2945/1's rule: a new neighbour may not know our certificate);
    otherwise its HashedId8 digest.  The decisions follow the data's clock, so a run
    repeats them exactly; generationTime is the wall-clock deadline of the frame.
    """

    CERT_PERIOD_S = 1.0

    def __init__(self, pki: Any, n_vehicles: int, host_index: int) -> None:
        from catc.security import unix_to_time64

        rvs = n_vehicles - 1
        if len(pki.pseudonyms) < rvs:
            raise ValueError(f"--sign {pki.directory}: {len(pki.pseudonyms)} pseudonym "
                             f"certificates for {rvs} remote vehicles (rve pki init "
                             f"--vehicles {rvs})")
        self.to_time64 = unix_to_time64
        others = [i for i in range(n_vehicles) if i != host_index]
        #: each RV's pseudonym: its index in the PKI (what a signing worker is told) and
        #: its (certificate, key)
        self.pseudonym = {v: k for k, v in enumerate(others)}
        self.identity = {v: pki.pseudonyms[k] for k, v in enumerate(others)}
        self.last_cert: dict = {}
        self.owed: set = set()
        self.heard: set = set()
        self.counts = {"signed": 0, "with_certificate": 0}
        # the attackers' identities: an insider holds the PKI's first pseudonym that no RV
        # uses; an outsider, a pseudonym of the untrusted foreign PKI
        self.insider = pki.pseudonyms[rvs] if len(pki.pseudonyms) > rvs else None
        self.outsider = pki.foreign[0] if pki.foreign else None
        self.directory = pki.directory

    def attacker(self, who: str) -> tuple[Any, Any]:
        """The (certificate, key) of an ``insider`` or ``outsider`` attacker."""
        ident = self.insider if who == "insider" else self.outsider
        if ident is None:
            raise ValueError(
                f"--sign {self.directory}: no {who} identity for the attack ("
                + ("rve pki init --vehicles N with N > the number of RVs)" if who == "insider"
                   else "the PKI has no foreign/ directory)"))
        return ident

    def decide(self, vehicle: object, t: float) -> bool:
        """Whether ``vehicle``'s BSM of data time ``t`` carries the full certificate (else
        its digest); counts it as signed.  Called in schedule order, once per frame."""
        if vehicle not in self.heard:  # a new sender: everybody else owes its certificate
            self.heard.add(vehicle)
            self.owed.update(v for v in self.heard if v != vehicle)
        last = self.last_cert.get(vehicle)
        full = last is None or t - last >= self.CERT_PERIOD_S - 1e-9 or vehicle in self.owed
        if full:
            self.last_cert[vehicle] = t
            self.owed.discard(vehicle)
            self.counts["with_certificate"] += 1
        self.counts["signed"] += 1
        return full

    def sign(self, vehicle: object, frame: bytes, t: float, gen_unix: float,
             identity: tuple[Any, Any] | None = None) -> bytes:
        """``frame`` signed by ``vehicle``'s pseudonym (or ``identity``, an attacker's
        (certificate, key), for a fabricated sender ``vehicle``)."""
        from catc.security import sign_bsm

        full = self.decide(vehicle, t)
        cert, key = identity or self.identity[vehicle]
        return sign_bsm(frame, key, cert, self.to_time64(gen_unix), include_cert=full)


def make_signer(args: argparse.Namespace, the_plan: Plan) -> Signer | None:
    """The --sign PKI's signer for this plan, or None (ValueError when it does not fit)."""
    if not args.sign:
        return None
    from hil.pki import load

    return Signer(load(args.sign), len(the_plan.vehicles),
                  list(the_plan.vehicles).index(the_plan.host_id))
