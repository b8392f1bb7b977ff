"""The receivers and samples of each light of a solve (what the solvers see of it: LightProblem).

receiver_points: the visible receivers a map must contain, from the coarse pass (service.pipeline,
renderers.coarse): the coarse hits in the light's receiver mask, the edge pass's fine hits, the frusta of the
cells it traced and the tangent-plane reach of the mask's edge pixels, each with its view-depth slack (the
cascade overlap). receiver_prep: its part that depends on the camera alone, kept per camera by
service.coarse_cache. light_problems: per light, the metric's samples (solvers.samples) and these receivers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..renderers.coarse import DEPTH_CONTINUITY, CoarseBuffers, edge_cells
from ..solvers.samples import Samples, select_samples
from .rigs import ResolvedRig


@dataclass
class LightProblem:
    """What the solvers see of one light: the metric's samples and every visible receiver."""

    light: object
    samples: Samples
    receivers: np.ndarray  # (N, 3) world positions of visible receivers that could be in shadow
    receiver_slack: np.ndarray  # (N,) view-depth change to a neighbouring coarse pixel (cascade overlap)
    sample_rows: np.ndarray | None = None  # per sample, the index of the receiver at its pixel


EDGE_REACH = 1.5  # coarse pixels: a full-resolution receiver next to a coarse non-receiver can be up to ~1.4 coarse pixels (diagonally) from the nearest coarse receiver
REACH_DEPTH_FACTOR = 2.0  # an extrapolated receiver stays within this factor of its coarse hit's distance
FINE_REACH_DEPTH_FACTOR = 1.25  # the same for the edge pass's one-fine-step reach (a fine step is a pixel or two)


def receiver_points(camera, buffers: CoarseBuffers, mask: np.ndarray, bounds=None,
                    fine_receivers: np.ndarray | None = None,
                    prep: "ReceiverPrep | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """The receivers the camera sees, (points, view-depth slack): the coarse hits in `mask` (first, in
    row-major order: sample_rows), the edge pass's hits that are receivers (`buffers.fine`,
    renderers.coarse.fine_points, where `fine_receivers` is True: rays through a finer grid over the
    coarse pixels next to a geometric edge and along the screen's border, so slivers and silhouettes a
    coarse ray missed are real hit points; those on the fine grid's own edges and on the border), and, for the mask's edge pixels the edge pass did not
    refine (the receiver region ends on a continuous surface: facing or cone changes), where the rays
    EDGE_REACH coarse pixels away meet the pixel's tangent plane, kept within REACH_DEPTH_FACTOR of the
    hit's distance (the pixel's footprint at its own depth where the plane is grazing or behind).
    Never the far plane or the scene's bounds (`bounds` is unused, kept for callers). Without an edge
    pass (buffers.fine None) every mask edge pixel is extrapolated.

    `prep`: receiver_prep(camera, buffers), what of this depends on the camera's buffers alone (kept per
    camera by service.coarse_cache, so a sun move computes only the mask's share); the same values, bit
    for bit (tests/test_solve_latency_cache.py)."""
    pts = buffers.position[mask]
    slack = depth_slack(buffers.depth, mask)[mask]
    if not mask.any():
        return pts, slack
    padded = np.pad(mask, 1)
    interior = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    edge = mask & ~interior
    parts, slacks = [pts], [slack]
    fine = getattr(buffers, "fine", None)
    use_fine = fine is not None and fine_receivers is not None and bool(fine_receivers.any())
    if fine is not None:
        edge &= ~(prep.edge_cells if prep is not None else edge_cells(buffers.hit, buffers.depth))
    if use_fine:
        fine_edge, fine_slack = fine.edges(fine_receivers, neighbours=prep.fine_neighbours if prep is not None else None)
        # the edge pass's receivers on its own edges and on the screen's border: those inside a
        # continuous fine patch lie between them (fewer points for every fit)
        border = prep.fine_border if prep is not None else fine_border(fine)
        keep = fine_edge | (border & fine_receivers)
        parts.append(fine.position[keep])
        slacks.append(fine_slack[keep])
        cell_pts, cell_slack = cell_frusta(camera, buffers, fine, fine_receivers,
                                           table=prep.cells if prep is not None else None)
        parts.append(cell_pts)
        slacks.append(cell_slack)
    rows, cols = np.nonzero(edge)
    if len(rows):
        if prep is not None:  # tangent_reach is a function of each pixel alone: its rows, computed ahead
            parts.append(prep.coarse_reach[prep.coarse_row[rows * buffers.width + cols]].reshape(-1, 3))
        else:
            parts.append(tangent_reach(camera, buffers, cols + 0.5, rows + 0.5, buffers.position[rows, cols],
                                       buffers.normal[rows, cols], EDGE_REACH))
        slacks.append(_reach_slack(camera, parts[-1], buffers.depth[rows, cols]))
    if use_fine and fine_edge.any():
        # the edge pass's own edges: its receivers next to a non-receiver or a depth jump, reached one
        # fine step (the full-resolution pixels between two fine rays) along their planes
        parts.append(_fine_reach(camera, buffers, fine, np.nonzero(fine_edge)[0], prep))
        slacks.append(_reach_slack(camera, parts[-1], fine.depth[fine_edge]))
    return np.vstack(parts), np.concatenate(slacks)


@dataclass
class CellTable:
    """cell_frusta's part that needs no receiver test: each (fine hit, edge cell it is a corner of) pair,
    the cells with a traced corner that missed, and each cell's smallest and largest fine-hit view depth."""

    cell: np.ndarray  # (K,) flat coarse cell index
    hit: np.ndarray  # (K,) index of the fine hit (FinePoints arrays)
    missed: np.ndarray  # (h w,) bool
    dmin: np.ndarray  # (h w,) float64, inf where no fine hit
    dmax: np.ndarray


