"""`method: optimized` for one light: per cascade, the optimized map or the best baseline, whichever the
metric scores lower (solvers.optimize.minimize searches one map's projective parameters; this module
runs the baselines, the split search, the starts and the choice per cascade, and biases what it keeps).
"""
from __future__ import annotations

import math
import time

import numpy as np

from .baselines import METHODS as BASELINES, fit_baseline
from .cameras import Camera
from .cascade_scores import cascade_terms, depth_shares, receiver_h, receiver_terms
from .cascades import ONE_SIZE_PER_LIGHT, allocate_mean, mean_terms
from .depth_modes import with_bias
from .lights import DirectionalLight
from .metric import per_sample_maps, predicted_error, predicted_objective, serial_kernels
from .optimize import Problem, minimize, optimizable, single_map_spot
from .samples import Samples
from .search_methods import DEFAULT_METHOD, METHODS
from .split_search import optimize_splits


def _shared_hull(fitted, k: int, part: np.ndarray, sub: Samples, receivers: np.ndarray, sample_rows, sel_s, sel_r):
    """The baselines' light-plane hull of cascade k, for the search too, when it is what Problem would
    compute: the same receivers, and every sample one of them at the same position (Qhull gives the
    same vertices in the same order when duplicates of the points are appended after them). Else None."""
    hull = fitted.fit_points[k]
    if hull is None or sample_rows is None or not len(hull[1]):
        return None
    if fitted.parts[k].shape != part.shape or not np.array_equal(fitted.parts[k], part):
        return None
    rows = np.asarray(sample_rows)[sel_s]
    if len(rows) and not (sel_r[rows].all() and np.array_equal(receivers[rows], sub.position)):
        return None
    return hull


def _receiver_weights(maps, subs, parts, camera, light, total_weight: float, shares):
    """Per cascade, rho_k = kappa N_k / W_k: the weight of its receivers' mean h beside its samples'
    mean h in cascades.with_receivers' objective (kappa from `maps`, one baseline per cascade; W_k
    the cascade's share of the sample weight, N_k its share of the receivers). None when a term is
    not finite (a receiver outside a map)."""
    P, Q, W, Pr, Qr = [], [], [], [], []
    for smap, sub, pts in zip(maps, subs, parts):
        p, q = mean_terms(smap, sub) if len(sub) else (0.0, 0.0)
        P.append(p / total_weight), Q.append(q / total_weight)
        W.append(float(np.sum(sub.weight)) / total_weight if len(sub) else 0.0)
        pr, qr = receiver_terms(smap, pts, camera, light)
        Pr.append(pr), Qr.append(qr)
    if not all(math.isfinite(v) for v in P + Q + Pr + Qr):
        return None
    P, Q, W, Pr, Qr = (np.asarray(v, float) for v in (P, Q, W, Pr, Qr))
    C, c = 2.0 * np.sqrt(P * Q), 2.0 * np.sqrt(Pr * Qr)
    den = float(np.sum((W * c)[C > 0]))
    kappa = float(np.sum(C)) / den if den > 0 and np.sum(C) > 0 else 1.0
    return kappa * np.asarray(shares, float) / np.maximum(W, 1e-300)


def _mean_h(smap, sub: Samples) -> float:
    """The weighted mean h of one map over samples from mean_terms (no kernel launch; inf when a
    sample has no valid footprint): to rank candidates before the allocation."""
    p, q = mean_terms(smap, sub)
    return (p / smap.resolution[0] ** 2 + q / smap.resolution[1] ** 2) / max(float(np.sum(sub.weight)), 1e-300)


def _reallocate(maps, subs, parts, camera, light, budget, total_weight, shares, also=None) -> None:
    """Set each cascade's resolution to allocate_mean's for `maps`, and the same on the maps in also[k]."""
    terms = cascade_terms(maps, subs, parts, camera, light, total_weight, shares)
    if terms is None:
        return  # a sample or receiver outside a map: keep the allocation it was scored at
    for k, r in enumerate(allocate_mean(*terms, budget, shared=ONE_SIZE_PER_LIGHT)):
        for m in [maps[k]] + (also[k] if also else []):
            if m.face is None:
                m.resolution = r


