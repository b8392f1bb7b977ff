"""Polygon soups -> triangles (renderers.usd_loader's meshes).

- Meshes are triangulated as authored (subdivision meshes as their cage): triangles and quads
  vectorised, larger faces fanned when a vectorised check finds them convex, the others projected on
  their Newell plane and triangulated by earcut (mapbox-earcut, C++); a face of more than 256
  corners is first cut along checked diagonals into pieces (earcut is quadratic on star-like faces).
"""
from __future__ import annotations

import math

import mapbox_earcut
import numpy as np


def _newell_normal(pts: np.ndarray) -> np.ndarray:
    nxt = np.roll(pts, -1, axis=0)
    return np.array([np.sum((pts[:, 1] - nxt[:, 1]) * (pts[:, 2] + nxt[:, 2])),
                     np.sum((pts[:, 2] - nxt[:, 2]) * (pts[:, 0] + nxt[:, 0])),
                     np.sum((pts[:, 0] - nxt[:, 0]) * (pts[:, 1] + nxt[:, 1]))])


def _project_ccw(pts: np.ndarray) -> np.ndarray | None:
    """(n, 3) polygon -> (n, 2) in its best-fit plane, counter-clockwise; None when degenerate."""
    normal = _newell_normal(pts)
    nn = np.linalg.norm(normal)
    if not np.isfinite(nn) or nn < 1e-300:
        return None
    normal = normal / nn
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)  # (u, v, normal) right-handed: the polygon winds counter-clockwise in (u, v)
    c = pts - pts.mean(axis=0)
    return np.stack([c @ u, c @ v], axis=1)


SPLIT_MIN = 256  # polygons with more corners are first cut along diagonals into pieces of at most this size