def cell_table(buffers: CoarseBuffers, fine) -> CellTable:
    f = fine.factor
    h, w = buffers.height, buffers.width
    W = fine.grid_shape[1]
    cells = edge_cells(buffers.hit, buffers.depth).ravel()
    n_cells = h * w
    missed_cell = np.zeros(n_cells, dtype=bool)
    dmin = np.full(n_cells, np.inf)
    dmax = np.full(n_cells, -np.inf)
    hit_flat = np.zeros(fine.grid_shape[0] * W, dtype=bool)
    hit_flat[fine.flat] = True
    missed = fine.traced[~hit_flat[fine.traced]]
    cell_parts, hit_parts = [], []
    for flat, kind in ((fine.flat, 0), (missed, 1)):
        vj, vi = np.divmod(flat, W)
        for dj in (0, 1):
            for di in (0, 1):
                cj, ci = vj // f - dj, vi // f - di
                ok = (cj >= 0) & (cj < h) & (ci >= 0) & (ci < w)
                if dj:
                    ok &= vj % f == 0
                if di:
                    ok &= vi % f == 0
                c = np.where(ok, cj * w + ci, 0)
                ok &= cells[c]
                c = c[ok]
                if kind == 1:
                    missed_cell[c] = True
                    continue
                cell_parts.append(c)
                hit_parts.append(np.nonzero(ok)[0])
                d = fine.depth[ok]
                np.minimum.at(dmin, c, d)
                np.maximum.at(dmax, c, d)
    return CellTable(np.concatenate(cell_parts).astype(np.int32), np.concatenate(hit_parts).astype(np.int32),
                     missed_cell, dmin, dmax)


