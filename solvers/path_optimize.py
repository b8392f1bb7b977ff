"""`method: path`: shadow maps that stay still while the camera moves (interactive: the previous frame
only; batch: a whole path cut into segments that hold their texel grid, with keyframes for engines that
interpolate).

Why texels swim. A directional map is a 2D projective map of the light plane, s = (g0 . p) / (g2 . p),
t = (g1 . p) / (g2 . p) (Chong & Gortler 2007: rows 1, 2 and 4 of P annihilate the light direction). The
per-frame optimizer (solvers.optimized_maps) refits all of it to each frame's receivers, so every
receiver's texel coordinates move by a fraction of a texel per frame: the shadow edges shimmer.

The world-fixed grid. Split the map into a *canonical* projective part G (the three rows g0, g1, g2
expressed in a light view anchored at a fixed world point: it carries the warp's centre and strength, the
warp axis and the skew of the affine fit) and an axis-aligned affine part per frame: s_ndc = a_s X + b_s,
X = (g0 . p) / (g2 . p) (likewise t). While G is held, the canonical coordinates (X, Y) of a world point do
not change, so the texel grid is fixed in the world when a is held on a ladder of levels and b is snapped
so that X = 0 falls on a texel corner (the engines' texel snapping, Valient 2008, done in the warped space
instead of light space; solvers.fitting.snap_to_texels is its unwarped case). Per frame only the box
moves, by whole texels: swim 0 for every point served by the same cascade (the grid: solvers.texel_grid).

Per frame (interactive, `path_maps`), per cascade:
- fresh: the per-frame optimized map (optimized_maps, warm-started from the previous frame's x), refit on
  its own canonical part and snapped;
- held: the previous frame's canonical part and scale levels, refit to this frame's receivers;
- the held grid is kept unless the fresh one's objective is below `hysteresis` x the held one's (or the
  held grid no longer contains the receivers in front of its warp centre); when it changes, it moves
  toward the fresh one by the smallest step of BLEND_STEPS whose objective is within BLEND_SLACK of the
  fresh one's (a limited per-frame change of the warp: the smaller the step, the fewer texels pop).
- scale levels: the ladder 2^(j / LADDER_STEPS) of NDC scales; the held level is kept while it still
  covers the receivers and wastes at most LEVEL_SLACK steps.
Coverage: the box is padded by PAD_TEXELS texels plus half a texel per side for the snap, and the level
rounds the scale down (the map grows), so every fit point (receivers' light-plane hull and the samples)
stays inside the map.

Whole paths (`optimize_path`, segment_pass): the path cut into segments, each holding one canonical part,
one scale level (the finest that holds every frame of the segment), one depth (stored from the segment's
first camera over the union of its frames' ranges) and one bias (the greatest its frames need): inside a
segment a frame's map differs from the previous one's only by a whole-texel move of its box, so no receiver
changes texel, stored depth or bias, and nothing flickers; the grid changes only at a segment's first frame.
The cut: the fewest segments whose summed objective is within SEGMENT_TOLERANCE of the per-frame optimizer's
(dynamic programming over segment counts; each segment's candidates are its frames' fresh canonical parts and
its joint optimum over all its frames' samples). `keyframes`: every K-th
frame's maps, the rule (linear interpolation of the world-to-clip matrix entries, each keyframe's matrix
scaled so its w row has unit norm) and the error interpolation adds at the skipped frames (objective ratio
and receivers left outside), measured.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .cascade_scores import receiver_h
from .depth_modes import with_bias
from .fitting import box_corners, light_plane_hull
from .lights import DirectionalLight
from .metric import predicted_objective
from .optimized_maps import optimized_maps
from .samples import Samples
from .shadow_map import ShadowMap, serving_maps
from .texel_grid import LADDER_STEPS, Grid, blend, fit_on_grid, grid_of, tight_levels

HYSTERESIS = 0.85  # the held grid is replaced when the fresh one's objective is below this x the held one's
BLEND_STEPS = (0.25, 0.5)  # fractions of the way from the held canonical part to the fresh one, tried in order
BLEND_SLACK = 1.05  # a partial step is taken when its objective is within this factor of the fresh one's
SEGMENT_TOLERANCE = 1.3  # segment_pass: the fewest segments whose summed objective is within this x the per-frame one's
SEGMENT_MAX_FRAMES = 48  # frames per segment at most (a long path: the search stays linear in its length)
SEGMENT_CANDIDATES = 5  # canonical parts tried per segment: its frames' fresh ones, evenly spaced


# ------------------------------------------------------------------ one frame (interactive)
def _cascade_selection(camera, receivers, slack, samples: Samples, maps):
    """Per cascade: (sample mask, receiver mask) as optimized_maps selects them (the split and, for the
    receivers, their view-depth slack; the first and last cascades unbounded)."""
    depth = (receivers - camera.position) @ camera.forward if len(receivers) else np.zeros(0)
    out = []
    for k, m in enumerate(maps):
        lo, hi = m.split
        sel_s = (samples.view_depth >= lo) & (samples.view_depth <= hi)
        sel_r = np.ones(len(receivers), bool)
        if len(maps) > 1 and len(receivers):
            sel_r = (depth + slack >= (lo if k else -np.inf)) & (depth - slack <= (hi if k < len(maps) - 1 else np.inf))
        out.append((sel_s, sel_r))
    return out


@dataclass
class CascadeFit:
    """What a cascade's choice needs: its samples, receivers, fit points and the scene corners."""

    sub: Samples
    part: np.ndarray
    fit_pts: np.ndarray
    corners: np.ndarray

    def score(self, smap: ShadowMap, camera, light) -> float:
        if smap is None:
            return math.inf
        if len(self.sub):
            return float(predicted_objective([smap], self.sub, camera.position))
        return float(receiver_h(smap, self.part, camera, light))


