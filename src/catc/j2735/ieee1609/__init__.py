"""IEEE 1609.2 ``Ieee1609Dot2Data`` and certificates in canonical OER, and the WSMP envelope.

Deployed OBUs and RSUs send a J2735 UPER MessageFrame inside an IEEE 1609.2 secured
data structure, encoded with COER (ITU-T X.696 canonical OER), usually carried in a
WAVE Short Message (IEEE 1609.3).  The types come from IEEE Std 1609.2-2016 §6.3 and
§6.4 (ASN.1 modules ``Ieee1609Dot2`` and ``Ieee1609Dot2BaseTypes``, as published e.g. in
the usdot-jpo-ode/asn1_codec repository); the octet layout from X.696.  One module per
part, all written as readers over an :class:`io.BytesIO` and builders of octets:

- ``_oer``: the X.696 primitives (length determinant, quantities, integers, PSID, open
  types and extension additions);
- ``_basetypes``: curve points, public keys, signatures, hash algorithms and regions;
- ``_certificate``: §6.4 ``Certificate``, :func:`parse_certificate` and the builders;
- ``_data``: §6.3 ``Ieee1609Dot2Data``, :func:`unwrap`, :func:`wrap_unsecured`,
  :func:`tbs_data` and :func:`build_signed`;
- ``_wsmp``: the WAVE Short Message (IEEE 1609.3-2016 §8.3), :func:`wrap_wsmp` and
  :func:`unwrap_wsmp`;
- ``_fast``: :func:`fast_open`, the receive fast path for the usual layout of a signed
  BSM, which leaves everything else (errors included) to the parsers above.

Nothing here does cryptography: signatures are made and verified by
:mod:`catc.security`.  The only hash computed is the HashedId8 of a certificate
(§6.4.3), an identifier.

Every count, length and nesting depth is bounded, so hostile input costs time and
memory proportional to its length at most.  Errors are :class:`DecodeError` with the
reasons of :mod:`catc.errors`: input that ends early is ``truncated``, a form this codec
does not handle is ``unsupported``, anything else malformed is ``garbage``.
"""

from catc.j2735.ieee1609._basetypes import PSID_BSM
from catc.j2735.ieee1609._certificate import (
    ISSUE_ALL,
    Certificate,
    build_certificate,
    build_tbs_certificate,
    parse_certificate,
)
from catc.j2735.ieee1609._data import (
    PROTOCOL_VERSION,
    Unwrapped,
    build_signed,
    looks_like_1609,
    tbs_data,
    unwrap,
    wrap_unsecured,
)
from catc.j2735.ieee1609._fast import fast_open, remember
from catc.j2735.ieee1609._wsmp import (
    ETHERTYPE_WSMP,
    WSMP_VERSION,
    looks_like_wsmp,
    unwrap_wsmp,
    wrap_wsmp,
)

__all__ = [
    "ETHERTYPE_WSMP",
    "ISSUE_ALL",
    "PROTOCOL_VERSION",
    "PSID_BSM",
    "WSMP_VERSION",
    "Certificate",
    "Unwrapped",
    "build_certificate",
    "build_signed",
    "build_tbs_certificate",
    "fast_open",
    "looks_like_1609",
    "looks_like_wsmp",
    "parse_certificate",
    "remember",
    "tbs_data",
    "unwrap",
    "unwrap_wsmp",
    "wrap_unsecured",
    "wrap_wsmp",
]