def cell_frusta(camera, buffers: CoarseBuffers, fine, fine_receivers: np.ndarray,
                continuity: float = DEPTH_CONTINUITY, table: CellTable | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(2 K, 3) points and their view-depth slack: for each coarse cell the edge pass traced that has a
    receiver among its fine hits and a discontinuity there (a traced corner that missed or is not a
    receiver, or hits whose view depths span more than `continuity`), the corners of the cell's view
    frustum (its four corner rays) at the smallest and the largest view depth of its fine hits. A sliver
    thinner than a fine step between those rays (never traced) lies in that frustum when its depth is
    within the hits' range; the frustum is convex and every fit is projective, so containing the eight
    corners contains it (a corner ray shared by such cells: once, over the union of their ranges). Slack: the depth range (every cascade meeting it fits the corners).
    `table`: cell_table(buffers, fine), which depends on the camera alone."""
    t = cell_table(buffers, fine) if table is None else table
    h, w = buffers.height, buffers.width
    rec = np.asarray(fine_receivers, dtype=bool)[t.hit]
    has_rec = np.zeros(h * w, dtype=bool)
    has_rec[t.cell[rec]] = True
    has_other = t.missed.copy()
    has_other[t.cell[~rec]] = True
    dmin, dmax = t.dmin, t.dmax
    sel = np.nonzero(has_rec & (has_other | (dmax > dmin * (1.0 + continuity))))[0]
    if not len(sel):
        return np.zeros((0, 3)), np.zeros(0)
    cj, ci = np.divmod(sel, w)
    # each corner ray once (neighbouring cells share corners), over the union of their cells' depth ranges
    corner = ((cj[:, None] + np.array([0, 0, 1, 1])) * (w + 1) + ci[:, None] + np.array([0, 1, 0, 1])).ravel()
    lo_d, hi_d = np.repeat(dmin[sel], 4), np.repeat(dmax[sel], 4)
    ids, inv = np.unique(corner, return_inverse=True)
    near = np.full(len(ids), np.inf)
    far = np.full(len(ids), -np.inf)
    np.minimum.at(near, inv, lo_d)
    np.maximum.at(far, inv, hi_d)
    v, u = np.divmod(ids, w + 1)  # corner positions, coarse-pixel units
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    x = (u * (2.0 / w) - 1.0) * tw  # Camera.ray_directions' convention; forward component 1
    y = (1.0 - v * (2.0 / h)) * th
    d = camera.forward + x[:, None] * camera.right + y[:, None] * camera.up
    pts = np.concatenate([camera.position + near[:, None] * d, camera.position + far[:, None] * d])
    return pts, np.tile(far - near, 2)


def _fine_reach(camera, buffers: CoarseBuffers, fine, idx: np.ndarray, prep: "ReceiverPrep | None" = None) -> np.ndarray:
    """(4 len(idx), 3): tangent_reach of the edge pass's hits idx, one fine step (prep's rows where it has them)."""
    def reach(i):
        u, v = fine.uv()
        return tangent_reach(camera, buffers, u[i], v[i], fine.position[i], fine.normal[i], 1.0 / fine.factor,
                             FINE_REACH_DEPTH_FACTOR)

    if prep is None:
        return reach(idx)
    row = prep.fine_row[idx]
    have = row >= 0
    if have.all():
        return prep.fine_reach[row].reshape(-1, 3)
    out = np.empty((len(idx), 4, 3))
    out[have] = prep.fine_reach[row[have]]
    out[~have] = reach(idx[~have]).reshape(-1, 4, 3)
    return out.reshape(-1, 3)


def fine_reach_candidates(fine, neighbours: np.ndarray, continuity: float = DEPTH_CONTINUITY) -> np.ndarray:
    """(M,) bool: the edge pass's hits where a directional light's receiver region can end (FinePoints.edges):
    next to a traced corner that missed, a hit with another normal (facing can differ) or a depth jump. A spot
    light's cone can end anywhere: _fine_reach computes the others when they are asked for."""
    out = np.zeros(len(fine.flat), dtype=bool)
    nrm = [np.ascontiguousarray(fine.normal[:, k]) for k in range(3)]
    for s in range(4):
        j = neighbours[s]
        hit = j >= 0
        jj = np.where(hit, j, 0)
        dn = fine.depth[jj]
        other = (nrm[0][jj] != nrm[0]) | (nrm[1][jj] != nrm[1]) | (nrm[2][jj] != nrm[2])
        out |= (j == -1) | (hit & (other | (np.abs(dn - fine.depth) > continuity * np.minimum(dn, fine.depth))))
    return out


def fine_border(fine) -> np.ndarray:
    """(M,) bool: the edge pass's hits on its grid's outer rows and columns (the screen's border)."""
    vj, vi = np.divmod(fine.flat, fine.grid_shape[1])
    return (vi == 0) | (vj == 0) | (vi == fine.grid_shape[1] - 1) | (vj == fine.grid_shape[0] - 1)


@dataclass
class ReceiverPrep:
    """What receiver_points uses of the camera's buffers alone (no light, no receiver mask), computed once
    per camera pass by service.coarse_cache: the edge cells, the fine grid's border hits and 4-neighbours,
    cell_frusta's CellTable, tangent_reach of every coarse pixel that can be a mask edge pixel it extrapolates
    (a hit outside the edge cells; every hit without an edge pass) and of the fine hits where a directional
    light's receivers can end (fine_reach_candidates): tangent_reach is a function of each point alone, so the
    rows receiver_points picks are the bits it would compute."""

    edge_cells: np.ndarray
    coarse_row: np.ndarray  # (h w,) row of coarse_reach per flat pixel, -1 where none
    coarse_reach: np.ndarray  # (R, 4, 3)
    fine_border: np.ndarray | None = None
    cells: CellTable | None = None
    fine_neighbours: np.ndarray | None = None  # renderers.coarse.FinePoints.neighbours
    fine_row: np.ndarray | None = None  # (M,) row of fine_reach per fine hit (fine_reach_candidates), -1 where none
    fine_reach: np.ndarray | None = None  # (C, 4, 3) tangent_reach one fine step


def receiver_prep(camera, buffers: CoarseBuffers) -> ReceiverPrep:
    cells = edge_cells(buffers.hit, buffers.depth)
    fine = getattr(buffers, "fine", None)
    cand = buffers.hit & ~cells if fine is not None else buffers.hit
    rows, cols = np.nonzero(cand)
    row = np.full(buffers.height * buffers.width, -1, dtype=np.int32)
    row[rows * buffers.width + cols] = np.arange(len(rows))
    reach = tangent_reach(camera, buffers, cols + 0.5, rows + 0.5, buffers.position[rows, cols],
                          buffers.normal[rows, cols], EDGE_REACH).reshape(len(rows), 4, 3)
    if fine is None:
        return ReceiverPrep(cells, row, reach)
    nb = fine.neighbours().astype(np.int32)  # index arrays kept per camera: int32 (half the memory)
    cand = np.nonzero(fine_reach_candidates(fine, nb))[0]
    fine_row = np.full(len(fine.flat), -1, dtype=np.int32)
    fine_row[cand] = np.arange(len(cand))
    return ReceiverPrep(cells, row, reach, fine_border(fine), cell_table(buffers, fine), nb, fine_row,
                        _fine_reach(camera, buffers, fine, cand).reshape(len(cand), 4, 3))


