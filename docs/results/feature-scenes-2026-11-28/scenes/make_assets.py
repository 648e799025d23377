"""Writes the textures and the environment map the three feature scenes read (run in this
folder: ``python make_assets.py``; the files are committed beside it)."""
import mitsuba as mi
import numpy as np
from PIL import Image

mi.set_variant("scalar_rgb")
n = 64
y, x = np.mgrid[0:n, 0:n]
c = ((x // 8 + y // 8) % 2).astype(float)  # 8-pixel checker, warm tones
checker = np.stack([0.2 + 0.6 * c, 0.15 + 0.5 * c, 0.1 + 0.3 * c], -1)
Image.fromarray((checker * 255).astype(np.uint8)).save("checker.png")
u = (x / n) * 2 * np.pi * 4  # four ridges across the tangent-space normal map
nrm = np.stack([0.4 * np.cos(u), np.zeros_like(u), np.ones_like(u)], -1)
nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
Image.fromarray(((nrm * 0.5 + 0.5) * 255).astype(np.uint8)).save("normals.png")
Image.fromarray((((x // 4) % 2) * 255).astype(np.uint8)).save("opacity.png")  # stripes
H, W = 64, 128  # lat-long sky: a gradient, a dark ground half, a 4° sun of radiance ~300
th = (np.arange(H) + 0.5) / H * np.pi
ph = (np.arange(W) + 0.5) / W * 2 * np.pi
T, P = np.meshgrid(th, ph, indexing="ij")
sky = np.stack([0.3 + 0.2 * np.cos(T), 0.45 + 0.2 * np.cos(T), 0.8 + 0.1 * np.cos(T)], -1)
sky[T > np.pi / 2] = [0.15, 0.12, 0.1]
d = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1)
sun = np.array([0.5, 0.7, 0.3]) / np.linalg.norm([0.5, 0.7, 0.3])
sky[(d @ sun) > np.cos(np.radians(4))] = [300.0, 280.0, 250.0]
mi.Bitmap(sky.astype(np.float32)).write("sky.exr")