def cascade_fits(camera, light, samples: Samples, receivers: np.ndarray, casters_bounds, maps, receiver_slack=None):
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    receivers = receivers[np.all(np.isfinite(receivers), axis=1)] if len(receivers) else receivers
    slack = np.zeros(len(receivers)) if receiver_slack is None or len(receiver_slack) != len(receivers) \
        else np.asarray(receiver_slack, float)
    corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
    out = []
    for sel_s, sel_r in _cascade_selection(camera, receivers, slack, samples, maps):
        sub = samples if sel_s.all() else samples.subset(sel_s)
        part = receivers[sel_r] if sel_r.any() else receivers
        pts = np.vstack([part, sub.position]) if len(sub) else part
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        hull, ext = light_plane_hull(light.direction, pts)
        out.append(CascadeFit(sub, part, np.vstack([hull, ext]) if len(ext) else hull, corners))
    return out


def choose_grid(cf: CascadeFit, camera, light, fresh: Grid | None, held: Grid | None, hysteresis: float = HYSTERESIS):
    """(map, grid, decision) for one cascade: the held grid refit unless the fresh one is better by the
    hysteresis factor, then the smallest limited step toward it within BLEND_SLACK of the fresh objective."""
    cand_f = fit_on_grid(fresh, cf.fit_pts, cf.corners, None, camera.position) if fresh is not None else None
    f_f = cf.score(cand_f[0], camera, light) if cand_f else math.inf
    if held is not None and fresh is not None and held.resolution != fresh.resolution:
        held = Grid(held.view, held.G, fresh.resolution, None, held.x)  # a new allocation: the level follows
    cand_h = fit_on_grid(held, cf.fit_pts, cf.corners, held.levels, camera.position) if held is not None else None
    f_h = cf.score(cand_h[0], camera, light) if cand_h else math.inf
    decision = {"objective_fresh": f_f, "objective_held": f_h if held is not None else None}
    if cand_h is not None and math.isfinite(f_h) and not (f_f < hysteresis * f_h):
        grid = Grid(held.view, held.G, held.resolution, cand_h[1], fresh.x if fresh is not None else held.x)
        decision.update(kept="held", objective=f_h)
        return cand_h[0], grid, decision
    if cand_f is None:  # nothing to fit (no receiver, no sample) or a map outside this family: the per-frame map
        decision.update(kept="per-frame", objective=None)
        return None, None, decision
    if cand_h is not None and fresh is not None:
        for alpha in BLEND_STEPS:
            g = blend(held, fresh, alpha)
            c = fit_on_grid(g, cf.fit_pts, cf.corners, g.levels, camera.position)
            f = cf.score(c[0], camera, light) if c else math.inf
            if f <= BLEND_SLACK * f_f and f < hysteresis * f_h:
                g.levels = c[1]
                decision.update(kept="step", step=alpha, objective=f)
                return c[0], g, decision
    grid = Grid(fresh.view, fresh.G, fresh.resolution, cand_f[1], fresh.x)
    decision.update(kept="fresh", objective=f_f)
    return cand_f[0], grid, decision