def tangent_reach(camera, buffers: CoarseBuffers, u: np.ndarray, v: np.ndarray, p: np.ndarray, n: np.ndarray,
                  reach: float, factor: float = REACH_DEPTH_FACTOR) -> np.ndarray:
    """(4 E, 3): where the rays through the screen points (u +- reach, v +- reach) (coarse-pixel units,
    u right, v down) meet the tangent planes of the hits p (normals n), the distance along each ray kept
    within `factor` of the hit's distance (the hit's distance itself where the plane is
    parallel or behind). On a plane the full-resolution receivers within
    `reach` of the screen point lie in the hull of these four points.
    Per component: the operations, in their order, of the (E, 4, 3) form d = forward + x right + y up,
    d / |d|, s = n.(p - o) / n.d, o + s d (np.linalg.norm and np.sum over 3 components add left to right):
    the same bits, fewer passes over memory (tests/test_solve_latency_cache.py checks them)."""
    n = np.asarray(n, dtype=np.float64)
    o = camera.position
    q = [p[:, k] - o[k] for k in range(3)]
    dist = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    a = np.array([-reach, -reach, reach, reach])
    b = np.array([-reach, reach, -reach, reach])
    x = ((u[:, None] + a) * (2.0 / buffers.width) - 1.0) * tw  # (E, 4): Camera.ray_directions' convention
    y = (1.0 - (v[:, None] + b) * (2.0 / buffers.height)) * th
    fw, rt, up = camera.forward, camera.right, camera.up
    d = [fw[k] + x * rt[k] + y * up[k] for k in range(3)]
    norm = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    d = [c / norm for c in d]
    nk = [n[:, k, None] for k in range(3)]
    nd = nk[0] * d[0] + nk[1] * d[1] + nk[2] * d[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n[:, 0] * q[0] + n[:, 1] * q[1] + n[:, 2] * q[2])[:, None] / nd  # ray-plane distance
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, np.clip(s, dist[:, None] / factor, dist[:, None] * factor), dist[:, None])
    return np.stack([o[k] + s * d[k] for k in range(3)], axis=-1).reshape(-1, 3)


def _reach_slack(camera, reached: np.ndarray, source_depth: np.ndarray) -> np.ndarray:
    """Slack of tangent_reach's points: the view-depth change from their hit (the pixels between lie
    within it, so every cascade whose split meets that range fits the point)."""
    d = (reached - camera.position) @ camera.forward
    return np.abs(d - np.repeat(np.asarray(source_depth, dtype=np.float64), 4))


def depth_slack(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per pixel, the largest view-depth change to a 4-neighbour in `mask`: full-resolution pixels
    between coarse samples have depths within this of the sample's."""
    d = np.where(mask, depth, np.nan).astype(np.float64)
    p = np.pad(d, 1, constant_values=np.nan)
    with np.errstate(invalid="ignore"):
        out = np.abs(p[:-2, 1:-1] - d)
        for q in (p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]):
            np.fmax(out, np.abs(q - d), out=out)  # the largest of the differences that are not NaN
    return np.where(np.isfinite(out) & (out > 0), out, 0.0)


def light_problems(resolved: ResolvedRig, buffers: CoarseBuffers, bounds) -> list[LightProblem]:
    out = []
    fine = getattr(buffers, "fine", None)
    for li, (light, lb) in enumerate(zip(resolved.lights, buffers.lights)):
        samples = select_samples(resolved.camera, light, buffers.position, buffers.normal, buffers.hit,
                                 lb.facing, lb.boundary, lb.in_light)
        mask = buffers.hit & lb.facing & lb.in_light
        args = (resolved.camera, buffers, mask, bounds, fine.receiver[li] if fine is not None else None)
        memo = getattr(buffers, "receivers_memo", None)  # service.coarse_cache: per receiver mask, exact
        recv, slack = memo(receiver_points, *args) if memo is not None else receiver_points(*args)
        out.append(LightProblem(light, samples, recv, slack, sample_rows(samples, mask)))
    return out


def sample_rows(samples: Samples, mask: np.ndarray) -> np.ndarray:
    """Per sample, the index in receiver_points(mask) of the receiver at its pixel (the mask's
    pixels come first there, in row-major order)."""
    rank = np.cumsum(mask.ravel()) - 1
    return rank[samples.pixel[:, 0] * mask.shape[1] + samples.pixel[:, 1]]
