"""``python -m mi_twopass check``: is each integrator right on a scene?

For each integrator: one render of the scene at a modest spp, compared with the cached ``path``
reference (:func:`~mi_twopass.evaluation.reference.reference_image`) by two numbers that a
correct integrator keeps small whatever its noise pattern:

* the image mean ratio (mean / reference mean over pixels and channels): a global energy
  error (a missing light path, a wrong normalisation) moves it;
* the block relMSE: relMSE of the 8×8-pixel block means, mean((b − r)² / (r² + 0.01)) over
  blocks and channels; averaging 64 pixels first removes most of the per-pixel noise, so what
  is left is mostly bias in regions (a dark corner, a missing caustic).

A row is marked "OUT" when |ratio − 1| > 1 % or block relMSE > 3e-3 (:data:`RATIO_TOLERANCE`,
:data:`BLOCK_RELMSE_MAX`). Both include the noise of the render and of the reference: the
default rows start with ``path`` itself at the same spp, which shows that noise (on a scene
with fireflies ``path`` is OUT too, and every other OUT row then says it is noise-limited,
:func:`mark_noise_limited`) and the report names the ``spp`` and ``ref_spp`` at which
path's noise would leave room to see a bias (:func:`spp_to_see_bias`). An integrator that
refuses the scene (``ValueError`` / ``NotImplementedError`` from its prepass) is reported as
refused, with its message. The result is a report: nothing here raises for a row that is out of bounds.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scenefile import load_scene
from .harness import make_integrator
from .metrics import BLOCK, BLOCK_RELMSE_MAX, RELMSE_EPS
from .reference import reference_image

#: what ``check`` runs when no integrators are named: ``path`` first, at the same spp, the
#: noise an unbiased estimator leaves in both numbers (an integrator's row OUT where ``path``'s
#: is OUT too says the bounds are noise-limited at that spp, not that the integrator is biased)
DEFAULT_INTEGRATORS = ("path", "radiosity_gather", "spike_gather", "rex", "radiance_cache",
                       "twopass")
DEFAULT_SPP = 64
DEFAULT_REF_SPP = 1024
#: bounds of a row that is in: |mean ratio − 1| and block relMSE (of BLOCK × BLOCK pixels,
#: metrics.BLOCK_RELMSE_MAX)
RATIO_TOLERANCE = 0.01
#: added to the render's seed, so that no render shares its random numbers with the reference
RENDER_SEED_OFFSET = 0x5EED
#: the second render's samplers are this far from the first's (``renders=2``)
SECOND_RENDER_STRIDE = 7919


@dataclass
class CheckRow:
    """One integrator's line of the report (``refused`` set: the other numbers are None)."""

    integrator: str
    seconds: float | None = None
    prepass_seconds: float | None = None
    render_seconds: float | None = None
    mean_ratio: float | None = None
    block_relmse: float | None = None
    out: bool = False
    refused: str | None = None
    stats: dict = field(default_factory=dict)
    #: out of bounds where ``path``'s own row, at the same spp, is out too
    #: (:func:`mark_noise_limited`): the bounds are noise-limited there, not proof of a bias
    noise_limited: bool = False
    #: with two renders (``renders=2``): :func:`block_bias2` and its standard error; the mean
    #: ratio and block relMSE are then those of the two renders' mean image, and the row is
    #: OUT on the mean ratio or this estimate (not on the block relMSE, which holds noise)
    bias2: float | None = None
    bias2_se: float | None = None
    #: ... and the standard error of the mean ratio, from the two renders' block differences
    #: (:func:`ratio_se`)
    ratio_se: float | None = None


def block_means(image, block: int = BLOCK) -> np.ndarray:
    """Means of ``block`` × ``block`` pixel blocks of an (H, W, C) image, shape
    (ceil(H/block), ceil(W/block), C); blocks at the right and bottom edges may be smaller and
    average the pixels they have."""
    x = np.asarray(image, dtype=np.float64)
    if x.ndim == 2:
        x = x[..., None]
    h, w = x.shape[:2]
    rows = np.arange(0, h, block)
    cols = np.arange(0, w, block)
    sums = np.add.reduceat(np.add.reduceat(x, rows, axis=0), cols, axis=1)
    counts = np.outer(np.minimum(block, h - rows), np.minimum(block, w - cols))
    return sums / counts[..., None]