def previous_grids(state) -> list[Grid | None] | None:
    """The held grids of a previous frame's path state (solution["solver"]["path"]), None when absent."""
    if not isinstance(state, dict) or not isinstance(state.get("cascades"), list):
        return None
    return [Grid.from_json(c) if isinstance(c, dict) else None for c in state["cascades"]]


def path_maps(camera, light, samples: Samples, receivers: np.ndarray, casters_bounds, previous_state=None,
              hysteresis: float | None = None, per_frame_out: list | None = None, **opts):
    """`method: path` for one light: the per-frame optimized maps (optimized_maps with `opts`, warm-started
    from the previous frame's x), each directional cascade replaced by its coherent choice on a world-fixed
    snapped grid (choose_grid). Returns (maps, solver_json) with solver_json["path"] = {"cascades": [the held
    grid per cascade and the decision]} for the next frame. A light with no light-plane projective map (spot,
    point) gets the per-frame optimized maps with the optimizer's own hysteresis (previous_x)."""
    t0 = time.perf_counter()
    hysteresis = HYSTERESIS if hysteresis is None else float(hysteresis)
    held = previous_grids(previous_state)
    opts = {**opts, "allow_log": False}  # a log warp is not a light-plane projective map: no world-fixed grid
    if held is not None and all(g is not None and g.x is not None for g in held):
        opts.setdefault("x0", [g.x for g in held])
    maps, sj = optimized_maps(camera, light, samples, receivers, casters_bounds, **opts)
    if per_frame_out is not None:  # optimize_path's reference: the per-frame optimizer's own maps
        per_frame_out.append(maps)
    if not isinstance(light, DirectionalLight) or maps[0].face is not None:
        sj["path"] = {"cascades": [], "note": "per-frame optimized: only directional maps have a world-fixed grid"}
        return maps, sj
    if held is not None and len(held) != len(maps):
        held = None  # another cascade count: start fresh
    if held is not None:  # a grid projects along the light it was made for (a moving sun: a new grid)
        d = np.asarray(light.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        held = [g if g is not None and np.allclose(-g.view[2, :3] / max(np.linalg.norm(g.view[2, :3]), 1e-300), d,
                                                   rtol=0, atol=1e-9) else None for g in held]
    fits = cascade_fits(camera, light, samples, receivers, casters_bounds, maps, opts.get("receiver_slack"))
    # the texel allocation across cascades is held with the grids while it stays within the texel budget (one
    # re-allocated every frame would change every cascade's scale, so its grid)
    res = [tuple(m.resolution) for m in maps]
    budget = opts.get("texel_budget") or sum(r[0] * r[1] for r in res)
    top = 2 * max(max(r) for r in res)  # a previous frame's state is a client's JSON: sides within reason
    if held is not None and all(g is not None and 16 <= min(g.resolution) and max(g.resolution) <= top for g in held) \
            and sum(g.resolution[0] * g.resolution[1] for g in held) <= budget:
        res = [g.resolution for g in held]
    out, state = [], []
    xs = sj.get("x") or [None] * len(maps)
    for k, (smap, cf) in enumerate(zip(maps, fits)):
        fresh = grid_of(smap, light, casters_bounds)
        if fresh is not None:
            fresh.resolution = res[k]
            x = xs[k] if k < len(xs) else None
            fresh.x = [float(v) for v in x] if x else None
        m, g, dec = choose_grid(cf, camera, light, fresh, held[k] if held else None, hysteresis)
        dec["objective_per_frame"] = float(sj["cascades"][k]["objective"]) if k < len(sj.get("cascades", [])) else None
        if m is None:
            out.append(smap)
            dec["objective"] = dec["objective_per_frame"]
            state.append({"decision": _finite_or_none(dec)})
            continue
        m.split = smap.split
        with_bias(m, cf.part, light)
        out.append(m)
        dec["fresh"] = fresh.to_json() if fresh is not None else None  # the second pass's input (optimize_path)
        state.append({**g.to_json(), "decision": _finite_or_none(dec)})
    sj["path"] = {"cascades": state, "hysteresis": hysteresis, "ladder_steps_per_octave": LADDER_STEPS,
                  "time_ms": round((time.perf_counter() - t0) * 1e3, 3)}
    sj["fun"] = float(sum(s["decision"]["objective"] or 0.0 for s in state))
    return out, sj


def _finite_or_none(d: dict) -> dict:
    """A decision for JSON: infinite objectives (a grid that cannot hold the receivers) as null."""
    return {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in d.items()}


def previous_state(previous: dict | None, light_index: int):
    """The path state of light `light_index` in a previous solution (service.solve's `previous=`, normalized
    by validate_solution), or None (no previous frame, or one solved by another method)."""
    if not previous or not isinstance(previous.get("solver"), dict):
        return None
    s = previous["solver"]
    if "lights" in s:
        s = s["lights"][light_index] if light_index < len(s["lights"]) else None
    elif light_index != 0:
        return None
    return s.get("path") if isinstance(s, dict) else None


# ------------------------------------------------------------------ whole paths (batch)
@dataclass
class FrameProblem:
    """One frame of a path for one light: what path_maps needs (`opts`: optimized_maps' keywords:
    resolution, cascades, splits, texel_budget, receiver_slack, sample_rows, ...)."""

    camera: object
    light: object
    samples: Samples
    receivers: np.ndarray
    casters_bounds: tuple
    opts: dict = field(default_factory=dict)


@dataclass
class PathResult:
    maps: list  # per frame, the maps (list of ShadowMap per cascade)
    objective: list  # per frame, the predicted objective of those maps
    per_frame_objective: list  # per frame, the per-frame optimizer's (no coherence)
    grid_changes: int  # cascade-frames whose canonical part changed from the previous frame
    level_changes: int  # cascade-frames whose scale level changed with the same canonical part
    passes: dict  # per pass ("interactive", "segments"): the same numbers, and which pass was returned

    def to_json(self) -> dict:
        return {"objective": self.objective, "per_frame_objective": self.per_frame_objective,
                "grid_changes": self.grid_changes, "level_changes": self.level_changes, "passes": self.passes}


def _grid_key(g: Grid):
    return (g.G.tobytes(), g.view.tobytes())


def _changes(grids: list[list[Grid]]) -> tuple[int, int]:
    gc = lc = 0
    for a, b in zip(grids, grids[1:]):
        for ga, gb in zip(a, b):
            if ga is None or gb is None or _grid_key(ga) != _grid_key(gb):
                gc += 1
            elif ga.levels != gb.levels:
                lc += 1
    return gc, lc


def _objective(maps, fp: FrameProblem) -> float:
    return float(predicted_objective(maps, fp.samples, fp.camera.position))


def optimize_path(frames: list[FrameProblem], hysteresis: float | None = None,
                  segment_tolerance: float = SEGMENT_TOLERANCE) -> PathResult:
    """A whole path (batch precomputation). Pass 1 ("interactive"): the editor's choice frame after frame
    (path_maps with the previous frame's state), which also gives each frame's fresh canonical parts and the
    per-frame optimizer's maps (the reference). Pass 2 ("segments", directional lights with the same cascade
    count on every frame): segment_pass. Returned: the pass with the fewest grid and level changes among those
    whose summed objective is within `segment_tolerance` of the per-frame optimizer's (or of the best pass's,
    when a held texel allocation puts that out of reach); both are reported."""
    hysteresis = HYSTERESIS if hysteresis is None else float(hysteresis)
    maps1, grids1, fresh, per_frame, pf_maps = [], [], [], [], []
    state = None
    for fp in frames:
        maps, sj = path_maps(fp.camera, fp.light, fp.samples, fp.receivers, fp.casters_bounds, state, hysteresis,
                             per_frame_out=pf_maps, **fp.opts)
        state = sj["path"]
        maps1.append(maps)
        cs = state.get("cascades") or []
        grids1.append([Grid.from_json(c) for c in cs])
        fresh.append([Grid.from_json(c["decision"]["fresh"]) if c["decision"].get("fresh") else None for c in cs])
        per_frame.append(_objective(pf_maps[-1], fp))
    obj1 = [_objective(m, fp) for m, fp in zip(maps1, frames)]
    gc1, lc1 = _changes(grids1)
    passes = {"interactive": {"objective_sum": float(sum(obj1)), "grid_changes": gc1, "level_changes": lc1}}
    candidates = [(maps1, obj1, gc1, lc1, "interactive")]
    k = len(grids1[0]) if grids1 and grids1[0] else 0
    fits = None
    if k and all(len(g) == k for g in grids1) and all(len(fr) == k and all(f is not None for f in fr) for fr in fresh):
        fits = [cascade_fits(fp.camera, fp.light, fp.samples, fp.receivers, fp.casters_bounds, maps1[i],
                             fp.opts.get("receiver_slack")) for i, fp in enumerate(frames)]
        per_frame_c = [[f.score(m, fp.camera, fp.light) for f, m in zip(fits[i], pf_maps[i])]
                       for i, fp in enumerate(frames)]  # each cascade's reference, scored as segment_pass scores
        got = segment_pass(frames, fits, fresh, per_frame_c, segment_tolerance)
        if got is not None:
            maps3, grids3, rep = got
            for i in range(len(frames)):
                for c, m in enumerate(maps3[i]):
                    m.split = maps1[i][c].split
            obj3 = [_objective(m, fp) for m, fp in zip(maps3, frames)]
            gc3, lc3 = _changes(grids3)
            passes["segments"] = {"objective_sum": float(sum(obj3)), "grid_changes": gc3, "level_changes": lc3,
                                  "cascades": rep}
            candidates.append((maps3, obj3, gc3, lc3, "segments"))
    bound = segment_tolerance * max(float(sum(per_frame)), min(float(sum(cd[1])) for cd in candidates))
    best = min((cd for cd in candidates if sum(cd[1]) <= bound), key=lambda cd: (cd[2] + cd[3], sum(cd[1])))
    if best[4] == "segments":  # the bias of the maps returned (pass 1's have theirs), one per segment
        for i, fp in enumerate(frames):
            for c, m in enumerate(best[0][i]):
                with_bias(m, fits[i][c].part, fp.light)
        for c, r in enumerate(passes["segments"]["cascades"]):
            for a, b in r["segments"]:
                hold_bias([best[0][i][c] for i in range(a, b + 1)])
    passes["returned"] = best[4]
    return PathResult(best[0], best[1], per_frame, best[2], best[3], passes)


def concat_samples(parts: list[Samples]) -> Samples:
    """The samples of several frames as one set (each keeps its own pixel footprint dx, dy, view depth and
    weight): the objective over it is the weighted mean over all the frames' samples."""
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        if any(v is None for v in vals):
            return None if all(v is None for v in vals) else np.concatenate(
                [np.ones(len(p)) if v is None else v for p, v in zip(parts, vals)])
        return np.concatenate(vals)

    return Samples(cat("position"), cat("normal"), cat("dx"), cat("dy"), cat("view_depth"), cat("weight"),
                   cat("pixel"), parts[0].kind, cat("pixels"), cat("light_area_factor"))


def joint_grid(frames: list["FrameProblem"], c: int, resolution=None) -> Grid | None:
    """Cascade c's canonical part optimized for several frames at once: the per-frame optimizer
    (optimized_maps) on the union of their samples and receivers, seen from the middle frame's camera (its
    splits and warp frame), so that its objective is the error summed over the frames. None when that map
    is not a light-plane projective map."""
    mid = frames[len(frames) // 2]
    samples = concat_samples([f.samples for f in frames])
    recs = [np.asarray(f.receivers, float).reshape(-1, 3) for f in frames]
    opts = dict(mid.opts)
    rows, slack, off = [], [], 0
    for f, r in zip(frames, recs):
        sr, sl = f.opts.get("sample_rows"), f.opts.get("receiver_slack")
        rows.append(None if sr is None else np.asarray(sr) + off)
        slack.append(np.zeros(len(r)) if sl is None or len(sl) != len(r) else np.asarray(sl, float))
        off += len(r)
    opts["sample_rows"] = None if any(r is None for r in rows) else np.concatenate(rows)
    opts["receiver_slack"] = np.concatenate(slack)
    opts.pop("x0", None)
    opts["allow_log"] = False
    maps, _ = optimized_maps(mid.camera, mid.light, samples, np.vstack(recs), mid.casters_bounds, **opts)
    if c >= len(maps):
        return None
    g = grid_of(maps[c], mid.light, mid.casters_bounds)
    if g is not None and resolution is not None:
        g.resolution = tuple(resolution)
    return g


def hold_bias(maps: list[ShadowMap]) -> None:
    """One bias for the frames of a segment (in place): each constant and clamp the greatest of the frames'
    (the depth_bias rule's and, per mode, the depth block's), so that a held grid's classification does not
    change with the bias either; the greatest is the one every frame's receivers need."""
    if not maps:
        return
    for key in maps[0].depth_bias:
        v = max(float(m.depth_bias.get(key, 0.0)) for m in maps)
        for m in maps:
            m.depth_bias[key] = v
    if all(m.depth is not None for m in maps):
        for mode in ("hardware", "linear"):
            for key in ("constant", "slope_clamp"):
                v = max(float(m.depth[mode][key]) for m in maps)
                for m in maps:
                    m.depth[mode][key] = v


def segment_pass(frames: list["FrameProblem"], fits: list[list["CascadeFit"]], fresh: list[list[Grid]],
                 reference: list[list[float]], tolerance: float = SEGMENT_TOLERANCE,
                 max_frames: int = SEGMENT_MAX_FRAMES, joint: bool = True):
    """Whole paths, one cascade at a time: cut the path into segments that each hold ONE canonical part and ONE
    scale level (the finest level holding every frame of the segment: tight_levels), so that inside a segment
    each frame only moves its box by whole texels (no texel changes, no flicker) and a change happens only at a
    segment's first frame. The canonical part of a segment is the best of up to SEGMENT_CANDIDATES of its
    frames' fresh ones (the per-frame optimizer's, pass 1). Among all cuts (dynamic programming over segment
    counts), the one with the fewest segments whose summed objective is within `tolerance` x the summed
    `reference` (the per-frame optimizer's objective per frame and cascade); when none is, the lowest sum.
    With `joint`, each chosen segment of two or more frames also tries its joint optimum (joint_grid: the error
    summed over the segment's frames, minimized) and keeps it when its summed objective is lower.
    Returns (maps per frame and cascade, grids per frame and cascade, report) or None when a frame has no
    fresh canonical part."""
    n = len(frames)
    k = len(fits[0]) if n else 0
    if not n or any(len(f) != k for f in fits) or any(len(g) != k or any(x is None for x in g) for g in fresh):
        return None
    maps = [[None] * k for _ in range(n)]
    grids = [[None] * k for _ in range(n)]
    report = []
    for c in range(k):
        cand = []  # per frame: its fresh canonical part, rescaled on its own frame (level 0 = its tight scale)
        for o in range(n):
            g = Grid(fresh[o][c].view, fresh[o][c].G.copy(), fresh[o][c].resolution)
            got = fit_on_grid(g, fits[o][c].fit_pts, fits[o][c].corners, None, frames[o].camera.position)
            cand.append(g if got is not None else None)
        tight = {}

        def level(o, kk):
            if (o, kk) not in tight:
                tight[o, kk] = tight_levels(cand[o], fits[kk][c].fit_pts) if cand[o] is not None else None
            return tight[o, kk]

        cost_cache = {}

        def cost(o, kk, L):
            key = (o, kk, L)
            if key not in cost_cache:
                fp = frames[kk]
                got = fit_on_grid(cand[o], fits[kk][c].fit_pts, fits[kk][c].corners, L, fp.camera.position, L)
                cost_cache[key] = (fits[kk][c].score(got[0], fp.camera, fp.light) if got else math.inf, got)
            return cost_cache[key]

        seg = {}  # (i, j) -> (summed objective, candidate, level)
        for i in range(n):
            for j in range(i, min(n, i + max_frames)):
                idx = sorted({int(round(x)) for x in np.linspace(i, j, min(SEGMENT_CANDIDATES, j - i + 1))})
                best = (math.inf, None, None)
                for o in idx:
                    lv = [level(o, kk) for kk in range(i, j + 1)]
                    if any(v is None for v in lv):
                        continue
                    L = (min(v[0] for v in lv), min(v[1] for v in lv))
                    tot = 0.0
                    for kk in range(i, j + 1):
                        tot += cost(o, kk, L)[0]
                        if tot >= best[0]:
                            break
                    if tot < best[0]:
                        best = (tot, o, L)
                seg[i, j] = best
        # dp[s][j]: the least summed objective of frames 0..j in s segments, and the cut
        INF = (math.inf, None)
        dp = [[INF] * n for _ in range(n + 1)]
        for j in range(min(n, max_frames)):
            dp[1][j] = (seg[0, j][0], None)
        for s_ in range(2, n + 1):
            for j in range(s_ - 1, n):
                best = INF
                for i in range(max(s_ - 1, j - max_frames + 1), j + 1):
                    prev = dp[s_ - 1][i - 1][0]
                    if prev < math.inf and seg[i, j][0] < math.inf and prev + seg[i, j][0] < best[0]:
                        best = (prev + seg[i, j][0], i)
                dp[s_][j] = best
        ref = float(sum(r[c] for r in reference))
        counts = [s_ for s_ in range(1, n + 1) if dp[s_][n - 1][0] < math.inf]
        if not counts:
            return None
        # within tolerance of the reference, or of the best cut when the reference is out of reach (the ladder,
        # the snap and a held texel allocation cost a little even with a segment per frame)
        bound = tolerance * max(ref, min(dp[s_][n - 1][0] for s_ in counts))
        within = [s_ for s_ in counts if dp[s_][n - 1][0] <= bound]
        s_best = within[0] if within else min(counts, key=lambda s_: dp[s_][n - 1][0])
        cuts, j, s_ = [], n - 1, s_best
        report_joint = []
        while s_ >= 1:
            i = dp[s_][j][1] if s_ > 1 else 0
            cuts.append((i, j))
            j, s_ = i - 1, s_ - 1
        for i, j in reversed(cuts):
            if j > i and joint:  # the segment's own optimum: the per-frame optimizer over all its frames' samples
                g = joint_grid(frames[i:j + 1], c, cand[i].resolution if cand[i] is not None else None)
                if g is not None:
                    mid = (i + j) // 2
                    if fit_on_grid(g, fits[mid][c].fit_pts, fits[mid][c].corners, None,
                                   frames[mid].camera.position) is not None:
                        cand.append(g)
                        o = len(cand) - 1
                        lv = [level(o, kk) for kk in range(i, j + 1)]
                        if all(v is not None for v in lv):
                            L = (min(v[0] for v in lv), min(v[1] for v in lv))
                            tot = sum(cost(o, kk, L)[0] for kk in range(i, j + 1))
                            if tot < seg[i, j][0]:
                                report_joint.append([i, j])
                                seg[i, j] = (tot, o, L)
            _, o, L = seg[i, j]
            # one depth for the segment (stored depth from its first camera, the union of the frames' ranges):
            # with the grid and the level held, a frame's light pass stores the same depths as the previous one's
            z0 = frames[i].camera.position
            held = [fit_on_grid(cand[o], fits[kk][c].fit_pts, fits[kk][c].corners, L, z0, L)[0].depth_frame
                    for kk in range(i, j + 1)]
            df = (held[0][0], min(h[1] for h in held), max(h[2] for h in held),
                  (min(h[3][0] for h in held), max(h[3][1] for h in held)))
            for kk in range(i, j + 1):
                got = fit_on_grid(cand[o], fits[kk][c].fit_pts, fits[kk][c].corners, L, None, L, df)
                maps[kk][c] = got[0]
                grids[kk][c] = Grid(cand[o].view, cand[o].G, cand[o].resolution, got[1])
        report.append({"segments": [[i, j] for i, j in reversed(cuts)],
                       "objective_sum": float(sum(seg[i, j][0] for i, j in cuts)),
                       "reference_sum": ref, "within_tolerance": bool(within), "joint": report_joint})
    return maps, grids, report


INTERPOLATION_RULE = ("per cascade, linear interpolation of the 16 entries of the world-to-clip matrix "
                      "(projection x view, column vectors) between the keyframes before and after the frame, each "
                      "keyframe's matrix first divided by the norm of its w row (the same map); the split linearly")


def _unit_w(M: np.ndarray) -> np.ndarray:
    return M / max(float(np.linalg.norm(M[3])), 1e-300)


def interpolated_maps(ma: list[ShadowMap], mb: list[ShadowMap], t: float) -> list[ShadowMap]:
    """INTERPOLATION_RULE's maps at fraction t between keyframe maps ma and mb (same cascade count)."""
    out = []
    for a, b in zip(ma, mb):
        M = (1.0 - t) * _unit_w(a.matrix) + t * _unit_w(b.matrix)
        split = tuple(float((1.0 - t) * x + t * y) if math.isfinite(x) and math.isfinite(y) else x
                      for x, y in zip(a.split, b.split))
        out.append(ShadowMap(np.eye(4), M, a.resolution, split=split, light_depth=a.light_depth,
                             warp_kind=a.warp_kind, n_prime=a.n_prime))
    return out


def keyframes(result: PathResult, frames: list[FrameProblem], every: int) -> dict:
    """Every `every`-th frame's maps (and the last frame's) for engines that interpolate, the rule
    (INTERPOLATION_RULE) and what interpolation adds at the skipped frames, measured there: the objective of the
    interpolated maps over the frame's samples against the chosen maps' (max ratio and max added), and the
    frame's receivers that the interpolated serving map leaves outside (max count)."""
    n = len(frames)
    keys = list(range(0, n, max(1, int(every))))
    if keys[-1] != n - 1:
        keys.append(n - 1)
    worst_ratio, worst_added, worst_outside, per = 1.0, 0.0, 0, []
    for a, b in zip(keys, keys[1:]):
        for j in range(a + 1, b):
            fp = frames[j]
            mi = interpolated_maps(result.maps[a], result.maps[b], (j - a) / (b - a))
            f = _objective(mi, fp)
            f0 = result.objective[j]
            rec = np.asarray(fp.receivers, float).reshape(-1, 3)
            depth = (rec - fp.camera.position) @ fp.camera.forward
            idx = serving_maps(mi, rec, depth)
            outside = int(np.sum(idx < 0))
            for c, m in enumerate(mi):
                sel = idx == c
                if sel.any():
                    s, t, z, w = m.map_coords(rec[sel])
                    with np.errstate(invalid="ignore"):
                        outside += int(np.sum(~((w > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1))))
            ratio = f / f0 if f0 > 0 else (1.0 if f == 0 else math.inf)
            worst_ratio, worst_added = max(worst_ratio, ratio), max(worst_added, f - f0)
            worst_outside = max(worst_outside, outside)
            per.append({"frame": j, "objective": f, "objective_chosen": f0, "outside_receivers": outside})
    return {"every": int(every), "frames": keys,
            "keyframes": [{"frame": i, "cascades": [{"world_to_clip": _unit_w(m.matrix).tolist(),
                                                      "split": [float(v) for v in m.split],
                                                      "resolution": list(m.resolution)} for m in result.maps[i]]}
                          for i in keys],
            "rule": INTERPOLATION_RULE, "max_objective_ratio": worst_ratio, "max_objective_added": worst_added,
            "max_outside_receivers": worst_outside, "skipped": per}


def held_cascade_count(maps_for, maps, info, auto: dict, state, shadow: dict, hysteresis: float | None = None):
    """`cascades: "auto"` with method path: the previous frame's count is kept unless the count auto_cascades
    chose scores better by the hysteresis factor (objective x texels below `hysteresis` x the held count's), or,
    with a target_p95_m, unless the held count misses the target and the chosen one meets it. Returns (maps, info,
    auto) as service.map_sizing.auto_cascades does, the rule saying when the held count was kept."""
    hysteresis = HYSTERESIS if hysteresis is None else float(hysteresis)
    if not isinstance(state, dict) or not isinstance(state.get("cascades"), list):
        return maps, info, auto
    k_prev = len(state["cascades"])
    tried = {t["cascades"]: t for t in auto.get("tried", [])}
    k_new = auto["chosen"]
    if k_prev == k_new or k_prev not in tried:
        return maps, info, auto
    target = shadow.get("target_p95_m")
    old, new = tried[k_prev], tried[k_new]
    if target is not None:
        keep = old["p95_m"] <= target or new["p95_m"] > target
    else:
        keep = not (new["objective"] * new["texels"] < hysteresis * old["objective"] * old["texels"])
    if not keep:
        return maps, info, auto
    maps, info = maps_for(k_prev)
    return maps, info, {**auto, "chosen": k_prev,
                        "rule": f"{auto['rule']}; the previous frame's {k_prev} kept (path hysteresis {hysteresis})"}
