"""Pilot samples: what one more sample per pixel costs and how much it varies, per estimator.

``twopass``'s cost model (:mod:`mi_twopass.compose.cost`) needs, per candidate estimator, two
numbers measured on *this* scene and camera: the seconds one sample of every pixel costs and the
relative variance of one sample. Both come from a pilot: P pixels of the film drawn at random
(the same pixels for every candidate), M independent camera samples each, traced by the
candidate's ``sample`` exactly as its render would trace them.

Cost per sample. A Dr.Jit call costs a fixed part (tracing the loop in Python, looking up the
compiled kernel, launching it) plus a part per lane, which is what a render's cost per sample
is made of. The pilot traces its samples in one call and takes the per-lane part from Dr.Jit's
kernel history: the execution time of the call's kernels, which leaves out the Python tracing,
the launch and any compilation, over its lanes; a full-film sample costs that × film pixels.
The fixed part is not small: tracing a loop that calls every emitter's sampling code grows with
the emitters, and at 256² it was 60 % of a 4M run on many_lights (0.025 of 0.042 s: a pilot
that divided wall time by lanes put path at 0.050 s per sample where its renders take 0.0146).
Until session 19 the pilot timed M, 4M and 4M runs and one of 16 pixels × 1 sample for the
fixed part, subtracted from the faster 4M run; from session 19 to 24 it ran M/9 and 8M/9 and
took the smaller per-lane time of the two. The larger run set it almost always (the small one's
lanes cost more: thread start-up), and on many_lights the second call's tracing and code
generation (about 0.04 s per candidate) was a third of the pilot's time. Since session 25 one
call traces all M = 144 samples (:data:`CALLS`): twopass's pilot went 0.319–0.338 →
0.228–0.245 s on many_lights at 256², 256 spp, and 0.226–0.257 → 0.211–0.220 s on
window_interior at 64 spp, for the same choices (``tools/pilot_timing.py``, alternating
checkouts).

Relative variance. For pixel p, channel k, the sample variance s²_pk of the M samples, over
the squared pixel value R_pk of a reference shared by all candidates, with relMSE's ε
(:data:`mi_twopass.evaluation.metrics.RELMSE_EPS`)::

    v = mean_pk s²_pk / (R_pk² + ε)

so that a render of N samples per pixel has an expected relMSE of v / N (plus the square of its
bias), the metric of the harness.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..evaluation.metrics import RELMSE_EPS
from ..host_arrays import jit
from ..seeds import hash31
from .cost import RenderProbe

#: salt of the pilot's sampler streams (mi_twopass.seeds)
_SALT_PILOT = 0x5117
#: salt of the blocks a prepass's own noise is measured on (choose_blocks)
_SALT_BLOCKS = 0xB10C


@dataclass(frozen=True)
class PilotSettings:
    """Pixels drawn from the film and camera samples per pixel, traced in one call. Defaults:
    1024 pixels × 144 samples."""

    pixels: int = 1024
    samples: int = 144


@dataclass
class PilotPixels:
    """The film pixels of a pilot: flat indices ``index`` (row-major), the film's size."""

    index: np.ndarray
    width: int
    height: int

    @property
    def film_pixels(self) -> int:
        return self.width * self.height


#: a pilot's samples per candidate are at most this share of the render's path samples (its
#: samples per pixel × film pixels): a short render gets fewer pilot pixels than
#: ``PilotSettings.pixels``, at least :data:`MIN_PIXELS` (:func:`pixel_count`). The pilot is
#: what twopass loses where the structure it finds pays little: at 256², 16 spp the office's
#: 1024-pixel pilot was 0.25 s of twopass's 0.86 s, where spike_gather alone reaches relMSE
#: 0.01 in 0.57 s (bench, session 19); with 384 pixels twopass took 0.71 s, and window_interior
#: 1.10 -> 0.99 s, for the same choices
PIXEL_SHARE = 0.05
#: the fewest pixels a scaled pilot draws (unless ``PilotSettings.pixels`` asks for fewer)
MIN_PIXELS = 256


def pixel_count(settings: PilotSettings, spp: int, film_pixels: int) -> int:
    """The pilot's pixels for a render of ``spp`` samples per pixel of ``film_pixels`` pixels:
    ``settings.pixels``, or fewer where its samples would pass :data:`PIXEL_SHARE` of the
    render's, down to :data:`MIN_PIXELS`. The gates before the pilot (``cost.pilot_too_dear``)
    weigh the full ``settings.pixels``: whether a pilot can pay is asked of the pilot as
    designed, how large it need be of the render it decides."""
    per_pixel = settings.samples
    fit = int(PIXEL_SHARE * max(spp, 1) * film_pixels / per_pixel)
    return int(min(settings.pixels, max(fit, MIN_PIXELS)))


