"""IEEE 1609.2-2016 security for BSMs: a test PKI, signing, and a bounded verifier.

Pure: keys are ``cryptography`` objects, certificates and messages are octets; nothing
here touches files or the network (:meth:`Pki.private_pem` gives PEM octets for a CLI to
write, :func:`load_private_pem` reads them back).  The wire formats are in
:mod:`catc.j2735.ieee1609`; this package adds the cryptography (ECDSA over NIST P-256 with
SHA-256, the only algorithms it supports): ``_crypto`` time, hashing, signing;
``_pki`` keys, certificates and the test PKI; ``_verify`` the verifier; ``_replay`` its
replay cache; :mod:`~catc.security.ondemand` verify on demand (which messages to verify at
once, and the queue of the others).

Signatures (§5.3.1)
    The data to sign is hashed as ``H = SHA-256( SHA-256(data input) ||
    SHA-256(signer identifier input) )``.  The data input is the COER
    ``ToBeSignedData`` for signed messages (§6.3.4) and the COER ``ToBeSignedCertificate``
    for certificates (§6.4.8).  The signer identifier input is the canonical COER of the
    signer's certificate, or the empty string when self-signed.  ECDSA is applied to
    ``H``: here the outer SHA-256 is computed in Python and handed to ``cryptography`` as
    ``ECDSA(Prehashed(SHA256()))``.  That equals ``ECDSA(SHA256())`` over the 64-octet
    concatenation, and ``openssl dgst -sha256`` over it.  Signatures are sent as r || s
    with rSig x-only and s low (below n/2).  When the installed OpenSSL supports it,
    signing is deterministic (RFC 6979), so a seeded PKI and its signed messages are
    reproducible octet for octet.

Time (base types Time32, Time64)
    Time32 and Time64 count TAI seconds and microseconds since 2004-01-01 00:00:00 UTC.
    TAI−UTC was 32 s at that epoch and has been 37 s since 2017-01-01.  So a UTC instant
    after 2016 is ``unix − 1 072 915 200 + 5`` s in these units.  :func:`unix_to_time64`
    and :func:`time64_to_unix` apply the five leap seconds inserted since 2004 at their
    true dates (end of 2005, 2008, June 2012, June 2015, 2016).  No leap second has been
    announced after 2016; a new one would need a new table entry.  Wireshark's 1609.2
    dissector converts the same way (a test checks this).

Verification (:class:`Verifier`)
    The verifier trusts the roots it is given.  It verifies a certificate chain once and
    then keeps every verified certificate by HashedId8 in a bounded LRU cache, so a BSM
    with a cached signer costs one ECDSA verification.  A ``digest`` signer that is not
    cached yet is ``unknown-signer``: that is normal, since vehicles attach the
    certificate only now and then.

The envelope (issue 28)
    A BSM is one ``SignedData`` (hashId sha256) whose payload is ``unsecuredData``
    holding the MessageFrame, optionally in a WAVE Short Message.  What else arrives is
    refused, each with its reason:

    * ``unsigned``: unsecured data where a signature is required (the OBU's
      ``--verify``), or no 1609.2 envelope at all.
    * ``nested``: signed data inside signed data.  :func:`catc.j2735.ieee1609.unwrap`
      reports the innermost layer, the one that signs the frame; the outer layers'
      headers and signatures would go unchecked, so an outer layer could say anything.
    * ``wsmp-psid``: the WSMP header addresses another PSID than the verifier's (0x20,
      BSMs) when the frame came in a WSM (:func:`catc.j2735.open_envelope` records it).
      The headerInfo psid must be 0x20 too (``wrong-psid``).
    * The WSMP version and the ``Ieee1609Dot2Data`` protocolVersion must be 3.  Those
      are not verdicts but decode errors (:func:`catc.j2735.open_envelope`, ``unwrap``,
      ``unwrap_wsmp``: ``unsupported`` or ``garbage``), since nothing after an unknown
      version can be read: the OBU drops such a frame in every mode.
    * ``message-expired``: a headerInfo expiryTime before the receive time (or before the
      generationTime), a relevance check (§5.2) like the freshness of generationTime.

Canonical signatures (``non-canonical``)
    ECDSA verification (FIPS 186-4) checks ``r = x(R) mod n`` and ``s``, and (r, n − s)
    verifies whenever (r, s) does: anyone can turn a valid signature into a second valid
    one without the key.  1609.2 adds encodings: rSig is an ``EccP256CurvePoint``, sent
    ``x-only`` (the integer r) or, "to allow for fast verification" (SEC 1), as the point
    R itself, ``compressed-y-0``, ``compressed-y-1`` or ``uncompressed``, "at the sender's
    discretion"; ``fill`` carries no r and does not decode.  This verifier checks the
    FIPS way, from r alone (``cryptography`` takes no R), so it never looks at y: with R
    compressed both y-0 and y-1 would verify, and uncompressed any 32 octets of y.
    Every form that carries y is therefore malleable here, and so is a high s, and so is
    an r of n or more (x(R) lies in [n, p) with probability 2^-128: never honestly).
    Only ``x-only`` with 1 <= r < n and 1 <= s <= (n − 1)/2 is accepted: from it, no
    other accepted encoding of a valid signature can be made without the key.  The cost:
    1609.2 requires neither low s nor x-only, and the one real signed BSM of
    ``../shared/data`` (the ODE's ``decoder-input-bsm.json``) has rSig compressed-y-0
    and a high s; ``Verifier(canonical_only=False)`` takes such senders (the replay check
    below does not depend on it).  :func:`sign_bsm` signs in the canonical form.

Replays (``replay``)
    The verifier keeps the SHA-256 of the ``ToBeSignedData`` of every message it
    accepted until that message would be ``stale`` (generationTime + ``max_age_us``),
    and a message with the same ToBeSignedData is a ``replay``.  The key is the signed
    octets, not the signature's: a copy can change only what the signature does not
    cover, that is the signer (digest or certificate), the signature's encoding and the
    layers around, and none of those changes the key.  The check comes before the
    chain and ECDSA, since a hash in the cache is of a message that verified: a repeat
    cannot be a valid new message, and refusing it costs the one SHA-256 the signature
    needs anyway.  Only a message that verified is added, after ECDSA: else a forged
    frame carrying the ToBeSignedData of a message not yet sent (a generationTime just
    ahead, a predictable position) would make the genuine message a replay.
    A frame received twice for an innocent reason (a repeater, a duplicated datagram) is
    a ``replay`` too: its second copy brings nothing.  The cache holds at most
    ``max_replays`` (200,000) hashes, oldest evicted first (:class:`ReplayCache`).  An
    entry lives at most ``max_age_us + max_future_us`` (3 s), so the cap is reached only
    above about 67,000 accepted messages/s, some seven times what one core verifies.
    ``bench/security.py`` measures the cost: about 1 µs per accepted message (1 % of
    its verification), 10 µs to refuse a replay (parsing included; a verification is
    100 µs), 41 MB for a full cache (docs/log/2026-11-27-replay-cache.md).
"""

from catc.security._crypto import (
    P256_ORDER,
    hash_input,
    sign_bsm,
    sign_data,
    time64_to_unix,
    unix_to_time32,
    unix_to_time64,
)
from catc.security._pki import (
    Identity,
    Pki,
    issue_certificate,
    load_private_pem,
    make_pki,
    private_pem,
)
from catc.security._replay import ReplayCache
from catc.security._verify import VERDICT_REASONS, Checked, Verdict, Verifier, canonical
from catc.security.ondemand import (
    CLAIMS,
    OnDemandConfig,
    Priority,
    Threats,
    UrgentLimiter,
    VerifyQueue,
)

__all__ = [
    "CLAIMS",
    "P256_ORDER",
    "VERDICT_REASONS",
    "Checked",
    "Identity",
    "OnDemandConfig",
    "Pki",
    "Priority",
    "ReplayCache",
    "Threats",
    "UrgentLimiter",
    "Verdict",
    "Verifier",
    "VerifyQueue",
    "canonical",
    "hash_input",
    "issue_certificate",
    "load_private_pem",
    "make_pki",
    "private_pem",
    "sign_bsm",
    "sign_data",
    "time64_to_unix",
    "unix_to_time32",
    "unix_to_time64",
]