def block_relmse(image, ref, block: int = BLOCK, eps: float = RELMSE_EPS) -> float:
    """relMSE of the block means: mean((b − r)² / (r² + eps)) over blocks and channels."""
    x = np.asarray(image, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    if x.shape != r.shape:
        raise ValueError(f"image shape {x.shape} differs from reference shape {r.shape}")
    b, rb = block_means(x, block), block_means(r, block)
    return float(np.mean((b - rb) ** 2 / (rb**2 + eps)))


def block_bias2(first, second, ref, block: int = BLOCK,
                eps: float = RELMSE_EPS) -> tuple[float, float]:
    """The part of the block relMSE that is not the renders' noise, from two renders whose
    samples are independent: the mean over blocks and channels of (a − r)(b − r) / (r² + eps),
    a, b the two renders' block means and r the reference's. Each render's error is what the
    two share (the bias, and the noise of a prepass both read) plus its own samples' noise,
    independent of the other's, so the product's expectation is the shared error's square plus
    the reference's own variance (the same for every integrator: ``path``'s row shows it),
    where (a − r)² alone adds the render's variance too. Returns (estimate, its standard error
    over blocks); the estimate may be below 0 where there is no bias."""
    a, b, r = (block_means(np.asarray(x, dtype=np.float64), block)
               for x in (first, second, ref))
    if not a.shape == b.shape == r.shape:
        raise ValueError(f"shapes differ: {a.shape}, {b.shape}, reference {r.shape}")
    terms = ((a - r) * (b - r) / (r**2 + eps)).mean(axis=-1).ravel()  # per block
    se = float(terms.std(ddof=1) / math.sqrt(terms.size)) if terms.size > 1 else math.inf
    return float(terms.mean()), se


def ratio_se(first, second, ref, block: int = BLOCK) -> float:
    """The standard error of the mean ratio of the mean of two renders whose samples are
    independent: the image mean of (a + b)/2 has the variance var(a_k − b_k)/(4n) over the
    n block means (their noise is independent between blocks), over the reference's mean."""
    d = (block_means(np.asarray(first, dtype=np.float64), block)
         - block_means(np.asarray(second, dtype=np.float64), block)).mean(axis=-1).ravel()
    r = float(np.mean(np.asarray(ref, dtype=np.float64)))
    if d.size < 2 or r == 0.0:
        return math.inf
    return float(np.sqrt(d.var(ddof=1) / (4 * d.size)) / r)


def mean_ratio(image, ref) -> float:
    """Mean of the image over the reference's (pixels and channels); 1 when both are 0, inf
    when only the reference is."""
    m = float(np.mean(np.asarray(image, dtype=np.float64)))
    r = float(np.mean(np.asarray(ref, dtype=np.float64)))
    if r == 0.0:
        return 1.0 if m == 0.0 else math.inf
    return m / r


def is_out(ratio, brel, ratio_tol: float = RATIO_TOLERANCE,
           brel_max: float = BLOCK_RELMSE_MAX) -> bool:
    """True unless |ratio − 1| ≤ ``ratio_tol`` and ``brel`` ≤ ``brel_max`` (NaN is out)."""
    return not (abs(ratio - 1.0) <= ratio_tol and brel <= brel_max)


def refusal_of(exc):
    """The ``ValueError`` / ``NotImplementedError`` by which an integrator refused a scene,
    found in ``exc`` or the exceptions it was raised from (``mi.render`` re-raises what a
    prepass raises as a ``RuntimeError`` of Dr.Jit's custom operation); None if there is
    none."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (ValueError, NotImplementedError)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def path_row(rows):
    """The first row of Mitsuba's ``path`` that rendered (the noise alone at that spp), or
    None."""
    return next((r for r in rows if r.refused is None and r.integrator.split(":")[0] == "path"),
                None)


def mark_noise_limited(rows) -> None:
    """Mark OUT rows ``noise_limited``, each by what it has measured. A row of two renders
    (:func:`check_integrator`, ``renders=2``) by its own standard errors: where its mean ratio
    and its bias part are both within :data:`NOISE_SIGMAS` of the bounds
    (:func:`within_noise`). A row of one render by ``path``'s (Mitsuba's unbiased estimator
    at the same spp: the noise alone): where ``path``'s row is OUT too; where there is no
    ``path`` row or it is in bounds, no row of one render is marked."""
    path = path_row(rows)
    for r in rows:
        if r.bias2 is not None:
            r.noise_limited = bool(r.out and within_noise(r))
        else:
            r.noise_limited = bool(path is not None and path.out and r is not path and r.out)


def within_noise(row) -> bool:
    """Whether a row of two renders is out of bounds by less than :data:`NOISE_SIGMAS`
    standard errors on both its mean ratio and its bias part: more samples could bring it in."""
    return (abs(row.mean_ratio - 1.0) - NOISE_SIGMAS * row.ratio_se <= RATIO_TOLERANCE
            and row.bias2 - NOISE_SIGMAS * row.bias2_se <= BLOCK_RELMSE_MAX)


#: an OUT row of two renders within this many standard errors of the bounds is noise-limited
#: (:func:`within_noise`)
NOISE_SIGMAS = 2.0
#: :func:`spp_to_see_bias` asks for the spp where path's own noise fills at most this share of
#: each bound, and a reference of REF_SPP_FACTOR times that
NOISE_SHARE = 0.25
REF_SPP_FACTOR = 16


def spp_to_see_bias(rows, spp: int, ref_spp: int, renders: int = 1) -> int | None:
    """Where ``path``'s row is OUT at ``spp`` (against a reference of ``ref_spp``): the spp, a
    power of two, at which its noise would fill at most :data:`NOISE_SHARE` of each bound with a
    reference of :data:`REF_SPP_FACTOR` × that, so that an OUT row there is a bias. None where
    there is no ``path`` row or it is in bounds.

    An unbiased render of s spp against an independent reference of r spp has block relMSE
    c·(1/s + 1/r) and |mean ratio − 1| of order a·√(1/s + 1/r) (the reference's noise counts
    too: raising ``spp`` alone does not bring path in); c and a are read off path's row, and
    (1/s + 1/r) = (1 + 1/REF_SPP_FACTOR)/s solved for s. With ``renders`` = 2 the row's image
    is the mean of two renders: 1/(2s) in place of 1/s where c and a are read off."""
    path = path_row(rows)
    if path is None or not path.out:
        return None
    noise = 1.0 / (renders * spp) + 1.0 / ref_spp
    c = path.block_relmse / noise
    a2 = (path.mean_ratio - 1.0) ** 2 / noise
    need = (1.0 + 1.0 / REF_SPP_FACTOR) * max(
        c / (NOISE_SHARE * BLOCK_RELMSE_MAX), a2 / (NOISE_SHARE * RATIO_TOLERANCE) ** 2)
    return 1 << max(int(math.ceil(math.log2(max(need, spp + 1)))), 0)


def check_integrator(scene, spec: str, ref, spp: int, seed: int = 0,
                     renders: int = 1) -> CheckRow:
    """Render ``scene`` with a fresh integrator from ``spec`` (``NAME[:key=value...]``) at
    ``spp`` and compare with ``ref``. A ``ValueError`` / ``NotImplementedError`` raised while
    rendering (a prepass refusing the scene) gives a refused row; an integrator that cannot be
    made from ``spec`` raises (it is the caller's error, not the scene's).

    ``renders=2``: a second render with other samples, the row's numbers those of the mean
    image, and the bias part of the block relMSE (:func:`block_bias2`) beside them; the
    seconds are the first render's. The second render keeps the first one's prepass (a
    mi_twopass integrator's samplers are offset by :data:`SECOND_RENDER_STRIDE`, as the CLI's
    passes are; another integrator gets that seed offset), so the prepass's own noise, which
    no number of samples removes from a user's image, is counted in the bias part."""
    if renders not in (1, 2):
        raise ValueError(f"renders={renders}: must be 1 or 2")
    integrator = make_integrator(spec)
    images = []
    for k in range(renders):
        dr.sync_thread()
        t0 = time.perf_counter()
        render_seed = seed + RENDER_SEED_OFFSET
        if k and hasattr(integrator, "sample_seed_offset"):
            integrator.sample_seed_offset = SECOND_RENDER_STRIDE
        elif k:
            render_seed += SECOND_RENDER_STRIDE
        try:
            image = mi.render(scene, integrator=integrator, spp=spp, seed=render_seed)
            images.append(np.asarray(image, dtype=np.float32)[..., :3])
        except (ValueError, NotImplementedError, RuntimeError) as e:
            cause = refusal_of(e)
            if cause is None:
                raise
            return CheckRow(spec, refused=" ".join(str(cause).split()) or type(cause).__name__)
        dr.sync_thread()
        if k == 0:
            wall = time.perf_counter() - t0
            stats = dict(getattr(integrator, "stats", {}) or {})
    if "prepass_seconds" in stats and "render_seconds" in stats:
        pre, ren = float(stats["prepass_seconds"]), float(stats["render_seconds"])
        seconds = pre + ren
    else:
        pre, ren, seconds = 0.0, wall, wall
    image = np.mean(images, axis=0)
    ratio = mean_ratio(image, ref)
    brel = block_relmse(image, ref)
    bias2, bias2_se = block_bias2(*images, ref) if renders == 2 else (None, None)
    rse = ratio_se(*images, ref) if renders == 2 else None
    out = is_out(ratio, brel if bias2 is None else bias2)
    return CheckRow(spec, seconds=seconds, prepass_seconds=pre, render_seconds=ren,
                    mean_ratio=ratio, block_relmse=brel, out=out, bias2=bias2,
                    bias2_se=bias2_se, ratio_se=rse,
                    stats={k: v for k, v in stats.items() if isinstance(v, (int, float, str))})