def choose_pixels(sensor, count: int, seed: int) -> PilotPixels:
    """``count`` distinct pixels of ``sensor``'s film (all of them if it has fewer), uniformly
    at random."""
    width, height = (int(v) for v in sensor.film().crop_size())
    n = width * height
    rng = np.random.default_rng(hash31(seed, _SALT_PILOT))
    index = np.arange(n) if count >= n else np.sort(rng.choice(n, size=count, replace=False))
    return PilotPixels(index=index.astype(np.uint32), width=width, height=height)


def choose_blocks(sensor, count: int, size: int, seed: int) -> PilotPixels:
    """``count`` distinct ``size`` × ``size``-pixel blocks of ``sensor``'s film, on the grid of
    ``check``'s block means and inside the film, drawn uniformly at random (all of them where
    the film has fewer; one block of the whole film where it is smaller than a block). The
    pixels are listed block by block, each block's row-major."""
    width, height = (int(v) for v in sensor.film().crop_size())
    bw, bh = width // size, height // size
    if bw == 0 or bh == 0:
        return PilotPixels(index=np.arange(width * height, dtype=np.uint32), width=width,
                           height=height)
    rng = np.random.default_rng(hash31(seed, _SALT_BLOCKS))
    chosen = np.arange(bw * bh) if count >= bw * bh else rng.choice(bw * bh, size=count,
                                                                      replace=False)
    dy, dx = np.divmod(np.arange(size * size), size)
    rows = (chosen // bw)[:, None] * size + dy[None, :]
    cols = (chosen % bw)[:, None] * size + dx[None, :]
    return PilotPixels(index=(rows * width + cols).ravel().astype(np.uint32), width=width,
                       height=height)


def _camera_rays(sensor, pixels: PilotPixels, samples: int, sampler):
    """One camera ray per (pixel, sample), sample-minor, with its importance weight."""
    idx = jit(mi.UInt32, np.repeat(pixels.index, samples))  # data, not a size baked into a kernel
    offset = mi.Point2f(mi.Float(idx % pixels.width), mi.Float(idx // pixels.width))
    crop = sensor.film().crop_offset()
    pos = (offset + mi.Vector2f(crop) + sampler.next_2d()) / mi.Vector2f(
        sensor.film().size())
    ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), pos, sampler.next_2d())
    return ray, weight


def run_samples(scene, sensor, pixels: PilotPixels, samples: int, estimator, seed: int):
    """``estimator(scene, sampler, ray, active) -> Spectrum`` on ``samples`` camera rays per
    pixel. Returns (values of shape (pixels, samples, 3), seconds including evaluation)."""
    n = len(pixels.index) * samples
    sampler = mi.load_dict({"type": "independent"})
    # an opaque seed: a literal would make every run compile its kernel anew
    sampler.seed(dr.opaque(mi.UInt32, hash31(seed, _SALT_PILOT, samples)), n)
    t0 = time.perf_counter()
    ray, weight = _camera_rays(sensor, pixels, samples, sampler)
    L = estimator(scene, sampler, ray, mi.Bool(True))
    L = mi.Color3f(L) * mi.Color3f(weight) + dr.zeros(mi.Color3f, n)  # n lanes, even if constant
    dr.eval(L)
    dr.sync_thread()
    values = samples_array(L, pixels, samples)
    seconds = time.perf_counter() - t0
    return values, seconds


def samples_array(spectrum, pixels: PilotPixels, samples: int) -> np.ndarray:
    """A pilot's RGB values (sample-minor lanes) as an array (pixels, samples, 3): a view of
    channel-major storage (pixels, 3, samples), so that the reductions over the samples (the
    pilot's means and variances) read contiguous memory. With the channels innermost, as until
    session 24, ``np.var`` over the samples of 1024 × 144 took 5.2 ms instead of 0.4, and the
    twopass pilot's variances and bias test about 0.05 s on window_interior."""
    shape = (len(pixels.index), samples)
    arr = np.stack([np.asarray(c).reshape(shape) for c in (spectrum.x, spectrum.y, spectrum.z)],
                   axis=1)
    return arr.transpose(0, 2, 1)


def join_samples(arrays) -> np.ndarray:
    """Pilot arrays of the same pixels (pixels, samples_i, 3), their samples joined: as
    ``np.concatenate(arrays, axis=1)``, in :func:`samples_array`'s channel-major storage."""
    return np.concatenate([a.transpose(0, 2, 1) for a in arrays], axis=2).transpose(0, 2, 1)


@dataclass
class PilotRun:
    """One candidate's pilot: its samples (pixels, samples, 3), its seconds per lane (module
    docstring), the seconds of the timed runs and the lanes run."""

    values: np.ndarray
    seconds_per_lane: float
    seconds: float
    lanes: int

    def seconds_per_spp(self, film_pixels: int) -> float:
        """Predicted seconds of one sample of every pixel of the film."""
        return self.seconds_per_lane * film_pixels


#: Dr.Jit calls a candidate's pilot makes, each paying the fixed part of a call (:func:`pilot`)
CALLS = 1


def pilot_samples(settings: PilotSettings, pixels: PilotPixels) -> int:
    """The camera samples one candidate's pilot traces: its pixels × samples."""
    return len(pixels.index) * settings.samples


def with_kernel_history(call):
    """``call()`` with Dr.Jit's kernel history on → (its result, the seconds its kernels spent
    compiling (codegen and backend), the seconds they spent executing)."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()  # reading it clears it
        result = call()
        history = dr.kernel_history()
    compiling = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0)
                    for k in history) / 1000.0
    executing = sum(k.get("execution_time", 0.0) for k in history) / 1000.0
    return result, compiling, executing


def timed_samples(scene, sensor, pixels: PilotPixels, samples: int, estimator, seed: int):
    """:func:`run_samples` with the kernel history on: (values, seconds, the execution seconds
    of the call's kernels, or its seconds where the history has none)."""
    (values, seconds), _, executing = with_kernel_history(
        lambda: run_samples(scene, sensor, pixels, samples, estimator, seed))
    return values, seconds, (executing if executing > 0.0 else seconds)


def pilot(scene, sensor, pixels: PilotPixels, settings: PilotSettings, estimator, seed: int):
    """Run ``estimator`` with ``settings.samples`` samples per pixel in one call; the cost per
    lane is its kernels' execution time over its lanes (module docstring) →
    :class:`PilotRun`."""
    lanes = pilot_samples(settings, pixels)
    values, seconds, executing = timed_samples(scene, sensor, pixels, settings.samples,
                                               estimator, seed)
    return PilotRun(values=values, seconds_per_lane=executing / max(lanes, 1), seconds=seconds,
                    lanes=lanes)


def probe_render(scene, sensor, integ, seed: int):
    """``integ``'s render of the whole film at one sample per pixel, timed to the image on the
    host → :class:`mi_twopass.compose.cost.RenderProbe`.

    Dr.Jit's kernel history splits the call's seconds: its kernels' compilation (codegen and
    backend time, paid once per process and kernel cache, not per render) is taken off; their
    execution time is the part that grows with the samples per pixel (an upper bound of it:
    one sample per pixel fills a GPU least); the rest, recording the loop, launching, the
    film's development and the copy back, is the fixed part."""
    def timed_render():
        t0 = time.perf_counter()
        np.asarray(integ.render(scene, sensor, seed=seed, spp=1))  # waits for the kernels
        return time.perf_counter() - t0

    wall, compiling, executing = with_kernel_history(timed_render)
    work = max(wall - compiling, 0.0)
    per_spp = min(executing, work)
    return RenderProbe(fixed=work - per_spp, per_spp=per_spp)


def relative_variance(values: np.ndarray, reference: np.ndarray, eps: float = RELMSE_EPS):
    """v = mean over pixels and channels of s² / (R² + ε) (module docstring): the relMSE of a
    one-sample-per-pixel render. ``values``: (pixels, samples, 3); ``reference``: (pixels, 3)."""
    var = np.var(values, axis=1, ddof=1)
    return float(np.mean(var / (reference**2 + eps)))


def pixel_means(values: np.ndarray) -> np.ndarray:
    """The pilot's estimate of each pixel: (pixels, 3)."""
    return values.mean(axis=1)


def path_reference(path_values: np.ndarray, others: list) -> np.ndarray:
    """The pixels' reference R for path's relative variance once other pilots ran on the same
    pixels: the average of *their* means, not of path's own (path's own where there are none).

    A heavy-tailed pilot normalises its own fireflies away against its own means: a firefly F
    among n samples of a pixel gives s² ≈ F²/n and a mean ≈ F/n, so the pixel's s²/R² stays
    near n however rare and bright F is. On caustic.xml at 256² path's relative variance read
    1.6–2.2 against its own means and 1.9–3.9 against the average of its and rex's (the
    reference every pilot had until session 9), against about 36 from its curve in the
    harness; against rex's means alone, 5.9–72 (six pilot pairs, ``tools/pilot_variance.py``).
    The structures' pilots are smooth where path's is heavy-tailed, and a few per cent of
    bias in their means moves R² by as much, so the candidates keep the pooled reference.
    On the Cornell box (radiosity_gather) and the office (spike_gather) path's variance is
    the same within 5 % against either reference."""
    if not others:
        return pixel_means(path_values)
    return np.mean([pixel_means(v) for v in others], axis=0)
