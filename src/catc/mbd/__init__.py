"""Misbehavior detection (MBD) on BSMs that passed IEEE 1609.2 verification.

A valid signature says who sent a message, not that it is true: an insider with a valid
pseudonym certificate can broadcast a ghost vehicle, a shifted position or a speed that
contradicts its own positions.  :class:`MisbehaviorDetector` runs plausibility checks on
every received BSM and keeps the sender's recent history, so that the OBU can drop
implausible messages and quarantine their senders (their tracks raise no warning).

The checks are the legacy checks of F2MD (J. Kamel et al., "Simulation Framework for
Misbehavior Detection in Vehicular Networks", IEEE TVT 69(6), 2020), read from its source:
``LegacyChecks.cc`` and ``F2MDParameters.h`` of IRT-SystemX/veins-f2md
(``src/veins/modules/application/f2md/``, commit 1d529e5), ``MDMLib.cc`` there for the
kinematic envelope and the rectangle overlap, and ``F2MDVeinsApp.cc`` for the vehicle limits;
the older ``josephkamel/F2MD`` tree (``f2mdVeinsApp/``) has the same checks with ``#define``
constants.  Each threshold in :class:`MbdConfig` cites its F2MD constant; where it had to
change for a 10 Hz BSM on a real radio, the comment says why.  F2MD's names map to ours
as:

========================================  ============================================
F2MD (``LegacyChecks.cc``)                 ``Detection.check``
========================================  ============================================
RangePlausibilityCheck                    ``range``
PositionConsistancyCheck                  ``position-consistency``
SpeedConsistancyCheck, SpeedPlausibility  ``speed-consistency``
PositionSpeedConsistancyCheck             ``position-speed``
SuddenAppearenceCheck                     ``sudden-appearance``
BeaconFrequencyCheck (+ secMark clock)    ``frequency``
PositionHeadingConsistancyCheck           ``heading``
(none; VeReMi extension's grid Sybil)     ``sybil``
IntersectionCheck, MultipleIntersection   ``intersection``
========================================  ============================================

F2MD's PositionPlausibilityCheck (distance from the road map) needs a map and is not done;
its Kalman checks belong to its newer "Kalman" versions, not the legacy set.  SAE J3287
(misbehavior reports; it reuses the observation structure of ETSI TS 103 759, whose
observation names include Beacon-IntervalTooSmall, Position-ChangeTooLarge,
Speed-ValueTooLarge-VehicleType, Speed-ChangeTooLarge, LongAcc-ValueTooLarge) is what a
report built from a :class:`Detection` would carry; ``evidence`` holds the numbers.

Conventions: positions are WGS-84 degrees as in :class:`catc.bsm.BSM`; distances come from
a local metric scale (:func:`local_offset_m`, checked against :mod:`catc.geo`'s geodesics
in the tests: catc.geo's pyproj calls cost ~11 us each, more than the whole budget of one
message here).  Headings are degrees clockwise from north.  Times: the sender's own clock
is its secMark (ms within the UTC minute, wrapped at 60000); ``t`` is the caller's
receive clock.  Pure: no I/O, no clock of its own.  docs/mbd.md has each check's formula,
threshold and source, the quarantine rule and the measured cost.

The modules, one job each:

==============  ===========================================================================
``checks``      one function per check, listed in ``checks.TABLE``: where a check is added
``detector``    :class:`MisbehaviorDetector`; ``observe`` runs the table on each message
``identity``    which signer holds each TemporaryID (an id claimed by another is a conflict)
``quarantine``  the evidence per signer and the quarantine rule
``state``       each sender's accepted messages (a bounded LRU) and the neighbour grid
``config``      :class:`MbdConfig`: every threshold, with its F2MD source
``geometry``    the local metric scale, the kinematic envelope and the footprint overlap
==============  ===========================================================================
"""

from catc.mbd.checks import CHECKS, ID_CONFLICT, Detection
from catc.mbd.config import MbdConfig
from catc.mbd.detector import MisbehaviorDetector
from catc.mbd.geometry import local_offset_m

__all__ = ["CHECKS", "ID_CONFLICT", "Detection", "MbdConfig", "MisbehaviorDetector",
           "local_offset_m"]
