"""PNG previews of coarse buffers (for people; the .npy files are the data)."""
from __future__ import annotations

import pathlib

import numpy as np
from PIL import Image

PREVIEW_SCALE = 3  # nearest-neighbour upscale so a 180 px buffer is readable


def _save(img: np.ndarray, path: pathlib.Path) -> str:
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    big = img.repeat(PREVIEW_SCALE, axis=0).repeat(PREVIEW_SCALE, axis=1)
    Image.fromarray(big).save(path)
    return path.name


def shade_depth(depth: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Near = white, far = dark, log scale; background black."""
    out = np.zeros(depth.shape, dtype=np.uint8)
    if hit.any():
        ld = np.log(np.maximum(depth[hit], 1e-6))
        lo, hi = ld.min(), ld.max()
        out[hit] = (255 * (1.0 - 0.85 * (ld - lo) / max(hi - lo, 1e-9))).astype(np.uint8)
    return out


def shade_lighting(hit, lit, boundary) -> np.ndarray:
    """Lit = light grey, shadowed = dark grey, boundary samples = red, background = black."""
    out = np.zeros(hit.shape + (3,), dtype=np.uint8)
    out[hit] = (60, 60, 70)
    out[hit & lit] = (210, 210, 200)
    out[boundary] = (230, 40, 40)
    return out


def save_previews(buffers, out_dir) -> list[str]:
    out = pathlib.Path(out_dir)
    names = [_save(shade_depth(buffers.depth, buffers.hit), out / "depth.png"),
             _save(((buffers.normal * 0.5 + 0.5) * 255 * buffers.hit[..., None]).astype(np.uint8),
                   out / "normal.png")]
    for k, lb in enumerate(buffers.lights):
        names.append(_save(shade_lighting(buffers.hit, lb.lit, lb.boundary), out / f"light{k}_lit.png"))
    return names