@serial_kernels()
def optimized_maps(camera: Camera, light, samples: Samples, receivers: np.ndarray, casters_bounds,
                   resolution=(2048, 2048), cascades: int = 1, splits: str = "practical", split_lambda: float = 0.5,
                   texel_budget: int | None = None, allow_log: bool = False, solver: str = DEFAULT_METHOD,
                   time_budget_ms: float | None = None, receiver_slack=None, x0=None, previous_x=None,
                   hysteresis: float = 0.8, sample_rows: np.ndarray | None = None):
    """`method: optimized`: per cascade, the optimized map or the best baseline, whichever the metric
    scores lower on that cascade's samples (so never worse than the best baseline). With several
    cascades (directional light) the score adds rho_k x the candidate's receivers' mean h (receiver_h;
    _receiver_weights), and a cascade no sample reaches is scored on its receivers alone. With a
    texel budget the resolutions are solvers.cascades.allocate_mean's for the samples' plus the
    receivers' mean h (before the search, from each cascade's best baseline, and again for the
    maps kept), not eq. 83. Returns (maps, solver_json).

    Temporal stability (Chong & Gortler 2007 §3): with `previous_x` (the previous solution's x per
    cascade), the previous projective parameters are refit to the current receivers and kept unless
    the new map's median h is below `hysteresis` x the refit one's.

    `sample_rows`: per sample, the index of the receiver at the same position, when the samples are
    receivers (service.solve's are): the search then reuses the baselines' hull of each cascade."""
    if solver not in METHODS:
        raise ValueError(f"solver: unknown solver {solver!r} (known: {', '.join(METHODS)})")
    t0 = time.perf_counter()
    split_info = None
    split_at = None
    if splits == "optimized":
        splits = "practical"
        if isinstance(light, DirectionalLight) and int(cascades) > 1:
            sr = optimize_splits(camera, light, samples, receivers, casters_bounds, resolution, int(cascades),
                                 texel_budget=texel_budget, receiver_slack=receiver_slack)
            split_at, split_info = sr.split_at, sr.to_json()
    by_mean = bool(texel_budget) and isinstance(light, DirectionalLight) and int(cascades) > 1
    if by_mean:  # allocate_mean sets the resolutions below: the baselines' own eq. 83 is not needed
        side = max(16, math.isqrt(int(texel_budget) // int(cascades)))
        resolution, budget_for_fit = (side, side), None
    else:
        budget_for_fit = texel_budget
    common = dict(resolution=resolution, cascades=cascades, splits=splits, split_lambda=split_lambda,
                  texel_budget=budget_for_fit, receiver_slack=receiver_slack, split_at=split_at)
    hulls: dict = {}  # the receivers' light-plane hull per cascade, shared by the four methods
    fitted = {m: fit_baseline(m, camera, light, receivers, casters_bounds, allow_log=allow_log and m == "logpsm",
                              hull_cache=hulls, **common) for m in BASELINES}
    per_method = {m: f.maps for m, f in fitted.items()}
    bias_points = {m: list(f.parts) for m, f in fitted.items()}  # per map, what its bias is measured on if kept
    ref = per_method["focused"]
    proxy = single_map_spot(light, receivers)
    if proxy is not None and ref and ref[0].face is not None:
        # A point light whose visible receivers lie in one cone: one perspective map with an optimized
        # axis instead of six cube faces, kept when the metric scores it no worse than the cube.
        maps, sj = optimized_maps(camera, proxy, samples, receivers, casters_bounds, resolution, 1, solver=solver,
                                  time_budget_ms=time_budget_ms, receiver_slack=receiver_slack)
        cube = float(predicted_error(ref, samples, camera.position)["objective"])
        if sj["fun"] <= cube:
            sj["point_light"] = {"single_map_cone_deg": proxy.cone_deg, "cube_objective": cube}
            return maps, sj
    if ref and ref[0].face is not None:  # a cube map (point light, wide spot): fixed 90° faces, nothing to search
        ref = fitted["focused"].biased(light)
        return ref, {"name": solver, "time_ms": round((time.perf_counter() - t0) * 1e3, 3), "nit": 0, "nfev": 0,
                     "fun": float(predicted_error(ref, samples, camera.position)["objective"]), "success": True,
                     "converged": True, "message": "cube map: six fixed 90-degree faces, no projective parameters",
                     "x": [None] * len(ref), "cascades": []}
    depth = (receivers - camera.position) @ camera.forward if len(receivers) else np.zeros(0)
    slack = np.zeros(len(receivers)) if receiver_slack is None else np.asarray(receiver_slack, float)
    out_maps, info, kept = [], [], []
    subs = []
    total_w = max(float(np.sum(samples.weight)), 1e-300)
    shares = depth_shares(ref, depth)
    for rmap in ref:
        sel_s = (samples.view_depth >= rmap.split[0]) & (samples.view_depth <= rmap.split[1])
        subs.append((sel_s, samples if sel_s.all() else samples.subset(sel_s)))
    if by_mean:
        # The budget shared for the mean h the service minimises (cascades.allocate_mean), from each
        # cascade's best baseline at focused's eq. 83 allocation, before the search: the optimizer
        # then searches at the resolution the cascade will have. Cascades no sample reaches keep eq. 83's area.
        firsts = []
        for k, (sel_s, sub) in enumerate(subs):
            pts = bias_points["focused"][k]
            sc = ({m: _mean_h(maps[k], sub) for m, maps in per_method.items()} if len(sub)
                  else {m: receiver_h(maps[k], pts, camera, light) for m, maps in per_method.items()})
            firsts.append(per_method[min(sc, key=sc.get)][k])
        _reallocate(firsts, [sub for _, sub in subs], bias_points["focused"], camera, light, texel_budget, total_w,
                    shares, [[maps[k] for maps in per_method.values()] + [ref[k]] for k in range(len(ref))])
    rho = None
    if isinstance(light, DirectionalLight) and len(ref) > 1 and len(receivers) > 0:
        rho = _receiver_weights([per_method["lispsm"][k] for k in range(len(ref))], [sub for _, sub in subs],
                                bias_points["lispsm"], camera, light, total_w, shares)
    for k, rmap in enumerate(ref):
        lo, hi = rmap.split
        sel_s, sub = subs[k]
        sel_r = np.ones(len(receivers), bool)
        if isinstance(light, DirectionalLight) and len(receivers) > 0:
            sel_r = (depth + slack >= (lo if k else -np.inf)) & (depth - slack <= (hi if k < len(ref) - 1 else np.inf))
        part_r = receivers[sel_r]
        hull_r = _shared_hull(fitted["focused"], k, part_r, sub, receivers, sample_rows, sel_s, sel_r)
        for m, maps in per_method.items():  # one allocation (focused's) for every candidate: the budget holds
            if tuple(maps[k].resolution) != tuple(rmap.resolution) and maps[k].face is None:
                maps[k].resolution = rmap.resolution
                bias_points[m][k] = part_r if sel_r.any() else receivers
        if len(sub) > 0:
            scores = {m: predicted_objective([maps[k]], sub, camera.position) for m, maps in per_method.items()}
        else:  # no sample in this cascade: every map scores 0 on the samples; score on its receivers
            pts = part_r if len(part_r) else receivers
            scores = {m: receiver_h(maps[k], pts, camera, light) for m, maps in per_method.items()}
        # With cascades, a candidate is scored on the samples' mean h plus its receivers' (rho[k] x
        # receiver_h): the objective allocate_mean spends the budget on (cascades.with_receivers, per
        # cascade: divided by its share of the sample weight), so a map that serves the boundary
        # samples but leaves the cascade's other receivers huge, warped texels (and bias) is not kept.
        pts_k = part_r if len(part_r) else receivers
        rh = ({m: receiver_h(maps[k], pts_k, camera, light) for m, maps in per_method.items()}
              if rho is not None and len(sub) > 0 else {})
        total = {m: v + rho[k] * rh[m] for m, v in scores.items()} if rh else scores
        best_name = min(total, key=total.get)
        best_map, best_f = per_method[best_name][k], scores[best_name]
        entry = {"cascade": k, "baselines": {m: float(v) for m, v in scores.items()},
                 "scored_on": "samples" if len(sub) > 0 else "receivers"}
        if rh:
            entry["receiver_h"] = {m: float(v) for m, v in rh.items()}
            entry["receiver_weight"] = float(rho[k])
        if len(sub) == 0:
            best_f = 0.0  # the solution's objective: the mean h over its samples (none here)
        if optimizable(light) and len(sub) > 0 and len(receivers) > 0:
            left = None if time_budget_ms is None else max(1.0, time_budget_ms - (time.perf_counter() - t0) * 1e3)
            starts = {m: per_method[m][k] for m in ("focused", "lispsm", "logpsm")}
            res = minimize(camera, light, sub, part_r, casters_bounds, rmap.resolution, solver,
                           x0=x0[k] if x0 is not None and k < len(x0) else None, time_budget_ms=left,
                           start_maps_given=starts, bias=False, fit_points=hull_r)
            entry["result"] = res.to_json()
            if allow_log and isinstance(light, DirectionalLight):  # LogPSM's family too; the lower objective wins
                left = None if time_budget_ms is None else max(1.0, time_budget_ms - (time.perf_counter() - t0) * 1e3)
                res_log = minimize(camera, light, sub, part_r, casters_bounds, rmap.resolution, solver,
                                   time_budget_ms=left, log=True, start_maps_given=starts, bias=False,
                                   fit_points=hull_r)
                entry["result_log"] = res_log.to_json()
                if res_log.map is not None and res_log.fun < res.fun:
                    res = res_log
                    entry["result"], entry["result_log"] = res_log.to_json(), entry["result"]
                    entry["result"]["warp"] = "log"
            # strictly lower beyond roundoff: a baseline map the search returned as it is (res.fun is the
            # Dr.Jit sum, best_f the NumPy one) keeps its baseline name
            if rh and res.map is not None:
                rh_opt = receiver_h(res.map, pts_k, camera, light)
                entry["receiver_h"]["optimized"] = float(rh_opt)
                if res.fun + rho[k] * rh_opt < total[best_name] * (1.0 - 1e-12):
                    best_map, best_f, best_name = res.map, res.fun, "optimized"
                    best_map.eta = None
            elif res.map is not None and res.fun < best_f * (1.0 - 1e-12):
                best_map, best_f, best_name = res.map, res.fun, "optimized"
                best_map.eta = None
        prev = previous_x[k] if previous_x is not None and k < len(previous_x) else None
        if prev is not None and isinstance(light, DirectionalLight) and len(sub) > 0 and len(receivers) > 0:
            refit = Problem(camera, light, sub, part_r, casters_bounds, rmap.resolution, fit_points=hull_r).map_for(
                np.asarray(prev, dtype=np.float64))
            h_new, _, _ = per_sample_maps([best_map], sub, camera.position)
            h_old, _, _ = per_sample_maps([refit], sub, camera.position)
            med_new, med_old = float(np.median(h_new)), float(np.median(h_old))
            keep = not (med_new < hysteresis * med_old)
            entry["temporal"] = {"previous_x": [float(v) for v in prev], "median_h_new": med_new,
                                 "median_h_previous_refit": med_old, "hysteresis": hysteresis, "kept_previous": keep}
            if keep:
                best_map, best_name = refit, "optimized"
                best_f = float(predicted_error([refit], sub, camera.position)["objective"])
                if "result" in entry:
                    entry["result"]["x"] = [float(v) for v in prev]
        best_map.split = rmap.split
        if best_name == "optimized":
            best_map.resolution = rmap.resolution
        kept.append(part_r if best_name == "optimized" else bias_points[best_name][k])
        entry["chosen"] = best_name
        entry["objective"] = float(best_f)
        out_maps.append(best_map)
        info.append(entry)
    if by_mean:  # the final maps' own allocation (exact for their matrices: h = p / w^2 + q / h^2)
        _reallocate(out_maps, [sub for _, sub in subs], kept, camera, light, texel_budget, total_w, shares)
        for m, e, (_, sub) in zip(out_maps, info, subs):
            e["resolution"] = list(m.resolution)
            if len(sub):
                e["objective"] = float(predicted_objective([m], sub, camera.position))
    for m, pts in zip(out_maps, kept):
        with_bias(m, pts, light)
    results = [e.get("result", {}) for e in info]
    solver_json = {"name": solver, "time_ms": round((time.perf_counter() - t0) * 1e3, 3),
                   "nit": int(sum(r.get("nit", 0) for r in results)), "nfev": int(sum(r.get("nfev", 0) for r in results)),
                   "fun": float(sum(e["objective"] for e in info)),
                   "success": all(r.get("success", True) for r in results),
                   "converged": all(r.get("success", True) for r in results),
                   "message": "; ".join(sorted({r.get("message", "") for r in results if r})) or "best baseline (no optimizable projective parameters)",
                   "x": [r.get("x") for r in results], "cascades": info}
    if split_info is not None:
        solver_json["splits"] = split_info
    return out_maps, solver_json
