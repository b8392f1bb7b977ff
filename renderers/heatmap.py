"""Per-pixel aliasing heatmaps in the LogPSM colour key (Lloyd et al. 2007 figures).

Colour key (log scale in m, Lloyd's eq. 85 error, texel footprint in pixels):
  m <= 1  green (no perspective aliasing)  ->  yellow (m ~ 10^(1/3))  ->  red (m ~ 10^(2/3))
  ->  dark red at m >= 10.
Non-receivers (no hit, facing away from the light, outside a spot cone): dark grey.
Receivers where m cannot be measured (no neighbour on the same surface): mid grey.
Receivers outside every map that serves them: magenta (a lost receiver, whatever its aliasing).
Optional texel-grid overlay every N texels: a pixel is on a grid line when floor(u / N) or
floor(v / N) of the serving map changes between it and its right or lower neighbour.
"""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

M_MAX = 10.0
# (log10 m, RGB) stops of the key.
KEY = [(0.0, (0, 170, 0)), (1.0 / 3.0, (240, 220, 0)), (2.0 / 3.0, (230, 0, 0)), (1.0, (110, 0, 0))]
NON_RECEIVER = (48, 48, 48)
UNMEASURED = (128, 128, 128)
OUTSIDE = (200, 0, 200)
GRID = (255, 255, 255)
GRID_ALPHA = 0.6


def colour_key(m: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 colours for m values (NaN -> UNMEASURED)."""
    m = np.asarray(m, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.clip(np.log10(np.maximum(m, 1e-300)), 0.0, 1.0)
    xs = np.array([k[0] for k in KEY])
    cols = np.array([k[1] for k in KEY], dtype=np.float64)
    x = np.where(np.isnan(m), 0.0, x)
    rgb = np.stack([np.interp(x, xs, cols[:, c]) for c in range(3)], axis=-1)
    rgb[np.isnan(m)] = UNMEASURED
    return np.round(rgb).astype(np.uint8)


def grid_lines(texel_uv: np.ndarray, every: int, map_index: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: pixels where floor(u / every) or floor(v / every) changes towards a neighbour."""
    uv = np.asarray(texel_uv, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        cell = np.floor(uv / float(every))
    valid = np.all(np.isfinite(cell), axis=-1)
    line = np.zeros(uv.shape[:2], dtype=bool)
    for a, b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                 ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        both = valid[a] & valid[b]
        if map_index is not None:
            both &= map_index[a] == map_index[b]
        line[a] |= both & np.any(cell[a] != cell[b], axis=-1)
    return line


def heatmap_image(m: np.ndarray, receivers: np.ndarray, texel_uv: np.ndarray | None = None,
                  grid_every: int | None = None, outside: np.ndarray | None = None,
                  map_index: np.ndarray | None = None) -> Image.Image:
    """An RGB image of the screen's size: m in the colour key over receivers."""
    h, w = receivers.shape
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = NON_RECEIVER
    img[receivers] = colour_key(m[receivers])
    if outside is not None:
        img[outside & receivers] = OUTSIDE
    if grid_every and texel_uv is not None:
        line = grid_lines(texel_uv, int(grid_every), map_index) & receivers
        if outside is not None:
            line &= ~outside
        blend = (1 - GRID_ALPHA) * img[line] + GRID_ALPHA * np.array(GRID, dtype=np.float64)
        img[line] = np.round(blend).astype(np.uint8)
    return Image.fromarray(img, "RGB")


def ground_truth_heatmap(gt, grid_every: int | None = None) -> Image.Image:
    """The heatmap of a renderers.ground_truth.GroundTruth."""
    return heatmap_image(gt.m, gt.receivers, gt.texel_uv, grid_every, gt.outside, gt.map_index)


def legend_image(width: int = 360, height: int = 46) -> Image.Image:
    """The colour key as a bar from m = 1 to m = 10 (log scale) with tick labels."""
    img = Image.new("RGB", (width, height), (255, 255, 255))
    bar_h = height // 2
    pad = 10
    xs = np.linspace(0.0, 1.0, width - 2 * pad)
    bar = colour_key(10.0 ** xs)[None, :, :].repeat(bar_h, axis=0)
    img.paste(Image.fromarray(bar, "RGB"), (pad, 2))
    d = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    for m in (1, 2, 5, 10):
        x = pad + int(round(np.log10(m) * (width - 2 * pad - 1)))
        d.line([(x, 2 + bar_h), (x, 6 + bar_h)], fill=(0, 0, 0))
        label = ("m<=1" if m == 1 else ("m>=10" if m == 10 else f"{m}"))
        tw = d.textlength(label, font=font)
        d.text((min(max(0, x - tw / 2), width - tw), 8 + bar_h), label, fill=(0, 0, 0), font=font)
    return img


def side_by_side(images: list[Image.Image], titles: list[str], path: str | None = None,
                 gap: int = 8) -> Image.Image:
    """Heatmaps next to each other with a title above each and one colour legend below."""
    if len(images) != len(titles):
        raise ValueError("one title per image")
    font = ImageFont.load_default()
    title_h = 18
    width = sum(im.width for im in images) + gap * (len(images) + 1)
    tallest = max((im.height for im in images), default=0)
    legend = legend_image(min(360, max(120, width - 2 * gap)))
    height = title_h + tallest + 2 * gap + legend.height + gap
    canvas = Image.new("RGB", (max(width, legend.width + 2 * gap), height), (255, 255, 255))
    d = ImageDraw.Draw(canvas)
    x = gap
    for im, title in zip(images, titles):
        d.text((x, 3), str(title), fill=(0, 0, 0), font=font)
        canvas.paste(im.convert("RGB"), (x, title_h))
        x += im.width + gap
    canvas.paste(legend, (gap, title_h + tallest + gap))
    if path is not None:
        canvas.save(path)
    return canvas
