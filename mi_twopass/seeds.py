"""Seeds of the prepasses' random streams, derived from the render's ``seed``, written once.

Every random number of a prepass comes from a stream whose initial state is a hash of the
render's seed and a *salt* naming the stream (particles, camera points, visibility rays,
photons, ...): the same seed gives the same prepass bit for bit, and no two streams share their
numbers. Seeds enter Dr.Jit kernels through ``dr.opaque`` (a literal would compile every
kernel anew for each seed); numpy streams come from :func:`numpy_rng` (or
``np.random.default_rng(hash31(...))``).
"""
from __future__ import annotations

import numpy as np

_MASK64 = 0xFFFFFFFFFFFFFFFF


def splitmix64(seed: int) -> int:
    """The splitmix64 finaliser of ``seed`` (Steele, Lea & Flood 2014): a 64-bit state for PCG32
    (``mi.PCG32(initstate=...)``) that differs in about half its bits between adjacent seeds."""
    z = (int(seed) + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def hash31(seed: int, salt: int, extra: int = 0) -> int:
    """A 31-bit seed for a stream named by ``salt`` (and ``extra``, e.g. a pass index): what
    ``Sampler.seed`` and ``numpy.random.default_rng`` take."""
    return (int(seed) * 0x9E3779B1 + int(salt) * 0x85EBCA77 + int(extra) * 0xC2B2AE3D) \
        & 0x7FFFFFFF


def numpy_rng(seed: int, salt: int) -> np.random.Generator:
    """The numpy stream named by ``salt`` of the render's ``seed``: a ``Generator`` seeded with
    ``SeedSequence([seed, salt])`` (numpy's own hash of the pair, so streams of different salts
    are independent)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(salt)]))
