"""Seeded, reproducible channel decisions: which BSMs are sent, lost, and how late.

Every decision is a pure function of ``(seed, vehicle, message index)``: a counter-
based generator (SplitMix64, Steele et al. 2014) hashes them into a uniform number in
[0, 1), with independent streams for the loss, the distance draw and the jitter.  Nothing
depends on the order in which messages are asked about (the Gilbert burst chain is
walked from message 0 of the vehicle, so it too is a function of the index alone), so the
live RVE, the offline simulator and a re-run of one vehicle all see the same pattern, and
every predictor in a sweep is scored on the same pattern.

:func:`schedule` applies the whole channel model of the RVE to one vehicle's messages,
in this order (:class:`ChannelConfig` documents each parameter):

1. **Transmission rate** (10 Hz down to 1 Hz) by subsampling the 10 Hz samples: sample
   ``i`` is sent when ``floor(i·rate/10)`` steps up (every sample at 10 Hz, every other
   at 5 Hz, 3 of 10 at 3 Hz).  Only sent messages are scheduled; ``seq`` numbers them.
2. **Loss**: Bernoulli with probability ``per`` (``burst`` = 1), or a Gilbert two-state
   chain (Gilbert 1960) over the sent messages whose bad state loses every message, with
   mean burst length ``burst`` and the same long-run loss ``per``: bad→good with
   probability ``1/burst``, good→bad ``per/(burst·(1−per))``.
3. **Distance** (optional): the message is also lost with probability ``1 − p_rx(d)``
   at HV–RV distance ``d`` (:func:`reception_probability`).
4. **Latency**: every delivered message is delayed ``latency + U(0, jitter)``; a message
   whose delay exceeds its successor's by more than the send interval arrives after it
   (reordering), as on a real channel.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _splitmix64(z: np.ndarray) -> np.ndarray:
    z = z + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def vehicle_key(vehicle: str | int) -> int:
    """A stable 32-bit key for a vehicle id (CRC-32 of its text; not Python's hash())."""
    return zlib.crc32(str(vehicle).encode())


def uniforms(seed: int, vehicle: str | int, index: np.ndarray, stream: int = 0) -> np.ndarray:
    """Uniform numbers in [0, 1), one per message index, for this seed and vehicle.

    ``stream`` selects an independent sequence (0: the loss draw; others for the
    distance draw, the jitter, ...)."""
    index = np.asarray(index, dtype=np.uint64)
    with np.errstate(over="ignore"):
        base = _splitmix64(np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
                           ^ (np.uint64(vehicle_key(vehicle)) << np.uint64(32)))
        if stream:
            base = _splitmix64(base ^ _splitmix64(np.uint64(stream)))
        z = _splitmix64(base ^ _splitmix64(index))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def bernoulli_received(seed: int, vehicle: str | int, n: int, per: float) -> np.ndarray:
    """Which of messages ``0..n-1`` arrive under independent loss with probability ``per``."""
    if not 0.0 <= per <= 1.0:
        raise ValueError(f"packet error rate {per} outside [0, 1]")
    return uniforms(seed, vehicle, np.arange(n)) >= per


# --- the RVE's whole channel model ---------------------------------------------------------

_STREAM_LOSS, _STREAM_DISTANCE, _STREAM_JITTER = 0, 1, 2

#: Why a message was not delivered, in :data:`SCHEDULE_DTYPE` ``cause``.
CAUSES = ("delivered", "loss", "distance")

#: One row per *sent* message of a vehicle.
SCHEDULE_DTYPE = np.dtype([
    ("index", np.int64),  # sample index in the vehicle's 10 Hz track
    ("seq", np.int64),  # number among the sent messages (0, 1, 2, ...)
    ("t", np.float64),  # generation time (s, dataset time)
    ("dropped", np.bool_),
    ("cause", np.int8),  # index into CAUSES
    ("delay", np.float64),  # s from generation to delivery; NaN when dropped
])


@dataclass(frozen=True)
class ChannelConfig:
    """The RVE's channel model (module docstring).  Percentages are fractions here."""

    #: Long-run packet error rate, 0..1.
    per: float = 0.0
    #: Mean burst length in messages; 1 = independent (Bernoulli) losses.
    burst: float = 1.0
    #: Transmission rate, Hz: 10 (every sample) down to 1.
    rate_hz: float = 10.0
    #: Fixed latency, s.
    latency_s: float = 0.0
    #: Jitter, s: each delay is latency + U(0, jitter).
    jitter_s: float = 0.0
    #: Distance-dependent reception (:func:`reception_probability`) on or off.
    distance: bool = False
    #: Its parameters: transmit power (dBm), receiver sensitivity (dBm), path-loss
    #: exponent and Nakagami-m shape (see :func:`reception_probability`).
    tx_power_dbm: float = 20.0
    sensitivity_dbm: float = -82.0
    path_loss_exponent: float = 2.0
    nakagami_m: float = 1.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.per <= 1.0:
            raise ValueError(f"packet error rate {self.per} outside [0, 1]")
        if not (math.isfinite(self.burst) and self.burst >= 1.0):
            raise ValueError(f"mean burst length must be >= 1 message, got {self.burst}")
        if not 1.0 <= self.rate_hz <= 10.0:
            raise ValueError(f"transmission rate must be 1-10 Hz, got {self.rate_hz}")
        if not (self.latency_s >= 0.0 and self.jitter_s >= 0.0
                and math.isfinite(self.latency_s + self.jitter_s)):
            raise ValueError("latency and jitter must be finite and >= 0")
        if self.nakagami_m < 0.5 or self.path_loss_exponent <= 0.0:
            raise ValueError("Nakagami m must be >= 0.5 and the path-loss exponent > 0")


#: Free-space path loss at 1 m for 5.9 GHz (Friis: 20 log10(4 pi / lambda)), dB.
PATH_LOSS_1M_DB = 20.0 * math.log10(4.0 * math.pi * 5.9e9 / 299_792_458.0)


def reception_probability(distance_m: np.ndarray, config: ChannelConfig = ChannelConfig()
                          ) -> np.ndarray:
    """Probability that a BSM sent ``distance_m`` away is received (the distance curve).

    Log-distance path loss at 5.9 GHz from the free-space loss at 1 m (47.9 dB, Friis)
    with exponent ``path_loss_exponent`` (2: line of sight on an open highway), Nakagami-m
    fading of the received power (m = 1.5: between Rayleigh and Rician, the range
    V2V channel measurements at 5.9 GHz report), and reception when the faded power is at
    least the sensitivity (-82 dBm: the IEEE 802.11 minimum sensitivity for 6 Mb/s QPSK
    1/2 in a 10 MHz channel, the DSRC default rate).  With 20 dBm this gives 0.99 at
    100 m, 0.79 at 300 m, 0.41 at 500 m and 0.01 at 1 km (a test pins these).  Under
    Nakagami-m the received power is Gamma(m, mean/m), so ``p = Q(m, m·sens/mean)``
    (regularised upper incomplete gamma).
    """
    d = np.maximum(np.asarray(distance_m, dtype=float), 1.0)
    mean_dbm = config.tx_power_dbm - PATH_LOSS_1M_DB \
        - 10.0 * config.path_loss_exponent * np.log10(d)
    ratio = 10.0 ** ((config.sensitivity_dbm - mean_dbm) / 10.0)
    m = config.nakagami_m
    from scipy.special import gammaincc  # here: scipy.special is half of the daemons' start-up

    return gammaincc(m, m * ratio)


def sent_indices(n: int, rate_hz: float) -> np.ndarray:
    """Sample indices (0..n-1) a vehicle sends at ``rate_hz`` (module docstring, step 1)."""
    i = np.arange(n)
    k = np.floor(i * rate_hz / 10.0 + 1e-9)
    keep = np.ones(n, dtype=bool)
    keep[1:] = k[1:] > k[:-1]
    return i[keep]


def gilbert_lost(seed: int, vehicle: str | int, n: int, per: float, burst: float) -> np.ndarray:
    """Losses of messages 0..n-1 under the Gilbert burst chain (module docstring, step 2).

    The chain starts in its stationary distribution; message ``k`` is lost in the bad
    state.  A prefix of the result does not depend on ``n``.
    """
    u = uniforms(seed, vehicle, np.arange(n), _STREAM_LOSS).tolist()
    if per <= 0.0:
        return np.zeros(n, dtype=bool)
    if per >= 1.0:
        return np.ones(n, dtype=bool)
    r = 1.0 / burst  # bad -> good
    p = per * r / (1.0 - per)  # good -> bad, so that the stationary loss is per
    if p > 1.0:
        raise ValueError(f"PER {per} needs bursts of at least {per / (1 - per):.2f} "
                         f"messages on average, got {burst}")
    out = [False] * n
    bad = bool(n) and u[0] < per
    for k in range(n):
        if k:
            bad = u[k] >= r if bad else u[k] < p
        out[k] = bad
    return np.array(out, dtype=bool)


def schedule(config: ChannelConfig, seed: int, vehicle: str | int, t: np.ndarray,
             distance_m: np.ndarray | None = None) -> np.ndarray:
    """The channel's decision for every message a vehicle sends (:data:`SCHEDULE_DTYPE`).

    ``t`` is the vehicle's 10 Hz sample times; ``distance_m`` the HV–RV distance at each
    sample (needed when ``config.distance``).  Pure: the same arguments give the same
    schedule, and message ``k``'s decision does not depend on how many follow.
    """
    t = np.asarray(t, dtype=float)
    idx = sent_indices(len(t), config.rate_hz)
    n = len(idx)
    seq = np.arange(n)
    if config.burst > 1.0:
        lost = gilbert_lost(seed, vehicle, n, config.per, config.burst)
    else:
        lost = uniforms(seed, vehicle, seq, _STREAM_LOSS) < config.per
    cause = np.where(lost, 1, 0).astype(np.int8)
    if config.distance:
        if distance_m is None:
            raise ValueError("the distance model needs the HV-RV distance of every message")
        p_rx = reception_probability(np.asarray(distance_m, dtype=float)[idx], config)
        far = (uniforms(seed, vehicle, seq, _STREAM_DISTANCE) >= p_rx) & ~lost
        cause[far] = 2
    dropped = cause != 0
    delay = config.latency_s + config.jitter_s * uniforms(seed, vehicle, seq, _STREAM_JITTER)
    out = np.empty(n, dtype=SCHEDULE_DTYPE)
    out["index"], out["seq"], out["t"] = idx, seq, t[idx]
    out["dropped"], out["cause"] = dropped, cause
    out["delay"] = np.where(dropped, np.nan, delay)
    return out