def earcut(p2: np.ndarray) -> np.ndarray:
    tris = mapbox_earcut.triangulate_float64(np.ascontiguousarray(p2), np.array([len(p2)], np.uint32))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _cross2(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def _in_cone(p2: np.ndarray, a, b, eps: float):
    """Does the segment from corner a towards corner b start into the polygon (O'Rourke's InCone;
    counter-clockwise p2; near the cone's sides counts as outside)? a, b: ints or index arrays."""
    n = len(p2)
    a, b = np.asarray(a), np.asarray(b)
    prev, nxt, pa, pb = p2[(a - 1) % n], p2[(a + 1) % n], p2[a % n], p2[b % n]
    convex = _cross2(pa, nxt, prev) >= 0
    inside_convex = (_cross2(pa, pb, prev) > eps) & (_cross2(pb, pa, nxt) > eps)
    inside_reflex = ~((_cross2(pa, pb, nxt) >= -eps) & (_cross2(pb, pa, prev) >= -eps))
    return np.where(convex, inside_convex, inside_reflex)


def _crosses_no_edge(p2: np.ndarray, i: int, j: int, eps: float) -> bool:
    """Does the segment between corners i and j cross or touch no edge that is not incident to i or j
    (near-touching counts as touching, so the answer errs on no)?"""
    n = len(p2)
    k = np.arange(n)
    k1 = (k + 1) % n
    edges = (k != i) & (k1 != i) & (k != j) & (k1 != j)
    a, b = p2[k[edges]], p2[k1[edges]]
    pi, pj = p2[i][None, :], p2[j][None, :]
    o1, o2 = _cross2(pi, pj, a), _cross2(pi, pj, b)
    o3, o4 = _cross2(a, b, pi), _cross2(a, b, pj)
    touching = (np.minimum(o1, o2) <= eps) & (np.maximum(o1, o2) >= -eps) \
        & (np.minimum(o3, o4) <= eps) & (np.maximum(o3, o4) >= -eps)
    return not bool(np.any(touching))


def _split(p2: np.ndarray, idx: np.ndarray, eps: float, pieces: list) -> bool:
    """Cut the sub-polygon p2[idx] along diagonals between roughly opposite corners (O'Rourke's
    Diagonal: in the cone at both ends, crossing no edge) until every piece has at most SPLIT_MIN corners; False when some piece has
    no such diagonal. Candidates are screened by the cone test (vectorised); at most 12 per piece
    get the O(m) edge test."""
    m = len(idx)
    if m <= SPLIT_MIN:
        pieces.append(idx)
        return True
    sub = p2[idx]
    i = np.repeat((np.arange(64) * m) // 128, 7)  # starts over the first half, partners about half-way
    j = i + m // 2 + np.tile([0, 1, -1, 2, -2, 3, -3], 64)
    ok = _in_cone(sub, i, j, eps) & _in_cone(sub, j, i, eps)
    for a, b in list(zip(i[ok].tolist(), j[ok].tolist()))[:12]:
        if _crosses_no_edge(sub, a, b, eps):
            return (_split(p2, idx[a:b + 1], eps, pieces)
                    and _split(p2, np.concatenate([idx[b:], idx[:a + 1]]), eps, pieces))
    return False


def _triangulate_ccw(p2: np.ndarray, eps: float) -> np.ndarray:
    """Triangles of the counter-clockwise polygon p2. earcut is quadratic on spiky polygons such as
    stars (every needle's bounding box spans many corners), so a big polygon is first cut into
    pieces of at most SPLIT_MIN corners along checked diagonals, each piece cut by earcut; when the
    polygon has no such cut all the way down (a comb, say, on which earcut is fast anyway), earcut
    takes it whole."""
    idx = np.arange(len(p2))
    pieces: list[np.ndarray] = []
    if len(p2) > SPLIT_MIN and _split(p2, idx, eps, pieces):
        return np.concatenate([piece[earcut(p2[piece])] for piece in pieces])
    return earcut(p2)


def ear_clip(pts: np.ndarray) -> np.ndarray:
    """Triangulate one simple polygon (n, 3) given in order, concave or not; returns (T, 3) local indices.

    The polygon is projected on its best-fit plane (Newell normal), counter-clockwise, cut along
    checked diagonals into pieces of about SPLIT_MIN corners when it is bigger, and each piece
    triangulated by earcut (mapbox-earcut, C++); every triangle keeps the polygon's winding. A
    polygon earcut cannot cover (self-intersecting, e.g. a pentagram: its triangles do not add up to
    the polygon's signed area) is fanned, as is a degenerate one: there is no right answer."""
    n = len(pts)
    fan = np.stack([np.zeros(max(n - 2, 0), np.int64), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    if n < 3:
        return np.zeros((0, 3), np.int64)
    if n == 3:
        return fan
    p2 = _project_ccw(np.asarray(pts, dtype=np.float64))
    if p2 is None or not np.all(np.isfinite(p2)):
        return fan  # degenerate: any fan has zero area
    scale = float(np.abs(p2).max()) or 1.0
    eps = 1e-12 * scale * scale
    tris = _triangulate_ccw(p2, eps)
    a, b, c = p2[tris[:, 0]], p2[tris[:, 1]], p2[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    nxt = np.roll(p2, -1, axis=0)
    area2 = float(np.sum(p2[:, 0] * nxt[:, 1] - nxt[:, 0] * p2[:, 1]))  # shoelace: twice the signed area
    if len(tris) != n - 2 and not math.isclose(float(np.abs(cross).sum()), area2, rel_tol=1e-6, abs_tol=eps):
        return fan
    return tris


def _convex_mask(P: np.ndarray) -> np.ndarray:
    """(F, n, 3) polygons -> (F,) True where the polygon is convex (a fan triangulates it exactly).

    Convex: every corner turns the same way about the face normal and the turns add up to one full
    turn (a pentagram turns the same way at every corner but twice around)."""
    nxt = np.roll(P, -1, axis=1)
    normal = np.stack([np.sum((P[..., 1] - nxt[..., 1]) * (P[..., 2] + nxt[..., 2]), axis=1),
                       np.sum((P[..., 2] - nxt[..., 2]) * (P[..., 0] + nxt[..., 0]), axis=1),
                       np.sum((P[..., 0] - nxt[..., 0]) * (P[..., 1] + nxt[..., 1]), axis=1)], axis=1)
    nlen = np.linalg.norm(normal, axis=1)
    normal = normal / np.where(nlen > 0, nlen, 1.0)[:, None]
    e = nxt - P  # edge i: corner i -> i+1
    e_prev = np.roll(e, 1, axis=1)
    sin = np.einsum("fnk,fk->fn", np.cross(e_prev, e), normal)
    cos = np.einsum("fnk,fnk->fn", e_prev, e)
    scale = np.linalg.norm(e_prev, axis=2) * np.linalg.norm(e, axis=2)
    left = sin >= -1e-9 * scale
    turn = np.arctan2(sin, cos).sum(axis=1)
    return (nlen > 0) & np.all(left, axis=1) & (np.abs(turn - 2 * np.pi) < 1e-3)


def triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygon soup -> (T, 3) vertex indices, in face order within each face size.

    Triangles and quads are vectorised; larger faces are grouped by size, checked for convexity in
    one vectorised pass and fanned, and only the concave ones go to earcut (ear_clip) one by one."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    out = []
    tri = counts == 3
    if tri.any():
        s = starts[tri]
        out.append(np.stack([indices[s], indices[s + 1], indices[s + 2]], axis=1))
    quad = counts == 4
    if quad.any():
        s = starts[quad]
        a, b, c, d = (indices[s + k] for k in range(4))
        pa, pb, pc, pd = points[a], points[b], points[c], points[d]
        n = np.cross(pc - pa, pd - pb)  # the quad's normal (diagonal cross product)
        # Split along a-c unless b or d is a reflex corner, in which case a-c leaves the quad.
        ok_ac = (np.sum(np.cross(pb - pa, pc - pa) * n, axis=1) > 0) & (np.sum(np.cross(pc - pa, pd - pa) * n, axis=1) > 0)
        t1 = np.where(ok_ac[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
        t2 = np.where(ok_ac[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
        out += [t1, t2]
    for nv in np.unique(counts[counts > 4]):
        s = starts[counts == nv]
        poly = indices[s[:, None] + np.arange(nv)[None, :]]  # (F, nv)
        convex = _convex_mask(points[poly])
        if convex.any():
            pc = poly[convex]
            j = np.arange(1, nv - 1)
            fan = np.stack([np.repeat(pc[:, :1], nv - 2, axis=1), pc[:, j], pc[:, j + 1]], axis=2)
            out.append(fan.reshape(-1, 3))
        for pl in poly[~convex]:
            t = ear_clip(points[pl])
            if len(t):
                out.append(pl[t])
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)
