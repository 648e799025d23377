"""How noisy ``path`` is on sharp light, predicted from rex's probe photons, not from path.

Sharp light is light that reaches a diffuse surface from an emitter through delta (specular)
bounces only: an L S+ D path, a caustic. Mitsuba's ``path`` meets it only when a BSDF ray
from the diffuse surface happens to find the emitter's image through the specular chain (a
shadow ray stops at glass), so it comes as rare, bright samples. A pilot of a few hundred
samples catches them now and then: on veach-bidir at 256², twopass's pilot put 0-14 % of
path's variance in its caustic part over three render seeds, while path's curve in the
harness shows that part is most of it (session 30,
docs/results/shape-order-sharp-light-2026-11-29). Photons find that light every time.

**The model.** A pixel's eye ray meets a diffuse surface of albedo ρ with throughput β
(a = β·ρ/π, as in :func:`~mi_twopass.prepass.rex_textures.predicted_noise`). There, sharp
light of irradiance E_s arrives from emitters of radiance L through chains of throughput T
(E_s = π·T·L·p: p the share of cosine-weighted directions that find the emitters' images). A
cosine-sampled BSDF ray (weight ρ) finds them with probability p and then carries β·ρ·T·L, so
one sample's second moment, the variance where p is small, is

    E[X²] = p·(β·ρ·T·L)² = π·a²·T·L·E_s ≤ π·a²·L·E_s.

With several emitters, Σ_e L_e·E_s,e. From the probe shoot, E_s,e of a size cell is the flux
of its records that came through delta bounces only (at least one: direct light is emitter
sampled) from emitter e, over the cell's area. L_e is the emitter's mean radiance
(:func:`emitter_radiance`). Delta emitters count 0: path's BSDF rays never find a point or a
direction, so that light is missing from path, not noisy in it
(:mod:`mi_twopass.compose.unsampled`). Per pixel, over (the pixel's radiance² + ε) as relMSE
reads it, averaged over the pixels the size pass models: the relative variance of one path
sample on sharp light, the quantity twopass's pilot reads as its caustic part
(:mod:`mi_twopass.compose.pilot`).

``tools/sharp_variance.py`` prints it per scene. Against path's curves in the harness
(relMSE × spp at 256²) it read, with the brightest area emitter's L for every record (session
30): veach-bidir 119 against ~290, caustic.xml 64 against 30-48, tut-cbox 2.5 against 1.75.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from .. import units
from ..evaluation.metrics import RELMSE_EPS
from . import rex_textures as R


@dataclass
class SharpLight:
    """``relative_variance``: path's predicted relative variance per sample on sharp light
    (module docstring); ``share``: sharp light's share of the image's radiance (all emitters,
    delta ones included); ``photons``: the rex photon budget the same measurement set
    (:func:`~mi_twopass.prepass.rex_textures.photon_need`)."""

    relative_variance: float
    share: float
    photons: int


def emitter_radiance(scene, power: np.ndarray, radius: float) -> np.ndarray:
    """Each emitter's mean radiance (channel mean) as a BSDF ray that finds it sees it, from
    its power Φ (:func:`~mi_twopass.prepass.rex_textures.probe_emitters`, the mean weight of
    :func:`~mi_twopass.scene.emission.emitter_rays`):

    * surface emitters: Φ / (π·A), a Lambertian emitter of area A (exitance π·L);
    * infinite emitters with a solid angle (constant, envmap, sky): Φ / (4π · πR²), as
      ``emitter_rays`` starts their photons on a disk of radius R (``radius``) facing a
      direction drawn over the sphere;
    * delta emitters (point, spot, directional, a sun): 0, path's BSDF rays never meet them."""
    out = np.zeros(len(power))
    for i, em in enumerate(scene.emitters()):
        flags = em.flags()
        if mi.has_flag(flags, mi.EmitterFlags.DeltaPosition) or \
                mi.has_flag(flags, mi.EmitterFlags.DeltaDirection):
            continue
        if mi.has_flag(flags, mi.EmitterFlags.Surface) and em.get_shape() is not None:
            area = float(em.get_shape().surface_area()[0])
            out[i] = power[i] / (math.pi * area) if area > 0 else 0.0
        elif mi.has_flag(flags, mi.EmitterFlags.Infinite) and radius > 0:
            out[i] = power[i] / (4.0 * math.pi * math.pi * radius * radius)
    return out


