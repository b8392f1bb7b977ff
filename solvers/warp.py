"""Perspective warps in light space (LiSPSM, Lloyd's η) and the LogPSM log warp: the formulas.

Light view space: the light looks down -Z (directional), +Y is the camera's view direction
projected into the light's image plane (the LiSPSM frame). The warp puts a centre of projection at
y_c = y_min - n' behind the receivers and divides by (y - y_c): light rays (constant x, y) stay
parallel, so the light remains directional after the warp, and texels are denser near the viewer.
"""
from __future__ import annotations

import math

import numpy as np

from .fitting import PAD_TEXELS
from .shadow_map import LogWarp

NO_WARP_SIN = 0.02  # Filament: no warp when sin(light, view) < 0.02 (about 1 degree)
MAX_N_OVER_DEPTH = 1e3  # n' beyond this many body depths is indistinguishable from no warp


def lispsm_n(z_near: float, z_far: float, sin_gamma: float) -> float:
    """Wimmer et al. 2004: n_opt = (z_n + sqrt(z_f z_n)) / sin γ (anchors.md, OpenSceneGraph's form)."""
    return (z_near + math.sqrt(z_far * z_near)) / max(sin_gamma, 1e-12)


def n_prime_from_eta(eta: float, n_e: float, f_e: float, w_ly: float | None = None) -> float:
    """Lloyd et al. 2007 eq. 120 (as reconstructed in the digest; the seed's layout is garbled):
    α = f_e/n_e; η < 0: n' = W/(α-1) (√α + 1 - η(α-1))/(η+1); η >= 0: n' = W/(α-1) (√α+1)/(η√α + 1).
    η = -1 -> ∞ (uniform), 0 -> n_e + sqrt(n_e f_e) (LiSPSM), 1 -> n_e, for W = f_e - n_e."""
    w = (f_e - n_e) if w_ly is None else w_ly
    alpha = max(f_e / n_e, 1.0 + 1e-9)
    ra = math.sqrt(alpha)
    if eta <= -1.0:
        return math.inf
    if eta < 0:
        return w / (alpha - 1) * (ra + 1 - eta * (alpha - 1)) / (eta + 1)
    return w / (alpha - 1) * (ra + 1) / (eta * ra + 1)


def eta_from_n_prime(n_prime: float, n_e: float, f_e: float, w_ly: float | None = None) -> float:
    """The inverse of n_prime_from_eta (eq. 120): the η a warp distance n' corresponds to, e.g. to
    report LiSPSM's n_opt (which is η = 0 only at γ = 90°) on Lloyd's scale. n' = ∞ -> -1."""
    w = (f_e - n_e) if w_ly is None else w_ly
    alpha = max(f_e / n_e, 1.0 + 1e-9)
    ra = math.sqrt(alpha)
    k = w / (alpha - 1)
    if not math.isfinite(n_prime):
        return -1.0
    n_prime = max(float(n_prime), 1e-300)
    if n_prime <= k * (ra + 1):
        return (k * (ra + 1) / n_prime - 1.0) / ra
    return (k * (ra + 1) - n_prime) / (n_prime + k * (alpha - 1))


def eta_shaping(gamma_deg: float, theta_deg: float, kind: str = "logp") -> float:
    """Lloyd et al. 2007 eq. 79 with the digest's corrections (first branch -1, not 0; last branch
    γ > γ_c), §6.1.1 parameters: LogP γ_a = θ/2, γ_b = θ, γ_c = θ + 0.4(90° - θ), η_b = -0.2,
    η_c = 1; "P" (improved LiSPSM) γ_a = θ/3, η_c = 0. γ is folded to [0, 90] (light in front of
    or behind the viewer is symmetric)."""
    g = min(gamma_deg % 360.0, 360.0 - gamma_deg % 360.0)
    g = min(g, 180.0 - g)
    ga = theta_deg / 2 if kind == "logp" else theta_deg / 3
    gb = theta_deg
    gc = theta_deg + 0.4 * (90.0 - theta_deg)
    eb, ec = -0.2, (1.0 if kind == "logp" else 0.0)
    if g < ga:
        return -1.0
    if g < gb:
        return -1.0 + (eb + 1.0) * (g - ga) / (gb - ga)
    if g < gc:
        return eb + (ec - eb) * math.sin(math.radians(90.0 * (g - gb) / (gc - gb)))
    return ec


def warp_matrix(y_centre: float, x_centre: float = 0.0) -> np.ndarray:
    """Light view -> warped space: x' = x - x_c, y' = -1, z' = z, w' = y - y_c.
    After the divide Y = -1/(y - y_c) grows with y; Z = z/(y - y_c) is linear along each light ray."""
    m = np.zeros((4, 4))
    m[0, 0], m[0, 3] = 1.0, -x_centre
    m[1, 3] = -1.0
    m[2, 2] = 1.0
    m[3, 1], m[3, 3] = 1.0, -y_centre
    return m


def logp_params(y0: float, y1: float, a: float) -> tuple[float, float, float]:
    """Lloyd et al. 2007 eq. 78 (digest): c0 = -1/log((y1+a)/(y0+a)), c1 = -(y1-y0)/(y1+a), c2 = 1,
    for a perspective t_p that is 0 at y0 and 1 at y1 with centre of projection at y = -a; then
    c1 t_p + c2 = (y0+a)/(y+a) and t = c0 log(c1 t_p + c2) = log((y+a)/(y0+a)) / log((y1+a)/(y0+a))."""
    return -1.0 / math.log((y1 + a) / (y0 + a)), -(y1 - y0) / (y1 + a), 1.0


def log_warp(depth: float, n_prime: float) -> LogWarp:
    """Lloyd et al. 2007 eq. 78 with y0 = 0, y1 = W (the body's depth along the warp axis), a = n':
    c0 = -1/log((y1+a)/(y0+a)), c1 = -(y1-y0)/(y1+a), c2 = 1, so that c1 t_p + c2 = (y0+a)/(y+a)
    and t = log((y+a)/a) / log((W+a)/a)."""
    return LogWarp(*logp_params(0.0, float(depth), float(n_prime)))


def padded_log(lw: LogWarp, texels: int) -> LogWarp:
    """The log warp's t' padded after itself by PAD_TEXELS texels: t'' = (t' + p) / (1 + 2p),
    p = margin / (n - 2 margin), which is again c0'' log(c1'' t + c2''), c0'' = c0 / (1 + 2p) and
    c1'', c2'' = e^(p / c0) (c1, c2)."""
    p = PAD_TEXELS / max(texels - 2.0 * PAD_TEXELS, 1.0)
    k = math.exp(p / lw.c0)
    return LogWarp(lw.c0 / (1.0 + 2.0 * p), lw.c1 * k, lw.c2 * k)


def gamma_deg(view_dir: np.ndarray, light_dir: np.ndarray) -> float:
    """Angle between the view direction and the direction the light travels (90 = overhead sun)."""
    c = float(np.clip(np.dot(view_dir, light_dir) / (np.linalg.norm(view_dir) * np.linalg.norm(light_dir)), -1, 1))
    return math.degrees(math.acos(c))
