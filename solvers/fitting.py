"""Geometric fitting steps, each a short function: convex hull, minimum-area rectangle, projections,
light-space bounds. Projections map to the canonical OpenGL clip space (solvers.shadow_map)."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.spatial import ConvexHull

PAD_TEXELS = 1.0  # map-space margin: texels kept outside the fitted receivers on each side, after the warp (fitting.texel_margin)


def _cross2(a, b) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def convex_hull_2d(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise hull vertices of (N, 2) points (Andrew's monotone chain); degenerate sets ok."""
    p = np.unique(np.asarray(p, dtype=np.float64), axis=0)
    if len(p) <= 2:
        return p
    if len(p) > 64:
        try:
            return p[ConvexHull(p).vertices]
        except Exception:  # collinear or otherwise degenerate: fall back to the chain below
            pass

    def half(pts):
        out = []
        for q in pts:
            while len(out) >= 2 and _cross2(out[-1] - out[-2], q - out[-2]) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def min_area_rectangle(points2d: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The minimum-area enclosing rectangle (one side along a hull edge, Freeman & Shapira 1975,
    as Chong & Gortler 2007 §2.3 use). Returns (angle, lo, hi): rotating points by -angle makes the
    rectangle axis-aligned with corners lo, hi."""
    hull = convex_hull_2d(points2d)
    if len(hull) < 3:
        lo, hi = (hull.min(0), hull.max(0)) if len(hull) else (np.zeros(2), np.zeros(2))
        return 0.0, lo, hi
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    best = None
    for a in angles:
        c, s = np.cos(a), np.sin(a)
        r = hull @ np.array([[c, -s], [s, c]])  # rotate by -a
        lo, hi = r.min(0), r.max(0)
        area = np.prod(hi - lo)
        if best is None or area < best[0] - 1e-15 * abs(area):
            best = (area, a, lo, hi)
    return float(best[1]), best[2], best[3]


def rotation_z(angle: float) -> np.ndarray:
    """4x4 rotating light-view x, y by -angle (so a rectangle at `angle` becomes axis-aligned)."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[0, :2] = [c, s]
    m[1, :2] = [-s, c]
    return m


def ortho(l: float, r: float, b: float, t: float, n: float, f: float) -> np.ndarray:
    """OpenGL glOrtho: view x in [l, r], y in [b, t], distance -z in [n, f] -> NDC [-1, 1]^3."""
    m = np.eye(4)
    m[0, 0], m[0, 3] = 2 / (r - l), -(r + l) / (r - l)
    m[1, 1], m[1, 3] = 2 / (t - b), -(t + b) / (t - b)
    m[2, 2], m[2, 3] = -2 / (f - n), -(f + n) / (f - n)
    return m


def frustum(l: float, r: float, b: float, t: float, n: float, f: float) -> np.ndarray:
    """OpenGL glFrustum: x/(-z) in [l/n, r/n] etc., distance -z in [n, f] -> NDC [-1, 1]^3."""
    m = np.zeros((4, 4))
    m[0, 0], m[0, 2] = 2 * n / (r - l), (r + l) / (r - l)
    m[1, 1], m[1, 2] = 2 * n / (t - b), (t + b) / (t - b)
    m[2, 2], m[2, 3] = -(f + n) / (f - n), -2 * f * n / (f - n)
    m[3, 2] = -1.0
    return m


def to_view(view: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return np.asarray(pts, dtype=np.float64) @ view[:3, :3].T + view[:3, 3]


def padded(lo: np.ndarray, hi: np.ndarray, frac: float, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Grow a box by `frac` of its size on each side, and to at least `floor` in each dimension."""
    size = hi - lo
    pad = np.maximum(size * frac, (floor - size).clip(min=0) / 2 + 1e-12)
    return lo - pad, hi + pad


def texel_margin(lo: np.ndarray, hi: np.ndarray, texels, margin: float, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Grow a box in map space (after the warp: s, t are affine in its coordinates) so that `margin`
    texels of an axis of `texels` texels lie outside it on each side: the box takes n - 2 margin texels,
    pad = size margin / (n - 2 margin); each dimension at least `floor`. Padding here, not in world space
    before a warp, keeps the margin a margin of texels at both ends of a warped map."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    n = np.broadcast_to(np.asarray(texels, dtype=np.float64), lo.shape)
    size = np.maximum(hi - lo, floor)
    pad = size * margin / np.maximum(n - 2.0 * margin, 1.0) + (floor - (hi - lo)).clip(min=0) / 2 + 1e-12 * size
    return lo - pad, hi + pad


def padded_range(lo: float, hi: float, frac: float, floor: float) -> tuple[float, float]:
    """padded() for one dimension in Python floats (the same operations; the optimizer's inner loop)."""
    size = hi - lo
    pad = max(size * frac, max(floor - size, 0.0) / 2 + 1e-12)
    return lo - pad, hi + pad


def extent_floor(max_abs: float) -> float:
    """The least extent a fitted box keeps: 1e-6 of the coordinates' magnitude, at least 1e-6
    (degenerate receivers, a point or a line, still give a map)."""
    return max(1e-6, 1e-6 * max_abs)


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def depth_range(d: np.ndarray, margin: float = 0.01, floor: float | None = None) -> tuple[float, float]:
    """[near, far] of distances `d` along the light's -Z, grown by `margin` of the span on each side
    (the span at least `floor`, default 1e-6 of the largest |d|, so a flat set still has a range)."""
    d = np.asarray(d, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return 0.0, 1.0
    near, far = float(d.min()), float(d.max())
    if floor is None:
        floor = max(1e-6 * float(np.abs(d).max()), 1e-9)
    span = max(far - near, floor)
    return near - margin * span, far + margin * span


def perspective_near(depths: np.ndarray, far: float) -> float:
    """A perspective light's near plane: 1e-4 of the far distance (at least 0.1 mm), pulled in to
    half the nearest receiver's depth so a receiver next to the light is never clipped (floor
    1e-7 of far). Casters between the light and the near plane are lost (Lloyd §B4: put the near
    plane close, trading depth precision)."""
    near = max(far * 1e-4, 1e-4)
    d = depths[np.isfinite(depths) & (depths > 0)]
    if len(d):
        near = min(near, 0.5 * float(d.min()))
    return max(near, far * 1e-7)


HULL_PREFILTER_POINTS = 1000  # below this, Qhull on every point is as fast as the prefilter


def _outside_octagon(xy: np.ndarray) -> np.ndarray | None:
    """Rows of xy that may be hull vertices (Akl & Toussaint 1978): the extreme points along 8
    directions are hull vertices, and a point strictly inside their convex polygon is not one, so
    the hull of the rest is the hull of all (a margin of 1e-9 of the extent keeps points near an
    edge). None when the polygon is degenerate (the caller hulls every point)."""
    x, y = xy[:, 0], xy[:, 1]
    u, v = x + y, x - y
    ext = [int(np.argmax(x)), int(np.argmax(u)), int(np.argmax(y)), int(np.argmin(v)),
           int(np.argmin(x)), int(np.argmin(u)), int(np.argmin(y)), int(np.argmax(v))]  # counter-clockwise
    poly = []
    for i in ext:
        if not poly or (i != poly[-1] and i != poly[0]):
            poly.append(i)
    if len(poly) < 3:
        return None
    scale = float(max(x.max() - x.min(), y.max() - y.min()))
    if not scale > 0:
        return None
    tol = 1e-9 * scale * scale
    inside = np.ones(len(xy), dtype=bool)
    for j in range(len(poly)):
        (px, py), (qx, qy) = xy[poly[j]], xy[poly[(j + 1) % len(poly)]]
        inside &= (qx - px) * (y - py) - (qy - py) * (x - px) > tol
    return np.flatnonzero(~inside)


@lru_cache(maxsize=256)
def _plane_axes(direction: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """light_plane_hull's (unit d, a, b) for a light direction (once per direction: np.cross on
    3-vectors costs more than the projection of a few hundred points)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(-d, a)  # (a, b, -d) right-handed: counter-clockwise in a view looking along d
    for v in (d, a, b):
        v.setflags(write=False)
    return d, a, b


def light_plane_hull(direction: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points a directional light's fits need, of many receivers: the vertices of their convex
    hull in the plane perpendicular to the light (counter-clockwise in any right-handed light view
    whose -Z is the light direction), and the two points nearest and farthest along the light.

    A directional map's fit is a 2D projective map of the light-plane coordinates (a rotation about
    the light, then a warp whose w depends on the in-plane y only), which keeps hulls and their
    vertex order, so min/max and hull-edge fits over the vertices equal those over all points.
    Returns (hull, depth_extremes); fewer than 3 points or a degenerate set: all points as the hull."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 8:
        return pts, pts[:0]
    d, a, b = _plane_axes(tuple(float(v) for v in np.asarray(direction, dtype=np.float64).ravel()))
    xy = np.column_stack([pts @ a, pts @ b])
    cand = _outside_octagon(xy) if len(pts) >= HULL_PREFILTER_POINTS else None
    try:
        if cand is None:
            hull = pts[ConvexHull(xy).vertices]  # Qhull: counter-clockwise for 2D input
        else:
            hull = pts[cand[ConvexHull(xy[cand]).vertices]]
    except Exception:  # collinear or coincident: every point
        return pts, pts[:0]
    z = pts @ d
    return hull, pts[[int(np.argmin(z)), int(np.argmax(z))]]



SNAP_STEPS_PER_OCTAVE = 8  # texel world sizes are rounded up to 2^(k/8) metres


def snap_to_texels(view: np.ndarray, projection: np.ndarray, resolution) -> np.ndarray | None:
    """Texel snapping for an unwarped (affine) map: the projection whose texel grid is fixed in the
    world, so that a camera that moves without turning sees no shimmering (the light frame, which
    follows the view direction, is unchanged). Per map axis i: the world spacing of its texel grid
    lines is rounded up to a size on a fixed geometric ladder (2^(k/8) m) with one texel of margin
    on each side, the map scaled about its centre to that size, then shifted by at most half a texel
    so that the world origin falls on a texel corner. Everything inside the map before stays inside.
    Returns None for a projective (warped or perspective) map."""
    P = np.asarray(projection, dtype=np.float64).copy()
    if not np.allclose(P[3], [0.0, 0.0, 0.0, 1.0]):
        return None
    origin = np.asarray(view, dtype=np.float64)[:, 3]  # the world origin in light view (homogeneous)
    for i, r in enumerate((int(resolution[0]), int(resolution[1]))):
        norm = float(np.linalg.norm(P[i, :3]))
        if norm == 0 or r < 4:
            continue
        spacing = (2.0 / r) / norm * r / (r - 2)  # world size of a texel, with a texel of margin per side
        size = 2.0 ** (math.ceil(math.log2(spacing) * SNAP_STEPS_PER_OCTAVE - 1e-9) / SNAP_STEPS_PER_OCTAVE)
        P[i] *= (2.0 / r) / norm / size
        o = float(P[i] @ origin)
        P[i, 3] += (round((o + 1.0) * r / 2.0) * 2.0 / r - 1.0) - o
    return P
