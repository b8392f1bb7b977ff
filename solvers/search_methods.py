"""The searches solvers.optimize.minimize runs over a problem's projective parameters x = (φ, u) from its
best start, each within the problem's deadline (its check_deadline raises TimeBudgetReached; the problem
keeps the best point seen): Chong & Gortler 2007's line search (gradient:linesearch), NLopt's algorithms
(nlopt:*) and torch's L-BFGS and Adam (gradient:lbfgs, gradient:adam). METHODS names them."""
from __future__ import annotations

import math
from typing import Protocol

import nlopt
import numpy as np


class Problem(Protocol):
    """What a search needs of a problem (solvers.optimize.Problem is one): its bounds, the best point seen
    (value, x), the objective and its gradient, clipping into the bounds and the deadline check."""
    lower: np.ndarray
    upper: np.ndarray
    best: tuple

    def value(self, x: np.ndarray) -> float: ...
    def gradient(self, x: np.ndarray) -> np.ndarray: ...
    def value_and_grad(self, x: np.ndarray) -> tuple: ...
    def clip(self, x: np.ndarray) -> np.ndarray: ...
    def check_deadline(self) -> None: ...

METHODS = ("gradient:lbfgs", "gradient:adam", "gradient:linesearch", "nlopt:LN_BOBYQA", "nlopt:LN_COBYLA",
           "nlopt:LN_SBPLX", "nlopt:GN_DIRECT_L", "nlopt:LD_MMA", "nlopt:LD_LBFGS", "nlopt:LD_SLSQP")
EXTRA_METHODS = ("none",)  # no search: the best start (or the warm start), for temporal stability
DEFAULT_METHOD = "nlopt:LN_BOBYQA"  # measured: the best time to the lowest error (BENCHMARKS.md)
XTOL, FTOL_REL = 1e-3, 1e-4  # NLopt stopping rules: (φ, u) within 1e-3, or a relative change of f below 1e-4
# Chong & Gortler 2007 §3: line search over these angles (degrees) along the negative gradient,
# the negative one forcing exploration.
CG07_ANGLES_DEG = (-10, 3, 5, 9, 16, 23, 30, 40, 50)


class TimeBudgetReached(Exception):
    pass


def search(prob, method: str, x: np.ndarray, maxiter: int, n_samples: int) -> tuple[int, bool, str]:
    """Run `method` from x within the problem's deadline: (iterations, success, message). The problem
    keeps the best point seen, so a search cut by the time budget still has a result."""
    try:
        prob.check_deadline()
        if n_samples == 0:
            return 0, True, "no samples: the best starting point is returned"
        if method == "none":
            return 0, True, "no optimization (method 'none'): the best start"
        return _run(method, prob, x, maxiter), True, "converged"
    except TimeBudgetReached:
        return 0, False, "time budget reached"


def _run(method: str, prob: Problem, x: np.ndarray, maxiter: int) -> int:
    kind, name = method.split(":")
    lo, hi = prob.lower, prob.upper
    if method == "gradient:linesearch":  # beside φ = 0, the affine fit's symmetric tie (as below)
        return cg07_linesearch(prob, np.asarray(x, float) + [1e-3, 0.0], maxiter)
    if kind == "gradient":
        return _torch(name, prob, x, maxiter, lo, hi)
    if name == "GN_DIRECT_L":
        n = _nlopt(nlopt.GN_DIRECT_L, prob, x, lo, hi, maxeval=max(4 * maxiter, 60))
        # a short local polish from the best point DIRECT found (its boxes resolve slowly)
        return n + _nlopt(nlopt.LN_BOBYQA, prob, prob.best[1], lo, hi, maxeval=2 * maxiter, step=0.05)
    if name.startswith("LD"):  # φ = 0 is a symmetric tie of the affine fit (f jumps there): start beside it
        return _nlopt(getattr(nlopt, name), prob, np.asarray(x, float) + [1e-3, 0.0], lo, hi, maxeval=2 * maxiter)
    return _nlopt(getattr(nlopt, name), prob, x, lo, hi, maxeval=3 * maxiter)


