"""The scene corpus in scenes_xml/: every scene loads and renders, the many-lights scene really has
many (and tiny, bright) lights, and the furnace matches its exact answer Le / (1 - albedo)."""
import math
import os

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (sets DRJIT_LIBLLVM_PATH and the llvm_ad_rgb variant)
import mitsuba as mi

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES_DIR = os.path.join(ROOT, "scenes_xml")
SCENES = ["cornell_box", "many_lights", "caustic", "window_interior", "furnace", "office",
          "mixed_room"]


def scene_path(name):
    return os.path.join(SCENES_DIR, name + ".xml")


def load(name, **params):
    return mi.load_file(scene_path(name), **params)


def test_corpus_is_complete():
    present = sorted(f[:-4] for f in os.listdir(SCENES_DIR) if f.endswith(".xml"))
    assert present == sorted(SCENES)


@pytest.mark.parametrize("name", SCENES)
def test_scene_defaults(name):
    """Without overrides: a 128 x 128 film with a box filter, 64 spp, path with max_depth -1."""
    scene = load(name)
    sensor = scene.sensors()[0]
    assert list(sensor.film().size()) == [128, 128]
    assert sensor.sampler().sample_count() == 64
    assert sensor.film().rfilter().class_name() == "BoxFilter"
    integrator = scene.integrator()
    assert integrator.class_name() == "PathIntegrator"
    # max_depth -1 is stored as an unsigned 32-bit integer
    assert "max_depth = 4294967295" in str(integrator)
    assert len(scene.emitters()) >= 1


@pytest.mark.parametrize("name", SCENES)
def test_scene_renders_tiny(name):
    scene = load(name, res=16, spp=2)
    assert list(scene.sensors()[0].film().size()) == [16, 16]
    assert scene.sensors()[0].sampler().sample_count() == 2
    image = np.array(mi.render(scene, seed=0))
    assert image.shape == (16, 16, 3)
    assert np.isfinite(image).all()
    assert image.mean() > 0.0
    assert (image >= 0).all()


def _area_emitters(scene):
    """(shape, max-channel radiance, surface area) for each shape with an area emitter."""
    params = mi.traverse(scene)
    out = []
    for shape in scene.shapes():
        if shape.emitter() is None:
            continue
        radiance = np.array(params[shape.id() + ".emitter.radiance.value"]).ravel()
        out.append((shape, float(radiance.max()), float(np.array(shape.surface_area()).ravel()[0])))
    return out


def test_many_lights_scene():
    scene = load("many_lights", res=16, spp=2)
    emitters = scene.emitters()
    assert len(emitters) >= 100
    n_point = sum(mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition) for e in emitters)
    assert n_point >= 3

    bbox = scene.bbox()
    diag = float(np.linalg.norm(np.array(bbox.max) - np.array(bbox.min)))
    assert 10.0 <= diag <= 40.0

    area = _area_emitters(scene)
    assert len(area) >= 90
    median_radiance = np.median([r for _, r, _ in area])
    median_power = np.median([math.pi * r * a for _, r, a in area])  # flux of a one-sided emitter
    tiny_bright = []
    for shape, radiance, surface in area:
        if shape.shape_type() != int(mi.ShapeType.Sphere):
            continue
        radius = float(np.array(shape.bbox().max)[0] - np.array(shape.bbox().min)[0]) / 2
        # tiny (radius < 2 % of the diagonal), far brighter than a typical light, yet carrying at
        # least that light's power: the "spike" case
        if (radius < 0.02 * diag and radiance > 20 * median_radiance
                and math.pi * radiance * surface > median_power):
            tiny_bright.append(shape.id())
    assert len(tiny_bright) >= 10, tiny_bright
    # ordinary (not tiny-and-bright) area lights are there too
    assert len(area) - len(tiny_bright) >= 30


def test_furnace_emits_inward_and_has_uniform_parameters():
    scene = load("furnace", res=8, spp=1, albedo=0.9, Le=2.0)
    params = mi.traverse(scene)
    assert np.allclose(np.array(params["enclosure.bsdf.reflectance.value"]).ravel(), 0.9)
    assert np.allclose(np.array(params["enclosure.emitter.radiance.value"]).ravel(), 2.0)


@pytest.mark.parametrize("albedo, Le, spp", [(0.5, 1.0, 64), (0.8, 1.0, 256), (0.5, 3.0, 64)])
def test_furnace_matches_exact_radiance(albedo, Le, spp):
    """A closed diffuse enclosure of albedo rho emitting Le everywhere has radiance Le / (1 - rho).

    Pixels are independent (box filter, independent sampler), so the standard error of the image
    mean is the standard deviation of the pixels over sqrt(#pixels). The deviation must be under
    1 % and under 4 standard errors, and the run must be precise enough for 1 % to be a real bound.
    """
    scene = load("furnace", res=32, spp=spp, albedo=albedo, Le=Le, max_depth=-1)
    image = np.array(mi.render(scene, seed=1), dtype=np.float64)
    assert np.isfinite(image).all()
    # every channel sees the same uniform albedo and emission
    assert np.allclose(image[..., 0], image[..., 1]) and np.allclose(image[..., 0], image[..., 2])
    pixels = image.mean(axis=2).ravel()
    exact = Le / (1.0 - albedo)
    mean = pixels.mean()
    stderr = pixels.std(ddof=1) / math.sqrt(pixels.size)
    deviation = abs(mean - exact)
    assert stderr < 0.0025 * exact, f"too few samples: stderr {stderr:.4g}"
    assert deviation < 0.01 * exact, f"mean {mean:.5f} vs exact {exact:.5f}"
    assert deviation < 4 * stderr, f"mean {mean:.5f} vs exact {exact:.5f}, stderr {stderr:.3g}"