def pixel_radiance(need: dict, read: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(model pixels, radiance per film pixel)`` as the size pass predicts the image
    (channel means): what the eye pass takes from elsewhere (``need["known"]``, on the
    modelled pixels) plus ``read``, the radiance each of the size pass's hits reads from its
    rex (a·E), summed into its pixel."""
    width, height = need["film"]
    model = need.get("model_pixels")
    model = np.arange(width * height) if model is None else model
    radiance = np.zeros(width * height)
    radiance[model] += need["known"]
    np.add.at(radiance, need["hits"]["pixel"], read)
    return model, radiance


def path_variance(scene, measure: R.ProbeMeasure) -> tuple[float, float]:
    """``(relative variance, share)`` of :class:`SharpLight` from a size pass and probe
    shoot (:func:`~mi_twopass.prepass.rex_textures.measure_probe`): the module docstring's
    π·a²·Σ_e L_e·E_s,e per pixel over (radiance² + ε), averaged over the modelled pixels."""
    need, tables = measure.need, measure.tables
    records = measure.probe[3]
    hits = need.get("hits", {})
    if not len(hits.get("rex", ())) or not len(records["rex"]) or "emitter" not in records:
        return 0.0, 0.0
    radiance_of = emitter_radiance(scene, measure.power, float(tables.bounds.radius))
    w = np.asarray(records["flux"], np.float64).mean(axis=1)
    sharp = np.asarray(records["sharp"], bool)
    chained = sharp & (np.asarray(records["depth"]) > 0)  # at least one delta bounce
    rc, _, _ = R.size_cells(tables, np.asarray(records["rex"], np.int64), records["u"],
                            records["v"])
    flux = np.bincount(rc, weights=w, minlength=tables.size_cells)
    flux_sharp = np.bincount(rc, weights=w * sharp, minlength=tables.size_cells)
    flux_l = np.bincount(rc, weights=w * chained * radiance_of[records["emitter"]],
                         minlength=tables.size_cells)
    cell, area = R.hit_cells(tables, hits)
    a = hits["beta"] * hits["albedo"] * units.INV_PI
    model, radiance = pixel_radiance(need, a * flux[cell] / area)
    var = np.zeros(len(radiance))
    np.add.at(var, hits["pixel"], math.pi * a * a * flux_l[cell] / area)
    relvar = float(np.mean(var[model] / (radiance[model] ** 2 + RELMSE_EPS)))
    share = float(np.sum(a * flux_sharp[cell] / area) / max(radiance[model].sum(), 1e-30))
    return relvar, share


def measure(scene, settings, seed: int = 0, sensor=None, memo=None) -> SharpLight:
    """The size pass and probe shoot of rex's photon budget
    (:func:`~mi_twopass.prepass.rex_textures.measure_probe`; ``memo``: a
    :class:`~mi_twopass.prepass.rex_textures.ProbeMemo` the builds that follow read it from),
    read twice: the photons the image needs and path's predicted variance on sharp light."""
    m = R.measure_probe(scene, settings, seed, sensor, memo)
    photons = settings.photons if settings.photons > 0 else \
        R.photon_need(m.need, settings, m.power, *m.probe, tables=m.tables)[0]
    relvar, share = path_variance(scene, m)
    return SharpLight(relvar, share, int(photons))


__all__ = ["SharpLight", "emitter_radiance", "measure", "path_variance", "pixel_radiance"]
