"""scene.view: what the camera sees, and the extent of it."""
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401  (variant)
from mi_twopass.scene.view import collect_shading_points, view_diagonal


def facing_quad_behind_ground(glossy: bool = False):
    """A 2 m × 2 m quad 3 m in front of the camera, and a 200 m ground plane behind the
    camera that it never sees (it sets the scene's bounds)."""
    bsdf = {"type": "roughconductor"} if glossy else {"type": "diffuse"}
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "quad": {"type": "rectangle", "bsdf": bsdf},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().translate([0, 0, 10]).scale(100)},
        "light": {"type": "constant"},
    })


def test_view_diagonal_of_points_and_fallback():
    pts = np.array([[0, 0, 0], [3, 4, 0], [1, 1, 0]], float)
    assert view_diagonal(pts, 99.0) == pytest.approx(5.0)
    assert view_diagonal(np.zeros((1, 3)), 7.0) == 7.0  # one point: no extent
    assert view_diagonal(np.full((2, 3), np.nan), 7.0) == 7.0


def test_points_cover_what_the_camera_sees_only():
    """The quad fills the view (fov 40° at 3 m: 2.2 m across); the ground behind the camera
    is not seen, so the points' diagonal is the quad's (≤ 2·√2 m), not the ground's 283 m."""
    scene = facing_quad_behind_ground()
    p, n, rays = collect_shading_points(scene, max_points=256)
    assert len(p) > 100 and rays >= 256
    assert 2.0 < view_diagonal(p, 0.0) <= 2 * np.sqrt(2) + 1e-3
    assert np.allclose(p[:, 2], 0.0, atol=1e-4)


def test_lambertian_only_drops_glossy_hits():
    scene = facing_quad_behind_ground(glossy=True)
    assert len(collect_shading_points(scene, max_points=256)[0]) == 0
    assert len(collect_shading_points(scene, max_points=256, lambertian_only=False)[0]) > 100
