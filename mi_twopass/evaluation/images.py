"""Writing images: linear EXR through OpenEXR, tone-mapped sRGB PNG for people to look at."""
import os

import numpy as np


def write_exr(path, image) -> None:
    """Write a linear (H, W, 3) float image as a 32-bit float RGB EXR."""
    import OpenEXR

    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if img.ndim == 2:
        img = img[..., None]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if img.shape[-1] == 1:
        channels = {"Y": img[..., 0].copy()}
    else:
        channels = {"RGB": img[..., :3].copy()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(path)


def read_exr(path) -> np.ndarray:
    """Read an RGB EXR written by :func:`write_exr` (or any RGB EXR) as (H, W, 3) float32."""
    import OpenEXR

    with OpenEXR.File(path) as f:
        ch = f.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float32)
        if "RGBA" in ch:
            return np.asarray(ch["RGBA"].pixels, dtype=np.float32)[..., :3]
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], -1)


def srgb_tonemap(image, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance → 8-bit sRGB (exposure in stops, clip to [0, 1], sRGB transfer curve)."""
    x = np.nan_to_num(np.asarray(image, dtype=np.float64)) * 2.0**exposure
    x = np.clip(x, 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_png(path, image, exposure: float = 0.0) -> None:
    """Tone-map a linear image and write it as PNG."""
    import matplotlib.image

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    rgb = srgb_tonemap(image, exposure)
    if rgb.ndim == 3 and rgb.shape[-1] == 1:
        rgb = rgb[..., 0]
    matplotlib.image.imsave(path, rgb, cmap="gray" if rgb.ndim == 2 else None)