def run_check(scene_path, integrators=DEFAULT_INTEGRATORS, spp: int = DEFAULT_SPP,
              film_res: int | None = None, ref_spp: int = DEFAULT_REF_SPP,
              params: dict | None = None, seed: int = 0, log=None,
              renders: int = 1) -> dict:
    """Check every integrator spec on ``scene_path`` (with ``params``; the film's longer side
    set to ``film_res`` pixels when given) against the cached ``path`` reference at
    ``ref_spp``, each rendered ``renders`` times (2: with the bias part of the block relMSE,
    :func:`check_integrator`). Returns ``{"meta": {...}, "rows": [CheckRow, ...]}``; ``log`` (e.g.
    ``print``) hears about each row as it is done."""
    params = dict(params or {})
    for name, value in (("spp", spp), ("ref_spp", ref_spp)):
        if int(value) < 1:
            raise ValueError(f"{name}={value}: must be >= 1")
    ref = reference_image(scene_path, params, spp=ref_spp, film_res=film_res,
                          verbose=log is not None)
    scene = load_scene(scene_path, film_res=film_res, **params)
    w, h = (int(v) for v in scene.sensors()[0].film().crop_size())
    rows = []
    for spec in integrators:
        row = check_integrator(scene, spec, ref, spp, seed, renders)
        rows.append(row)
        mark_noise_limited(rows)
        if log is not None:
            log(format_row(row))
    meta = {"scene": os.fspath(scene_path), "params": params, "film_res": film_res,
            "width": w, "height": h, "spp": spp, "ref_spp": ref_spp, "seed": seed,
            "variant": mi.variant(), "ratio_tolerance": RATIO_TOLERANCE,
            "block_relmse_max": BLOCK_RELMSE_MAX, "block": BLOCK, "renders": renders}
    return {"meta": meta, "rows": rows}


