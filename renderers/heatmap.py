"""Per-pixel aliasing heatmaps in the LogPSM colour key (Lloyd et al. 2007 figures).

Colour key (log scale in m, Lloyd's eq. 85 error, texel footprint in pixels):
  m <= 1  green (no perspective aliasing)  ->  yellow (m ~ 10^(1/3))  ->  red (m ~ 10^(2/3))
  ->  dark red at m >= 10.
Non-receivers (no hit, facing away from the light, outside a spot cone): dark grey.
Receivers where m cannot be measured (no neighbour on the same surface): mid grey.
Receivers outside every map that serves them: magenta (a lost receiver, whatever its aliasing).
Optional texel-grid overlay every N texels: a pixel is on a grid line when floor(u / N) or
floor(v / N) of the serving map changes between it and its right or lower neighbour.

The errors mode (`errors_image`) shows what went wrong instead of m: over the ground truth's shading
(receivers the exact shadow ray finds lit in light grey, exactly shadowed receivers in mid grey, surfaces
facing away from the light darker, no hit darkest; every one of these a pure grey, r = g = b), the
receivers the maps shadow although the light reaches them (WRONGLY_SHADOWED, vermillion) and the ones the
maps leave lit although they are in shadow (WRONGLY_LIT, blue; receivers outside their map are lit,
so an exactly shadowed one is wrongly lit). Colours from Okabe & Ito's colour-blind-safe palette (2008).
Exactly the misclassified pixels are coloured, no others.

Every heatmap written to a file carries its legend (`heatmap_with_legend`): the picture is the top-left
screen-sized region, the legend is the strip below it.
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
HEATMAP_MODES = ("m", "errors")
# Errors mode.
WRONGLY_SHADOWED = (213, 94, 0)  # the maps shadow it, the light reaches it
WRONGLY_LIT = (0, 114, 178)  # the maps leave it lit, it is in shadow
LIT_GREY = (215, 215, 215)  # exactly lit receiver
SHADOWED_GREY = (120, 120, 120)  # exactly shadowed receiver
FACING_AWAY_GREY = (72, 72, 72)  # a hit that is no receiver (faces away from the light, outside a cone)
NO_HIT_GREY = (32, 32, 32)


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


def misclassified_split(gt) -> dict:
    """Misclassified receivers of a GroundTruth split by how: the maps shadow a lit receiver
    (`wrongly_shadowed_pixels`) or leave a shadowed one lit (`wrongly_lit_pixels`); they sum to
    `misclassified_pixels`."""
    wrong = gt.misclassified & gt.receivers
    return {"wrongly_shadowed_pixels": int(np.sum(wrong & gt.map_shadowed)),
            "wrongly_lit_pixels": int(np.sum(wrong & ~gt.map_shadowed))}


def errors_image(gt, grid_every: int | None = None) -> Image.Image:
    """An RGB image of the screen's size: the misclassified receivers of a GroundTruth in two colours
    over its shading in greys (module doc). A grid overlay, if asked for, is drawn on the greys only."""
    sb = gt.screen
    h, w = gt.receivers.shape
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = NO_HIT_GREY
    img[sb.hit] = FACING_AWAY_GREY
    img[gt.receivers & ~gt.exact_shadowed] = LIT_GREY
    img[gt.receivers & gt.exact_shadowed] = SHADOWED_GREY
    wrong = gt.misclassified & gt.receivers
    if grid_every and gt.texel_uv is not None:
        line = grid_lines(gt.texel_uv, int(grid_every), gt.map_index) & gt.receivers & ~wrong
        blend = (1 - GRID_ALPHA) * img[line] + GRID_ALPHA * np.array(GRID, dtype=np.float64)
        img[line] = np.round(blend).astype(np.uint8)
    img[wrong & gt.map_shadowed] = WRONGLY_SHADOWED
    img[wrong & ~gt.map_shadowed] = WRONGLY_LIT
    return Image.fromarray(img, "RGB")


def _swatch_rows(entries: list[tuple[tuple[int, int, int], str]], width: int, columns: int = 1) -> Image.Image:
    """Colour swatches with labels, `columns` per row."""
    font = ImageFont.load_default()
    row_h, sw, pad = 14, 10, 6
    rows = (len(entries) + columns - 1) // columns
    img = Image.new("RGB", (width, rows * row_h + 4), (255, 255, 255))
    d = ImageDraw.Draw(img)
    col_w = (width - pad) // columns
    for k, (colour, label) in enumerate(entries):
        x, y = pad + (k % columns) * col_w, 2 + (k // columns) * row_h
        d.rectangle([x, y + 1, x + sw, y + 1 + sw], fill=tuple(colour), outline=(0, 0, 0))
        d.text((x + sw + 4, y), label, fill=(0, 0, 0), font=font)
    return img


def _stack(parts: list[Image.Image], width: int) -> Image.Image:
    img = Image.new("RGB", (width, sum(p.height for p in parts)), (255, 255, 255))
    y = 0
    for p in parts:
        img.paste(p, (0, y))
        y += p.height
    return img


def _caption(text: str, width: int) -> Image.Image:
    img = Image.new("RGB", (width, 14), (255, 255, 255))
    ImageDraw.Draw(img).text((6, 1), text, fill=(0, 0, 0), font=ImageFont.load_default())
    return img


def m_legend(width: int = 360, caption: str | None = None) -> Image.Image:
    """The m heatmap's legend: an optional caption, the colour bar (`legend_image`) and the other colours."""
    width = max(int(width), 200)
    rows = _swatch_rows([(OUTSIDE, "outside its map"), (UNMEASURED, "m not measurable"),
                         (NON_RECEIVER, "not a receiver")], width, columns=2 if width < 330 else 3)
    return _stack(([_caption(caption, width)] if caption else []) + [legend_image(width), rows], width)


