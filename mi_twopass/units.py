"""Radiometric conversions, written once (docs/design.md "Units").

Mitsuba works in radiance L [W/(m² sr)]. Radiosity B [W/m²] is the power leaving a surface per
unit area; for a Lambertian surface L = B/π. An emitter of radiance Le has emitted radiosity π·Le.
A photon carries flux Φ [W]; a bucket of area A that received ΣΦ has irradiance E = ΣΦ/A, and a
diffuse surface of albedo ρ reflects radiosity ρ·E, i.e. radiance ρ·E/π.
"""
import math

INV_PI = 1.0 / math.pi


def radiance_from_radiosity(B):
    """L = B/π for a Lambertian surface."""
    return B * INV_PI


def radiosity_from_radiance(L):
    """B = π·L for a Lambertian surface (emitted radiosity of an emitter of radiance Le)."""
    return L * math.pi


def irradiance_from_flux(flux, area):
    """E = ΣΦ / A; zero where the area is zero (degenerate patches receive nothing)."""
    import numpy as np

    area = np.asarray(area, dtype=np.float64)
    flux = np.asarray(flux, dtype=np.float64)
    safe = np.where(area > 0, area, 1.0)
    shape = (-1,) + (1,) * (flux.ndim - 1)
    return np.where(area.reshape(shape) > 0, flux / safe.reshape(shape), 0.0)


def reflected_radiosity(albedo, E):
    """B_reflected = ρ·E (diffuse reflection of irradiance E)."""
    return albedo * E


def reflected_radiance(albedo, E):
    """L = ρ·E/π (diffuse reflection of irradiance E, as radiance)."""
    return albedo * E * INV_PI


def channel_mean(c):
    """The mean of an RGB colour's three channels, per lane (a ``mi.Color3f``: how the suite
    weighs a colour as one number, e.g. a particle's flux). Not ``dr.mean``: on a Color3f,
    Dr.Jit 1.5 computes it as the sum times the array's width over three times its width, two
    literals that made the radiosity particle kernel new for every batch size (the emission
    guide's pilots: a kernel per seed on scenes_xml/mixed_room.xml,
    ``tools/kernel_recompiles.py --first-seed``)."""
    return (c.x + c.y + c.z) * (1.0 / 3.0)