HEADER = f"{'integrator':<32} {'seconds':>8} {'mean ratio':>11} {'block relMSE':>13}"
#: the column two renders add (:func:`block_bias2`)
BIAS_HEADER = f"{'bias part ± se':>20} {'ratio se':>10}"


def format_row(row: CheckRow) -> str:
    """One line of the table: numbers, "OUT" when out of bounds, or "refused: <message>"."""
    if row.refused is not None:
        return f"{row.integrator:<32} refused: {row.refused}"
    line = (f"{row.integrator:<32} {row.seconds:>8.2f} {row.mean_ratio:>11.4f} "
            f"{row.block_relmse:>13.2e}")
    if row.bias2 is not None:
        line += f" {row.bias2:>+10.2e} ± {row.bias2_se:.1e} {row.ratio_se:>10.4f}"
        if row.noise_limited:
            return line + (f"  OUT (within {NOISE_SIGMAS:g} se of the bounds: noise-limited "
                           "at this spp)")
    if row.noise_limited:
        return line + "  OUT (path is OUT too: noise-limited at this spp)"
    return line + ("  OUT" if row.out else "")


def format_table(result: dict) -> str:
    """The report: what was compared, the bounds, the header and one row per integrator."""
    m = result["meta"]
    renders = m.get("renders", 1)
    block = f"block ({m['block']}x{m['block']} px) relMSE"
    lines = [f"check {m['scene']} {m['params'] or ''} {m['width']}x{m['height']}, "
             f"{m['spp']} spp against path at {m['ref_spp']} spp; OUT: |ratio - 1| > "
             f"{m['ratio_tolerance']:g} or {'its bias part' if renders == 2 else block} > "
             f"{m['block_relmse_max']:g}"]
    if renders == 2:
        lines.append(f"two renders per row (other samples, the same prepass): ratio and {block} "
                     "of their mean image; bias part: what of it their samples' noise does not "
                     "explain")
    lines.append(HEADER + (BIAS_HEADER if renders == 2 else ""))
    lines += [format_row(r) for r in result["rows"]]
    more = spp_to_see_bias(result["rows"], m["spp"], m["ref_spp"], renders)
    if more is not None:
        lines.append(f"path itself is OUT: at {m['spp']} spp the bounds measure noise. To tell "
                     f"a bias from it, rerun with --spp {more} --ref-spp "
                     f"{REF_SPP_FACTOR * more}")
    return "\n".join(lines)


def write_json(result: dict, path) -> None:
    """Write the report as JSON (rows as dicts; non-finite numbers as null)."""
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    data = {"meta": result["meta"], "rows": [asdict(r) for r in result["rows"]]}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(clean(data), f, indent=1, default=str)