def _nlopt(algo, prob: Problem, x, lo, hi, maxeval: int, step: float = 0.2) -> int:
    opt = nlopt.opt(algo, 2)
    opt.set_lower_bounds(lo.tolist())
    opt.set_upper_bounds(hi.tolist())
    scale = max(abs(prob.best[0]), 1e-300)  # objective normalised by the start's value

    def f(v, grad):
        if grad.size > 0:
            fv, g = prob.value_and_grad(v)
            grad[:] = g / scale
            return fv / scale
        return prob.value(v) / scale

    opt.set_min_objective(f)
    opt.set_maxeval(int(maxeval))
    opt.set_xtol_abs([XTOL, XTOL])
    opt.set_ftol_rel(FTOL_REL)
    opt.set_initial_step([step, step])
    try:
        opt.optimize(np.clip(np.asarray(x, float), lo, hi).tolist())
    except TimeBudgetReached:
        raise
    except Exception:  # nlopt's roundoff-limited or runtime errors: the problem keeps the best value seen
        pass
    return int(opt.get_numevals())


def _torch(name: str, prob: Problem, x, maxiter: int, lo, hi) -> int:
    import torch  # lazy: seconds to import (11 s measured under load), only the gradient:lbfgs/adam solvers use it

    scale = max(abs(prob.best[0]), 1e-300)
    # The baselines' φ = 0 is a symmetric tie of the affine fit (f jumps there): start just beside it.
    x = np.asarray(x, float) + [1e-3, 0.0]
    p = torch.tensor(np.clip(x, lo, hi), dtype=torch.float64, requires_grad=True)
    lo_t, hi_t = torch.tensor(lo), torch.tensor(hi)

    def closure():
        opt.zero_grad()
        fv, g = prob.value_and_grad(p.detach().numpy())
        inside = ((p.detach() > lo_t) & (p.detach() < hi_t)).numpy()
        # on a bound, keep a component only when the step -g leads back inside (g has the sign of the side
        # the bound is on): the outward one is dropped, the inward one is what leaves the bound
        g = np.where(inside | (np.sign(g) * np.sign((lo + hi) / 2 - p.detach().numpy()) < 0), g, 0.0)
        p.grad = torch.tensor(g / scale, dtype=torch.float64)
        return torch.tensor(fv / scale, dtype=torch.float64)

    if name == "lbfgs":
        nit = 0
        for _ in range(3):  # restarts: a kink of the fit ends a strong-Wolfe search; a fresh history goes on
            before = prob.best[0]
            opt = torch.optim.LBFGS([p], lr=1.0, max_iter=maxiter, max_eval=2 * maxiter, tolerance_grad=1e-7,
                                    tolerance_change=1e-9, history_size=10, line_search_fn="strong_wolfe")
            opt.step(closure)
            nit += int(opt.state[p].get("n_iter", 0))
            with torch.no_grad():
                p.copy_(torch.tensor(prob.best[1]))
            if prob.best[0] > before * (1 - 1e-4):
                break
        return nit
    if name == "adam":
        opt = torch.optim.Adam([p], lr=0.05)
        for it in range(2 * maxiter):
            opt.step(closure)
            with torch.no_grad():
                p.clamp_(lo_t, hi_t)
        prob.value(p.detach().numpy())
        return 2 * maxiter
    raise ValueError(f"method: unknown solver 'gradient:{name}' (known: {', '.join(METHODS)})")


def cg07_linesearch(prob: Problem, x: np.ndarray, maxiter: int) -> int:
    """Chong & Gortler 2007 Algorithm 1: gradient, then a line search over fixed step sizes along the
    negative gradient (one backwards, for forced exploration), halving the smallest step when none of
    them helps, a few iterations."""
    fx = prob.value(x)
    it = 0
    for it in range(1, min(maxiter, 8) + 1):
        g = prob.gradient(x)
        norm = float(np.linalg.norm(g))
        if norm == 0 or not math.isfinite(norm):
            break
        d = -g / norm
        best = (fx, x)
        for a in CG07_ANGLES_DEG:
            step = math.radians(a) * 4  # degrees of the paper's sphere rotation, scaled to (φ, u) units
            xn = prob.clip(x + step * d)
            fn = prob.value(xn)
            if fn < best[0]:
                best = (fn, xn)
        step = math.radians(min(a for a in CG07_ANGLES_DEG if a > 0)) * 4
        for _ in range(6):  # none of the fixed steps helps: halve the smallest one (backtracking)
            if best[0] < fx * (1 - 1e-4):
                break
            step *= 0.5
            xn = prob.clip(x + step * d)
            fn = prob.value(xn)
            if fn < best[0]:
                best = (fn, xn)
        if best[0] >= fx * (1 - 1e-4):
            break
        fx, x = best
    return it
