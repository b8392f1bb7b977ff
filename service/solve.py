"""Compute a shadow setup for a scene and rig, and express it as the solution schema.

scene (cached) -> rig -> coarse buffers -> per light: samples + receivers -> maps (a baseline now,
the optimizer later) -> predicted error (solvers.metric, the one metric) -> JSON in the requested
matrix convention, layout and frame.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..renderers.coarse import DEPTH_CONTINUITY, CoarseBuffers
from ..solvers.baselines import baseline
from ..solvers.conventions import convention_info, export_matrices, output_frame
from ..solvers.metric import error_stats, map_texels, per_sample_maps, sample_pixels, with_limit
from ..solvers.optimize import DEFAULT_METHOD as DEFAULT_SOLVER
from ..solvers.optimized_maps import optimized_maps
from ..solvers.samples import Samples, select_samples
from ..solvers.shadow_map import ShadowMap
from .pipeline import coarse_pass
from .echo import resolved_echo
from .request_cost import flush_if_large, solve_work
from . import point_faces
from .need import drop_empty_maps, light_need, no_shadow_reason, split_budget
from .rigs import ResolvedRig
from .scenes import SceneEntry
from .solution_check import SCHEMA_VERSION, validate_solution

BASELINE_METHODS = ("uniform", "focused", "lispsm", "logpsm")
METHODS = BASELINE_METHODS + ("optimized", "stable_csm", "path")  # stable_csm: solvers.stable_csm (Valient 2008); path: solvers.path_optimize (previous= the previous frame)


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
        from ..renderers.coarse import edge_cells

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
    from ..renderers.coarse import edge_cells

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
    from ..renderers.coarse import edge_cells

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


def maps_error(maps: list[ShadowMap], samples: Samples, origin) -> tuple[dict, list[dict]]:
    """predicted_error for the whole light and for each map (over the samples it serves)."""
    h, m, idx = per_sample_maps(maps, samples, origin)
    a = sample_pixels(samples)  # misclassified_pixels: solvers.metric.predicted_misclassified
    total = error_stats(h, m, samples.weight, a)
    total["unserved_samples"] = int(np.sum(idx < 0))
    with_limit(total, samples, map_texels(maps))  # limit, ratio_to_limit: solvers.metric.texel_limit
    if len(maps) == 1 and total["unserved_samples"] == 0:  # one map serving every sample: its stats are the light's
        return total, [{k: v for k, v in total.items() if k != "unserved_samples"}]
    per_map = [with_limit(error_stats(h[idx == k], m[idx == k], samples.weight[idx == k], a[idx == k]),
                          samples.subset(idx == k), map_texels([smap])) for k, smap in enumerate(maps)]
    return total, per_map


@lru_cache(maxsize=1)
def software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("shadowopt")
    except PackageNotFoundError:
        return "0+unknown"


def solution_json(entry: SceneEntry, resolved: ResolvedRig, method: str, per_light: list[dict],
                  timings: dict, settings: dict) -> dict:
    ver = software_version()
    convention = convention_info(resolved.output or {}, entry.loaded.stage_to_world)
    convention["world_frame"] = "right-handed, +Y up, meters; matrices act on column vectors"
    return {
        "schema_version": SCHEMA_VERSION,
        "method": method,
        "convention": convention,
        "lights": per_light,
        "resolved": resolved_echo(resolved),
        "timings_ms": {k: round(v, 3) for k, v in timings.items()},
        "provenance": {"scene_hash": entry.loaded.scene_hash, "software": f"shadowopt {ver}",
                       "settings": settings, "seed": settings.get("seed", 0)},
    }


# The lengths of a map's JSON an engine uses, expressed in the output's length unit (convention
# .length_unit: the engine preset's, else metres; with frame "stage" too, only the matrices take stage
# coordinates: solvers.conventions.output_frame). depth_bias (the idealized texel rule, keys in metres)
# and predicted_error (metres, its keys say so) stay in metres.
LENGTH_PAIRS = ("split", "light_depth", "blend_band")
DEPTH_LENGTHS = {"hardware": ("normal_offset",), "linear": ("normal_offset", "near", "far")}


def _in_units(x, metres_per_unit: float):
    return x / metres_per_unit if isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) else x


def scale_lengths(d: dict, metres_per_unit: float) -> dict | None:
    """Express the map JSON `d`'s lengths (LENGTH_PAIRS, warp.n, DEPTH_LENGTHS) in units of
    `metres_per_unit` metres, in place; returns the fields as they were (world metres) for `internal`,
    or None when the unit is the metre (nothing changes)."""
    if metres_per_unit == 1.0:
        return None
    import copy

    metres = {k: copy.deepcopy(d[k]) for k in (*LENGTH_PAIRS, "warp", "depth") if d.get(k) is not None}
    for k in LENGTH_PAIRS:
        if d.get(k) is not None:
            d[k] = [_in_units(x, metres_per_unit) for x in d[k]]
    if isinstance(d.get("warp"), dict) and d["warp"].get("n") is not None:
        d["warp"]["n"] = _in_units(d["warp"]["n"], metres_per_unit)
    for mode, keys in DEPTH_LENGTHS.items():
        block = (d.get("depth") or {}).get(mode)
        if isinstance(block, dict):
            for k in keys:
                if k in block:
                    block[k] = _in_units(block[k], metres_per_unit)
    return metres


def light_json(light, maps: list[ShadowMap], total: dict, per_map: list[dict], output: dict,
               stage_to_world: np.ndarray, samples: Samples) -> dict:
    _, metres_per_unit = output_frame(output, stage_to_world)
    cascades = []
    for smap, err in zip(maps, per_map):
        d = smap.to_json()
        d.update(export_matrices(smap.view, smap.projection, output.get("convention", "opengl"),
                                 output.get("layout", "column_major"), output.get("frame", "world"),
                                 stage_to_world, reversed_z=bool(output.get("reversed_z", False)),
                                 engine=output.get("engine")))
        d["predicted_error"] = err
        if getattr(smap, "snap_note", None):
            d["texel_snap_note"] = smap.snap_note
        lo_z, hi_z = smap.split
        if smap.face is None and len(maps) > 1 and smap is not maps[-1]:
            # Blend into the next cascade over the last 10% of this one's depth range (engines:
            # three.js CSM, Bevy's overlap 0.2); 0 for the last cascade and for single maps.
            d["blend_band"] = [float(hi_z - 0.1 * (hi_z - lo_z)), float(hi_z)]
        else:
            d["blend_band"] = None
        # Exact (world, column-vector, canonical OpenGL) matrices so `evaluate` reads back what was chosen,
        # and the lengths in world metres when the output's unit is another (maps_from_solution).
        d["internal"] = {"view": smap.view.tolist(), "projection": smap.projection.tolist()}
        metres = scale_lengths(d, metres_per_unit)
        if metres is not None:
            d["internal"]["metres"] = metres
        cascades.append(d)
    return {"type": light.kind, "usd_path": light.usd_path, "samples_kind": samples.kind,
            "cascades": cascades, "predicted_error": total}


def solve(entry: SceneEntry, rig: dict, method: str = "focused", solver: str | None = None,
          time_budget_ms: float | None = None, previous: dict | None = None, hysteresis: float = 0.8,
          **options) -> dict:
    """The solution for `method` (a baseline name or "optimized"; "path": coherent with `previous`, the previous
    frame's solution, solvers.path_optimize) on a scene entry and validated rig dict.

    `time_budget_ms` bounds the optimizer's search (method optimized) over the whole solve: it is counted from
    the start of the solve (the coarse pass included) and shared by all lights and cascades, each search
    getting what is left (at least 1 ms); when it runs out, each remaining light's search returns its start
    maps. The coarse pass, the baselines' fits and the error statistics are not interruptible; their cost is
    bounded by the rig's work limit (service.request_cost). After a large request, Dr.Jit's cached
    allocations are returned to the system."""
    try:
        return _solve(entry, rig, method, solver, time_budget_ms, previous, hysteresis, **options)
    finally:
        flush_if_large(solve_work(rig))


def _solve(entry: SceneEntry, rig: dict, method: str, solver: str | None, time_budget_ms: float | None,
           previous: dict | None, hysteresis: float, **options) -> dict:
    if method not in METHODS:
        raise ValueError(f"method: unknown method {method!r} (known: {', '.join(METHODS)})")
    if previous is not None:  # only its solver's x is read; a malformed field is a SolutionError naming it
        previous = validate_solution(previous, "previous", n_lights=len(rig["lights"]), maps=False,
                                     code="invalid_previous")
    t0, c0 = time.perf_counter(), time.thread_time()

    def budget_left():  # the search time left of the whole solve's budget
        if time_budget_ms is None:
            return None
        return max(1.0, float(time_budget_ms) - (time.perf_counter() - t0) * 1e3)

    if options.get("cache_tenant") is not None:  # the camera part cached per tenant and scene (service.coarse_cache)
        from .coarse_cache import cached_coarse_pass

        resolved, buffers = cached_coarse_pass(entry, rig, options["cache_tenant"])
    else:
        resolved, buffers = coarse_pass(entry, rig)
    t1 = time.perf_counter()
    shadow = resolved.shadow
    lo, hi = entry.loaded.geometry.bounds()
    per_light = []
    solvers_json = []
    probs = light_problems(resolved, buffers, (lo, hi))
    t_receivers = time.perf_counter()
    split = rig_budget_split(resolved, buffers, probs, (lo, hi)) if shadow.get("budget_scope") == "rig" else None
    for li, prob in enumerate(probs):
        need = light_need(buffers, li)
        if not need.needs_map:  # no visible receiver: no map, nothing beyond the coarse pass (service.need)
            per_light.append(no_map_json(prob, need, (buffers.width, buffers.height)))
            if method in ("optimized", "path"):
                solvers_json.append(None)
            continue
        common = dict(resolution=tuple(shadow.get("resolution") or (2048, 2048)),
                      cascades=shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else 1,
                      splits=shadow.get("splits", "practical"),
                      split_lambda=shadow.get("lambda", 0.5), texel_budget=shadow.get("texel_budget"),
                      receiver_slack=prob.receiver_slack)
        if split is not None:  # budget_scope rig: this light's share of the rig's texels
            common["texel_budget"] = max(1, split["lights"][li]["texels"])
        allow_log = bool(resolved.output.get("allow_log_warp", False))

        def maps_for(k: int):
            opts = {**common, "cascades": k}
            if method == "optimized":
                return optimized_maps(resolved.camera, prob.light, prob.samples, prob.receivers, (lo, hi),
                                      allow_log=allow_log, solver=solver or DEFAULT_SOLVER,
                                      time_budget_ms=budget_left(), previous_x=_previous_x(previous, li),
                                      hysteresis=hysteresis, sample_rows=prob.sample_rows, **opts)
            if method == "path":  # coherent with the previous frame: a held world-fixed texel grid per cascade
                from ..solvers.path_optimize import path_maps, previous_state

                return path_maps(resolved.camera, prob.light, prob.samples, prob.receivers, (lo, hi),
                                 previous_state=previous_state(previous, li), solver=solver or DEFAULT_SOLVER,
                                 time_budget_ms=budget_left(), sample_rows=prob.sample_rows, **opts)
            if opts["splits"] == "optimized":  # a baseline method with optimized splits: the search's splits
                opts["splits"] = "practical"
                if opts["cascades"] > 1 and prob.light.kind == "directional":
                    from ..solvers.split_search import optimize_splits

                    opts["split_at"] = optimize_splits(
                        resolved.camera, prob.light, prob.samples, prob.receivers, (lo, hi), opts["resolution"],
                        opts["cascades"], texel_budget=opts["texel_budget"], receiver_slack=prob.receiver_slack,
                        method=method if method in ("focused", "lispsm") else "lispsm").split_at
            if method == "stable_csm":  # the engines' bounding sphere per cascade, texel-snapped
                from ..solvers.stable_csm import stable_csm_maps

                return stable_csm_maps(resolved.camera, prob.light, prob.receivers, (lo, hi), **opts), None
            return baseline(method, resolved.camera, prob.light, prob.receivers, (lo, hi),
                            allow_log=allow_log or method == "logpsm", **opts), None

        if shadow.get("cascades") == "auto":
            maps, info, auto = auto_cascades(maps_for, prob, resolved.camera.position, shadow, resolved.camera,
                                             drop=method != "path")
            if method == "path":  # the previous frame's cascade count, with hysteresis
                from ..solvers.path_optimize import held_cascade_count, previous_state

                maps, info, auto = held_cascade_count(maps_for, maps, info, auto, previous_state(previous, li), shadow)
        else:
            (maps, info), auto = maps_for(common["cascades"]), None
        notes = list(auto.pop("notes", [])) if auto is not None else []
        fp_block = None
        if method != "path":  # path: each cascade holds its world-fixed grid from frame to frame, none is dropped
            maps, dropped = drop_empty_maps(maps, prob.receivers, prob.receiver_slack, resolved.camera)
            notes += dropped
            # A point light: Lloyd et al. 2007 face partitioning against the cube, by objective (service.point_faces)
            maps, fp_block = point_faces.choose(method, resolved.camera, prob, (lo, hi), maps, allow_log, maps_error,
                                                resolved.camera.position, shadow.get("point_light_maps", "auto"))
            if shadow.get("target_p95_m") is not None and not shadow.get("fixed_resolution"):
                maps, note = smaller_resolution(maps, prob, resolved.camera.position, float(shadow["target_p95_m"]))
                if note:
                    notes.append(note)
        if shadow.get("snap_to_texels"):
            snap_maps(maps, prob)
        if info is not None:
            if auto is not None:
                info["auto_cascades"] = auto
            solvers_json.append(info)
        total, per_map = maps_error(maps, prob.samples, resolved.camera.position)
        per_light.append(light_json(prob.light, maps, total, per_map, resolved.output,
                                    entry.loaded.stage_to_world, prob.samples))
        per_light[-1]["shadow"] = "map"
        per_light[-1]["need"] = need.to_json()
        if fp_block is not None:
            per_light[-1]["face_partitioning"] = fp_block
        if notes:
            per_light[-1]["notes"] = notes
        if auto is not None:
            per_light[-1]["auto_cascades"] = auto
    t2 = time.perf_counter()
    # receivers: of optimize, the lights' samples and receivers (light_problems); total_cpu: this thread's CPU
    timings = {"coarse": (t1 - t0) * 1e3, "optimize": (t2 - t1) * 1e3, "receivers": (t_receivers - t1) * 1e3,
               "total": (t2 - t0) * 1e3, "total_cpu": (time.thread_time() - c0) * 1e3}
    settings = {"method": method, "solver": solver or (DEFAULT_SOLVER if method in ("optimized", "path") else None),
                "time_budget_ms": time_budget_ms, "coarse_long_side": resolved.coarse_long_side,
                "shadow": _jsonable(shadow)}
    sol = solution_json(entry, resolved, method, per_light, timings, settings)
    if split is not None:
        for li, light in enumerate(per_light):
            split["lights"][li]["returned_texels"] = sum(c["resolution"][0] * c["resolution"][1]
                                                         for c in light["cascades"])
        split["returned_texels"] = sum(l["returned_texels"] for l in split["lights"])
        sol["texel_budget_split"] = split
    if method in ("optimized", "path") and any(s is not None for s in solvers_json):
        sol["solver"] = solvers_json[0] if len(solvers_json) == 1 else {"lights": solvers_json}
    return sol


def rig_budget_split(resolved: ResolvedRig, buffers: CoarseBuffers, probs: list[LightProblem], bounds) -> dict:
    """`budget_scope: "rig"`: the rig's texel_budget split across its lights by need (service.need.split_budget).
    Each light with visible receivers is probed with the focused baseline at an equal share (its cascade count,
    1 for auto); its predicted misclassified pixels there set its need. A light with none gets 0 texels."""
    shadow = resolved.shadow
    budget = int(shadow["texel_budget"])
    needs = [light_need(buffers, li) for li in range(len(probs))]
    n = sum(1 for nd in needs if nd.needs_map)
    probe = budget // max(n, 1)
    k = shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else 1
    mis = []
    for prob, nd in zip(probs, needs):
        if not nd.needs_map:
            mis.append(None)
            continue
        maps = baseline("focused", resolved.camera, prob.light, prob.receivers, bounds, cascades=k,
                        splits=shadow.get("splits", "practical") if shadow.get("splits") != "optimized" else "practical",
                        split_lambda=shadow.get("lambda", 0.5), texel_budget=probe, receiver_slack=prob.receiver_slack)
        mis.append(float(maps_error(maps, prob.samples, resolved.camera.position)[0]["misclassified_pixels"]))
    texels = split_budget(budget, mis, probe)
    return {"scope": "rig", "budget": budget, "probe_texels": probe,
            "rule": ("T_i = budget d_i^(2/3) / sum d_j^(2/3), d_i = predicted misclassified pixels at an equal share x "
                     "sqrt(share) (Chong 2003's Lagrange allocation, generalized to lights); 0 for a light with no "
                     "visible receiver"),
            "lights": [{"texels": t, "predicted_misclassified_at_probe": m} for t, m in zip(texels, mis)]}


def no_map_json(prob: LightProblem, need, size: tuple[int, int]) -> dict:
    """The solution entry of a light that gets no map (service.need): `shadow` "none", the reason, no
    cascades; its predicted error is that of no samples, 0 texels."""
    total = error_stats(np.zeros(0), np.zeros(0), pixels=np.zeros(0))
    total.update(unserved_samples=int(len(prob.samples)), limit=None, ratio_to_limit=None, texels=0)
    return {"type": prob.light.kind, "usd_path": prob.light.usd_path, "samples_kind": prob.samples.kind,
            "shadow": "none", "reason": no_shadow_reason(prob.light, need, size), "need": need.to_json(),
            "cascades": [], "predicted_error": total}


def _path_options(shadow: dict, prob: LightProblem, solver: str | None) -> dict:
    """optimized_maps' keywords for one light of a path frame (FrameProblem.opts)."""
    return dict(resolution=tuple(shadow.get("resolution") or (2048, 2048)),
                cascades=shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else 1,
                splits=shadow.get("splits", "practical"), split_lambda=shadow.get("lambda", 0.5),
                texel_budget=shadow.get("texel_budget"), receiver_slack=prob.receiver_slack,
                sample_rows=prob.sample_rows, solver=solver or DEFAULT_SOLVER)


def frame_problems(entry: SceneEntry, rigs: list[dict], light_index: int = 0, solver: str | None = None):
    """solvers.path_optimize.FrameProblems of validated rigs (one light): each frame's coarse pass and light
    problem, as solve() makes them."""
    return [fp for fp, _, _ in _path_frames(entry, rigs, solver, light_index)]


def _path_frames(entry: SceneEntry, rigs: list[dict], solver: str | None, light_index: int | None = None):
    from ..solvers.path_optimize import FrameProblem

    lo, hi = entry.loaded.geometry.bounds()
    out = []
    for rig in rigs:
        t0 = time.perf_counter()
        resolved, buffers = coarse_pass(entry, rig)
        probs = light_problems(resolved, buffers, (lo, hi))
        fps = [FrameProblem(resolved.camera, p.light, p.samples, p.receivers, (lo, hi),
                            _path_options(resolved.shadow, p, solver)) for p in probs]
        out.append((fps[light_index] if light_index is not None else fps, resolved,
                    (time.perf_counter() - t0) * 1e3))
    return out


def whole_path_eligible(resolved: ResolvedRig) -> bool:
    """A frame the whole-path pass can solve with the others (solvers.path_optimize.optimize_path): every
    light directional and a fixed cascade count (not "auto"); other paths run frame after frame (previous=)."""
    return bool(resolved.lights) and all(l.kind == "directional" for l in resolved.lights) \
        and isinstance(resolved.shadow.get("cascades", 1), int)


def solve_path(entry: SceneEntry, rigs: list[dict], solver: str | None = None,
               keyframes_every: int | None = None) -> list[dict]:
    """Method "path" over a path known ahead (a path job, a batch precomputation): the solutions of the frames
    of `rigs` (validated rig dicts, in order), each in the optimize schema. Every directional light's maps come
    from solvers.path_optimize.optimize_path over all frames (segments holding one world-fixed grid, scale
    level, depth and bias: no texel changes inside a segment); the frame's solver report says which pass was
    returned and its segment per cascade. timings_ms: the frame's own coarse pass; optimize is the whole-path
    pass's time divided by the frame count. Paths that are not whole_path_eligible (a spot or point light,
    cascades "auto") are solved frame after frame with previous= (the interactive form).
    `keyframes_every` K: for engines that interpolate, every frame's report also says whether it is a keyframe
    (frames 0, K, 2K, ... and the last), the interpolation rule, and what interpolating the keyframes' matrices
    adds on these frames (solvers.path_optimize.keyframes: the objective of the interpolated maps at each skipped
    frame, the worst ratio to the chosen maps' and the receivers left outside)."""
    from ..solvers.path_optimize import keyframes, optimize_path

    if not rigs:
        return []
    frames = _path_frames(entry, rigs, solver)
    if not all(whole_path_eligible(f[1]) for f in frames) or len({len(f[0]) for f in frames}) != 1:
        out, prev = [], None
        for rig in rigs:
            prev = solve(entry, rig, "path", solver=solver, previous=prev)
            out.append(prev)
        return out
    n, n_lights = len(frames), len(frames[0][0])
    t0 = time.perf_counter()
    results = [optimize_path([f[0][li] for f in frames]) for li in range(n_lights)]
    kfs = [keyframes(res, [f[0][li] for f in frames], keyframes_every) if keyframes_every else None
           for li, res in enumerate(results)]
    per_frame_ms = (time.perf_counter() - t0) * 1e3 / n
    out = []
    for i, (fps, resolved, coarse_ms) in enumerate(frames):
        per_light, infos = [], []
        for li, (fp, res) in enumerate(zip(fps, results)):
            maps = res.maps[i]
            total, per_map = maps_error(maps, fp.samples, fp.camera.position)
            per_light.append(light_json(fp.light, maps, total, per_map, resolved.output,
                                        entry.loaded.stage_to_world, fp.samples))
            returned = res.passes["returned"]
            segs = [next([a, b] for a, b in c["segments"] if a <= i <= b)
                    for c in res.passes.get("segments", {}).get("cascades", [])] if returned == "segments" else None
            infos.append({"fun": float(res.objective[i]), "per_frame_objective": float(res.per_frame_objective[i]),
                          "path": {"mode": "whole path", "pass": returned, "segments": segs,
                                   "grid_changes": res.grid_changes, "level_changes": res.level_changes,
                                   "frames": n}})
            if kfs[li] is not None:
                kf = kfs[li]
                skipped = {d["frame"]: d for d in kf["skipped"]}
                infos[-1]["path"]["keyframes"] = {
                    "every": kf["every"], "is_keyframe": i in kf["frames"], "rule": kf["rule"],
                    "max_objective_ratio": kf["max_objective_ratio"], "max_objective_added": kf["max_objective_added"],
                    "max_outside_receivers": kf["max_outside_receivers"],
                    "interpolated_objective": skipped[i]["objective"] if i in skipped else None,
                    "interpolated_outside_receivers": skipped[i]["outside_receivers"] if i in skipped else None}
        timings = {"coarse": coarse_ms, "optimize": per_frame_ms, "total": coarse_ms + per_frame_ms}
        settings = {"method": "path", "solver": solver or DEFAULT_SOLVER, "time_budget_ms": None,
                    "coarse_long_side": resolved.coarse_long_side, "shadow": _jsonable(resolved.shadow),
                    "whole_path": True}
        sol = solution_json(entry, resolved, "path", per_light, timings, settings)
        sol["solver"] = infos[0] if len(infos) == 1 else {"lights": infos}
        out.append(sol)
    return out


def snap_maps(maps: list[ShadowMap], prob: LightProblem) -> None:
    """`shadow.snap_to_texels`: unwarped directional maps get a world-fixed texel grid
    (solvers.fitting.snap_to_texels); warped and perspective maps are left as they are, each with the
    reason in `snap_note` (the solution's `texel_snap_note`), so a request for snapping is never
    ignored silently."""
    from ..solvers.depth_modes import with_bias
    from ..solvers.fitting import snap_to_texels

    for smap in maps:
        note = _snap_refusal(smap, prob.light)
        P = None if note else snap_to_texels(smap.view, smap.projection, smap.resolution)
        if P is None:
            smap.snap_note = note or ("not snapped: the map is perspective-warped (its texels move with the "
                                      "camera's view of the receivers; only unwarped directional maps have a "
                                      "world-fixed texel grid)")
            continue
        smap.projection = P
        smap.snapped = True
        if len(prob.receivers):
            with_bias(smap, prob.receivers, prob.light)


def _snap_refusal(smap: ShadowMap, light) -> str | None:
    """Why a map cannot get a world-fixed texel grid, or None when snap_to_texels may try."""
    if light.kind != "directional":
        return "not snapped: a spot or point light's perspective map has no world-fixed texel grid"
    if smap.face is not None:
        return "not snapped: a cube-map face has no world-fixed texel grid"
    if smap.log_warp is not None:
        return "not snapped: the map is log-warped (its texels move with the camera)"
    return None


def _previous_x(previous: dict | None, light_index: int):
    """The projective parameters per cascade of a previous `optimized` solution for one light."""
    if not previous or previous.get("solver") is None:  # previous: validate_solution's normalized copy
        return None
    s = previous["solver"]
    s = s["lights"][light_index] if "lights" in s else (s if light_index == 0 else None)
    if not s:
        return None
    return [x if x else None for x in s.get("x", [])]


AUTO_TOLERANCE = 0.05  # cascades "auto": the fewest cascades whose objective x texels is within 5% of the least
# p95_m scales as texels^P95_TEXEL_EXPONENT: m is a texel's footprint in screen pixels, a texel's side is the map's
# extent over its resolution per side (the fit does not depend on it), so m ~ 1/side ~ texels^-1/2 at a fixed
# aspect (Stamminger & Drettakis 2002's texel-to-pixel ratio; checked against two resolutions in tests/test_need.py)
P95_TEXEL_EXPONENT = -0.5
ENGINE_SIZE_STEP = 64  # a smaller resolution is rounded up to a multiple of 64 texels per side


MAX_TEXEL_ESTIMATE = 2.0 ** 53  # beyond this an estimated budget is no budget (a target far below any reachable p95_m)


def texels_for_p95(p95_m: float, texels: int, target: float) -> int | None:
    """The texels at which p95_m (measured with `texels`) would meet `target` (P95_TEXEL_EXPONENT), or None when
    that is not a finite number below MAX_TEXEL_ESTIMATE."""
    try:
        v = texels * (p95_m / target) ** (1.0 / -P95_TEXEL_EXPONENT)
    except (OverflowError, ZeroDivisionError):
        return None
    return int(math.ceil(v)) if math.isfinite(v) and 0 <= v <= MAX_TEXEL_ESTIMATE else None


def auto_cascades(maps_for, prob: LightProblem, origin, shadow: dict, camera=None, drop: bool = True):
    """`cascades: "auto"`: with target_p95_m, the smallest k up to max_cascades whose predicted p95_m meets it;
    otherwise (or when none does) the fewest cascades whose objective x texels (the objective alone under a
    texel budget: every k gets the same texels) is within AUTO_TOLERANCE of the least: fewer draw calls for
    the engine. Cascades with no receivers are dropped (service.need) before k is scored (`drop`, with the
    camera), so a k that returns fewer maps counts as that many. When no k meets the target, says what texel
    budget would (texels_for_p95 from the k with the least p95_m)."""
    target = shadow.get("target_p95_m")
    kmax = int(shadow.get("max_cascades") or 4)
    tried, cands = [], []
    for k in range(1, kmax + 1):
        maps, info = maps_for(k)
        notes = []
        if drop and camera is not None:
            maps, notes = drop_empty_maps(maps, prob.receivers, prob.receiver_slack, camera)
        err, _ = maps_error(maps, prob.samples, origin)
        texels = sum(m.resolution[0] * m.resolution[1] for m in maps)
        tried.append({"cascades": k, "returned": len(maps), "p95_m": err["p95_m"], "objective": err["objective"],
                      "texels": texels})
        if target is not None and err["p95_m"] <= target:
            return maps, info, {"chosen": k, "returned": len(maps), "rule": f"smallest k with p95_m <= {target}",
                                "tried": tried, "notes": notes}
        cands.append((err["objective"] * texels, len(maps), k, maps, info, notes))
    best = min(c[0] for c in cands)
    ok = [c for c in cands if c[0] <= best * (1.0 + AUTO_TOLERANCE)]
    _, n, k, maps, info, notes = min(ok, key=lambda c: (c[1], c[2]))
    rule = f"fewest cascades with objective x texels within {AUTO_TOLERANCE:.0%} of the least"
    out = {"chosen": k, "returned": n, "rule": rule if target is None else f"no k met p95_m <= {target}: {rule}",
           "tolerance": AUTO_TOLERANCE, "tried": tried, "notes": notes}
    if target is not None:
        t = min(tried, key=lambda t: t["p95_m"])
        need = texels_for_p95(t["p95_m"], t["texels"], target)
        out["needed_texel_budget"] = need
        reach = f"about {need:,} texels would" if need is not None else \
            f"no texel budget up to {MAX_TEXEL_ESTIMATE:.3g} would"
        out["budget_estimate"] = (f"{reach} meet p95_m <= {target:g} (now {t['texels']:,}): "
                                  f"k = {t['cascades']} has p95_m {t['p95_m']:.3g}, and p95_m scales as "
                                  f"texels^{P95_TEXEL_EXPONENT:g}")
    return maps, info, out


def smaller_resolution(maps: list[ShadowMap], prob: LightProblem, origin, target: float):
    """Maps that meet p95_m <= `target` with fewer texels than given: every map's sides scaled by
    p95_m / target (P95_TEXEL_EXPONENT), rounded up to a multiple of ENGINE_SIZE_STEP (never above the given
    size), the depth bias refitted to the new texels; the scale is raised until the target is met again.
    Returns (maps, note) with the maps changed in place, or (maps, None) when nothing smaller meets it."""
    from ..solvers.depth_modes import with_bias

    err, _ = maps_error(maps, prob.samples, origin)
    p95, before = err["p95_m"], map_texels(maps)
    if not (err["samples"] and 0 < p95 <= target):
        return maps, None
    given = [tuple(m.resolution) for m in maps]
    s = p95 / target
    while s < 1.0:
        sizes = [tuple(min(g, max(ENGINE_SIZE_STEP, ENGINE_SIZE_STEP * math.ceil(g * s / ENGINE_SIZE_STEP)))
                       for g in res) for res in given]
        if sizes == given:
            break
        for m, r in zip(maps, sizes):
            m.resolution = r
            with_bias(m, prob.receivers, prob.light)
        e2, _ = maps_error(maps, prob.samples, origin)
        if e2["p95_m"] <= target:
            after = map_texels(maps)
            return maps, (f"resolution lowered to {', '.join(f'{a}x{b}' for a, b in sizes)} (multiples of "
                          f"{ENGINE_SIZE_STEP}) from {', '.join(f'{a}x{b}' for a, b in given)}: p95_m {e2['p95_m']:.3g} "
                          f"still meets {target:g}; {before - after:,} of {before:,} texels saved "
                          f"({(before - after) / before:.0%}); shadow.fixed_resolution keeps the given size")
        s *= 1.15
    for m, r in zip(maps, given):  # nothing smaller met the target: the given sizes
        m.resolution = r
        with_bias(m, prob.receivers, prob.light)
    return maps, None


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    return d


def maps_from_solution(solution: dict) -> list[list[ShadowMap]]:
    """Per light, the maps of a solution JSON in the world frame and metres, whatever its output
    convention, frame or engine preset: the exact internal matrices and, when the solution's lengths
    are in another unit, the internal copy of them in metres."""
    out = []
    for light in solution["lights"]:
        maps = []
        for c in light["cascades"]:
            d = dict(c)
            d.update(c["internal"].get("metres") or {})
            if d.get("split") is not None and d["split"][1] is None:  # an unbounded split's hi (JSON null)
                d["split"] = [d["split"][0], float("inf")]
            d["view_matrix"] = c["internal"]["view"]
            d["projection_matrix"] = c["internal"]["projection"]
            maps.append(ShadowMap.from_json(d))
        out.append(maps)
    return out
