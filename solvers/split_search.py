"""Optimized cascade splits: the k - 1 inner split depths that minimise the metric's objective.

The objective is the one the solution predicts (solvers.metric: the weighted mean of Chong &
Gortler's h over the light's samples, each sample scored on the cascade serving its view depth),
evaluated on a cheap per-cascade map (LiSPSM, or the method given) so that a split candidate costs
one fit and one metric pass per cascade. With a texel budget the candidate is scored at the
allocation the returned maps get (solvers.cascades.allocate_mean of the samples' and the
receivers' terms, cascades.with_receivers; objective_mean is its value in closed form), not at
LiSPSM's own eq. 83 allocation. The objective is piecewise (a sample jumps cascade when a
split crosses it), so the search is derivative-free: NLopt's BOBYQA from the best of the uniform,
logarithmic and practical (λ = 0.5) splits, over s_i in [0, 1] with z_i = z_n (z_f / z_n)^(s_i)
(Lloyd et al. 2007 eq. 80's log spacing is s_i = i / k). The optimizer of each cascade's light
matrix then runs at the chosen splits (solvers.optimized_maps.optimized_maps).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import nlopt
import numpy as np

from .baselines import fit_baseline
from .cascade_scores import cascade_terms, depth_shares
from .cascades import ONE_SIZE_PER_LIGHT, objective_mean, receiver_depth_range, split_depths
from .metric import predicted_error
from .samples import Samples, seeded_rows

SEARCH_RECEIVERS = 500  # receivers kept for the search's map fits (the final maps fit all of them)
SEARCH_RECEIVER_TERMS = 128  # of those, per cascade, the ones its receivers' terms are measured on


@dataclass
class SplitResult:
    split_at: np.ndarray  # the k - 1 inner split depths (view depth, metres)
    fun: float  # the objective at them (search maps)
    start: str  # which standard split the search started from
    starts: dict  # objective of each standard split
    nfev: int
    time_ms: float

    def to_json(self) -> dict:
        return {"split_at": [float(z) for z in self.split_at], "fun": self.fun, "start": self.start,
                "starts": {k: float(v) for k, v in self.starts.items()}, "nfev": self.nfev,
                "time_ms": round(self.time_ms, 3)}


def _subsample(receivers: np.ndarray, slack: np.ndarray | None, n: int):
    if len(receivers) <= n:
        return receivers, slack
    idx = seeded_rows(len(receivers), n)
    # keep the extremes along each axis so the fits span what the full set spans
    idx = np.unique(np.concatenate([idx, np.argmin(receivers, 0), np.argmax(receivers, 0)]))
    return receivers[idx], (None if slack is None else slack[idx])


def optimize_splits(camera, light, samples: Samples, receivers: np.ndarray, casters_bounds, resolution,
                    cascades: int, texel_budget: int | None = None, receiver_slack=None, method: str = "lispsm",
                    maxeval: int | None = None) -> SplitResult:
    """The inner split depths minimising the objective of `method`'s maps (a directional light)."""
    t0 = time.perf_counter()
    k = int(cascades)
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    z_lo, z_hi = receiver_depth_range(camera, (receivers - camera.position) @ camera.forward)
    rec, slack = _subsample(receivers, None if receiver_slack is None else np.asarray(receiver_slack, float),
                            SEARCH_RECEIVERS)
    nfev = 0

    def split_at(s) -> np.ndarray:
        return z_lo * (z_hi / z_lo) ** np.sort(np.clip(np.asarray(s, float), 0.0, 1.0))

    total_w = max(float(np.sum(samples.weight)), 1e-300)
    depth = np.sort((receivers - camera.position) @ camera.forward)

    def f(s) -> float:
        nonlocal nfev
        nfev += 1
        fitted = fit_baseline(method, camera, light, rec, casters_bounds, resolution, cascades=k,
                              allow_log=False, receiver_slack=slack, split_at=split_at(s))  # no bias: not scored
        if not texel_budget:
            v = predicted_error(fitted.maps, samples, camera.position)["objective"]
            return v if math.isfinite(v) else 1e300
        # the allocation the returned maps get (solvers.optimized_maps: allocate_mean), in closed form
        subs = []
        for m in fitted.maps:
            sel = (samples.view_depth >= m.split[0]) & (samples.view_depth <= m.split[1])
            subs.append(samples.subset(sel))
        terms = cascade_terms(fitted.maps, subs, fitted.parts, camera, light, total_w, depth_shares(fitted.maps, depth),
                              SEARCH_RECEIVER_TERMS)
        v = objective_mean(*terms, texel_budget, shared=ONE_SIZE_PER_LIGHT) if terms is not None else math.inf
        return v if math.isfinite(v) else 1e300

    if k < 2 or len(samples) == 0 or z_hi <= z_lo * (1 + 1e-9):
        z = split_depths(z_lo, z_hi, k)[1:-1]
        return SplitResult(z, math.nan, "practical", {}, 0, (time.perf_counter() - t0) * 1e3)
    starts = {}
    for kind in ("uniform", "log", "practical"):
        z = split_depths(z_lo, z_hi, k, kind, 0.5)[1:-1]
        starts[kind] = np.log(z / z_lo) / math.log(z_hi / z_lo)
    vals = {kind: f(s) for kind, s in starts.items()}
    best_kind = min(vals, key=vals.get)
    best = [vals[best_kind], starts[best_kind]]

    def g(s, grad):
        v = f(s)
        if v < best[0]:
            best[0], best[1] = v, np.array(s, float)
        return v / max(vals[best_kind], 1e-300)

    opt = nlopt.opt(nlopt.LN_BOBYQA, k - 1)
    opt.set_lower_bounds([0.0] * (k - 1))
    opt.set_upper_bounds([1.0] * (k - 1))
    opt.set_min_objective(g)
    opt.set_maxeval(int(maxeval or 4 * (k - 1) + 4))  # speed: ~20 candidates in all for 4 cascades
    opt.set_xtol_abs(1e-2)  # 1% of the log depth range
    opt.set_initial_step(0.08)
    try:
        opt.optimize(np.clip(starts[best_kind], 1e-3, 1 - 1e-3).tolist())
    except Exception:  # roundoff-limited: the best point seen is kept
        pass
    return SplitResult(split_at(best[1]), float(best[0]), best_kind, vals, nfev, (time.perf_counter() - t0) * 1e3)
