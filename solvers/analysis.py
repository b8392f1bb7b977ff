"""Lloyd et al. 2007's scene-independent analysis: critical resolution factors R_s, R_t and the
storage factor S = R_s R_t for a view frustum (half-angle θ, far/near ratio a = f/n), a directional
light at angle γ to the view direction, a parameterization and k equal-ratio z-partitions.

At γ = 90° (overhead light, where Lloyd's Table 3 minima occur) the closed forms are exact
(§5, eqs. 87-89 and the Table 2 forms; the digest verifies that Table 3's minima are X / (2 tan θ),
i.e. S without the 1/cos²θ factor):
    uniform      R_t = (a - 1)/sin 2θ,                 S = a (a - 1) / (2 tan θ)
    perspective  R_t = (a - 1)/(sin 2θ · √a · cos θ),  S = (a - 1) / (2 tan θ)        (min over n')
    log          R_t = ln a / sin 2θ,                  S = ln a / (2 tan θ)
and R_s = S / R_t. With k partitions each has ratio r = a^(1/k) and S adds up over partitions
(Table 3: ZPk = k r (r - 1), ZPk+P = k (r - 1), ZPk+Log = ln a, all over 2 tan θ).
Table 3's ZP5+P row is internally inconsistent (its max and mean are copied from ZP5+Log, digest);
its minimum 12.9 is what these forms give.

Away from 90° this module uses a documented approximation, not Lloyd's eqs. 111-119: a warped
parameterization loses its advantage as the light turns towards the view direction, following the
η shaping function (eq. 79): with w = (1 + η(γ))/2 in [0, 1] (0 = no warp), log S_method(γ) is
interpolated between log S_uniform and log S_method(90°) by w (P: w = 1 + η with η_c = 0), and the
uniform factors are taken as independent of γ (Table 3: standard maps vary only 2.31x over all
light directions); γ within 0.01° of 0° or 180° is clamped so that the answer stays finite.
"""
from __future__ import annotations

import math

from .warp import eta_shaping

METHODS = ("uniform", "perspective", "log")
GAMMA_GUARD_DEG = 0.01


def _at_overhead(a: float, theta: float, method: str) -> tuple[float, float]:
    """(R_t, S) for one frustum of far/near ratio a at γ = 90°."""
    s2, t = math.sin(2 * theta), math.tan(theta)
    if method == "uniform":
        return (a - 1) / s2, a * (a - 1) / (2 * t)
    if method == "perspective":
        return (a - 1) / (s2 * math.sqrt(a) * math.cos(theta)), (a - 1) / (2 * t)
    return math.log(a) / s2, math.log(a) / (2 * t)


def analyze(f_over_n: float, theta_deg: float, gamma_deg: float, method: str, partitions: int = 1) -> dict:
    """{"R_s", "R_t", "S"} for the whole view frustum (S summed over partitions, R the maxima)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not (f_over_n > 1 and 0 < theta_deg < 90 and 0 <= gamma_deg <= 180 and partitions >= 1):
        raise ValueError("need f_over_n > 1, 0 < theta_deg < 90, 0 <= gamma_deg <= 180, partitions >= 1")
    theta = math.radians(theta_deg)
    r = f_over_n ** (1.0 / partitions)
    g = min(max(gamma_deg, GAMMA_GUARD_DEG), 180.0 - GAMMA_GUARD_DEG)
    w = 1.0
    if method != "uniform":
        eta = eta_shaping(g, theta_deg, "logp" if method == "log" else "p")
        w = (1.0 + eta) / 2.0 if method == "log" else min(1.0, 1.0 + eta)
    R_s_max = R_t_max = S = 0.0
    for _ in range(partitions):
        Rt_u, S_u = _at_overhead(r, theta, "uniform")
        Rt_m, S_m = _at_overhead(r, theta, method)
        Rs_u, Rs_m = S_u / Rt_u, S_m / Rt_m
        Rt = math.exp((1 - w) * math.log(Rt_u) + w * math.log(Rt_m))
        Rs = math.exp((1 - w) * math.log(Rs_u) + w * math.log(Rs_m))
        R_s_max, R_t_max = max(R_s_max, Rs), max(R_t_max, Rt)
        S += Rs * Rt
    return {"R_s": R_s_max, "R_t": R_t_max, "S": S}