def errors_legend(width: int = 360, counts: dict | None = None) -> Image.Image:
    """The errors image's legend: the two colours (with the pixel counts of `misclassified_split`
    when given) and the greys of the shading."""
    width = max(int(width), 200)

    def n(key):
        return f": {counts[key]} px" if counts is not None and key in counts else ""

    top = _swatch_rows([(WRONGLY_SHADOWED, "wrongly shadowed (maps: shadow, exact: lit)" + n("wrongly_shadowed_pixels")),
                        (WRONGLY_LIT, "wrongly lit (maps: lit, exact: shadow)" + n("wrongly_lit_pixels"))], width)
    greys = _swatch_rows([(LIT_GREY, "lit receiver"), (SHADOWED_GREY, "shadowed receiver"),
                          (FACING_AWAY_GREY, "faces away"), (NO_HIT_GREY, "no hit")], width, columns=2)
    return _stack([top, greys], width)


def with_legend(image: Image.Image, legend: Image.Image, gap: int = 4) -> Image.Image:
    """`image` at the top left, `legend` below it, on white."""
    width = max(image.width, legend.width)
    canvas = Image.new("RGB", (width, image.height + gap + legend.height), (255, 255, 255))
    canvas.paste(image.convert("RGB"), (0, 0))
    canvas.paste(legend, (0, image.height + gap))
    return canvas


def heatmap_with_legend(gt, mode: str = "m", grid_every: int | None = None) -> Image.Image:
    """What `evaluate --heatmap` writes: the m heatmap or the errors image of a GroundTruth with its legend."""
    h, w = gt.receivers.shape
    if mode == "m":
        return with_legend(ground_truth_heatmap(gt, grid_every),
                           m_legend(max(w, 240), f"m: a texel's footprint in pixels of this {w}x{h} screen"))
    if mode == "errors":
        return with_legend(errors_image(gt, grid_every),
                           errors_legend(max(w, 300), misclassified_split(gt)))
    raise ValueError(f"heatmap mode must be one of {', '.join(HEATMAP_MODES)}, got {mode!r}")


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


def _wrap(d: ImageDraw.ImageDraw, text: str, width: int, font) -> list[str]:
    """`text` broken at spaces into lines no wider than `width` (a single long word stays whole)."""
    lines, cur = [], ""
    for word in text.split(" "):
        trial = f"{cur} {word}" if cur else word
        if cur and d.textlength(trial, font=font) > width:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    return lines + [cur]


def side_by_side(images: list[Image.Image], titles: list[str], path: str | None = None,
                 gap: int = 8, legend: Image.Image | None = None) -> Image.Image:
    """Heatmaps next to each other with a title above each and one legend below (default: the m legend;
    pass `errors_legend()` for errors images)."""
    if len(images) != len(titles):
        raise ValueError("one title per image")
    font = ImageFont.load_default()
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    wrapped = [_wrap(probe, str(t), max(im.width, 60), font) for im, t in zip(images, titles)]
    title_h = 4 + 12 * max((len(w) for w in wrapped), default=1)
    width = sum(im.width for im in images) + gap * (len(images) + 1)
    tallest = max((im.height for im in images), default=0)
    if legend is None:
        legend = m_legend(min(360, max(200, width - 2 * gap)))
    height = title_h + tallest + 2 * gap + legend.height + gap
    canvas = Image.new("RGB", (max(width, legend.width + 2 * gap), height), (255, 255, 255))
    d = ImageDraw.Draw(canvas)
    x = gap
    for im, lines in zip(images, wrapped):
        for k, line in enumerate(lines):
            d.text((x, 3 + 12 * k), line, fill=(0, 0, 0), font=font)
        canvas.paste(im.convert("RGB"), (x, title_h))
        x += im.width + gap
    canvas.paste(legend, (gap, title_h + tallest + gap))
    if path is not None:
        canvas.save(path)
    return canvas
