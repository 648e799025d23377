"""Writes the two textures zoo.xml reads (both are committed; this is how they were made).

    .venv/bin/python docs/results/material-zoo-2026-11-28/scenes/make_textures.py

sky.exr: a 64 x 32 latitude-longitude sky, blue fading towards the horizon, with a 3 x 3-texel
sun about 1000x brighter than the sky. normals.exr: a 64 x 64 tangent-space normal map of
gentle sine bumps, stored raw (n * 0.5 + 0.5).
"""
import os

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
HERE = os.path.dirname(os.path.abspath(__file__))

h, w = 32, 64
sky = np.zeros((h, w, 3), np.float32)
for y in range(h):
    sky[y, :, :] = np.array([0.4, 0.6, 1.0]) * (1.2 - y / h)
sky[6:9, 40:43] = [200.0, 180.0, 150.0]
mi.Bitmap(sky).write(os.path.join(HERE, "sky.exr"))

u = np.linspace(0, 8 * np.pi, 64)
n = np.zeros((64, 64, 3), np.float32)
n[..., 0] = 0.3 * np.sin(u)[None, :]
n[..., 1] = 0.3 * np.cos(u)[:, None]
n[..., 2] = 1.0
n /= np.linalg.norm(n, axis=-1, keepdims=True)
mi.Bitmap((n * 0.5 + 0.5).astype(np.float32)).write(os.path.join(HERE, "normals.exr"))
