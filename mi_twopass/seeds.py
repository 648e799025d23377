"""Seeds of the prepasses' random streams, derived from the render's ``seed``, written once.

Every random number of a prepass comes from a stream whose initial state is a hash of the
render's seed and a *salt* naming the stream (particles, camera points, visibility rays,
photons, ...): the same seed gives the same prepass bit for bit, and no two streams share their
numbers. Seeds enter Dr.Jit kernels through ``dr.opaque`` (a literal would compile every
kernel anew for each seed).
"""
from __future__ import annotations

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
