"""Seeded, reproducible channel decisions: which BSMs are lost.

Every decision is a pure function of ``(seed, vehicle, message index)``: a counter-
based generator (SplitMix64, Steele et al. 2014) hashes the three into a uniform
number in [0, 1).  Nothing depends on the order in which messages are asked about,
so the live RVE, the offline simulator and a re-run of one vehicle all see the same
loss pattern, and every predictor in a sweep is scored on the same pattern.
"""

from __future__ import annotations

import zlib

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


def uniforms(seed: int, vehicle: str | int, index: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1), one per message index, for this seed and vehicle."""
    index = np.asarray(index, dtype=np.uint64)
    with np.errstate(over="ignore"):
        base = _splitmix64(np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
                           ^ (np.uint64(vehicle_key(vehicle)) << np.uint64(32)))
        z = _splitmix64(base ^ _splitmix64(index))
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def bernoulli_received(seed: int, vehicle: str | int, n: int, per: float) -> np.ndarray:
    """Which of messages ``0..n-1`` arrive under independent loss with probability ``per``."""
    if not 0.0 <= per <= 1.0:
        raise ValueError(f"packet error rate {per} outside [0, 1]")
    return uniforms(seed, vehicle, np.arange(n)) >= per
