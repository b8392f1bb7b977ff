"""Temporal stability of shadow maps along a camera path, measured against ray-traced ground truth.

For two consecutive frames a, b (static geometry, static sun), each with its camera and its maps:

- Correspondence: every receiver pixel of frame a (renderers.ground_truth.evaluate_buffers: refined world
  position X, normal, exact visibility) is re-projected into frame b's camera (pinhole, the pixel whose
  square contains X's projection). The point is kept when that pixel of b is a receiver on the same surface
  (same prim, b's view depth there within coarse.DEPTH_CONTINUITY of X's view depth in b: not occluded, not
  off screen) and its exact visibility is the same as at a's pixel (the point's true shadow did not change).
- flicker: the fraction of kept points whose classification by the maps changes: a's classification at the
  pixel (evaluate_buffers' map_shadowed) against X classified with b's maps by the same lookup
  (ground_truth.classify_points: b's cascade for X's view depth in b, the same depth test). A world point
  whose shadow pops in or out while the truth stands still is what users see as shimmer.
- swim_texels: for the kept points served by the same cascade index in a and b (inside both), the texel
  coordinates u = (s * width, t * height) in a's and b's serving map; the motion modulo the texel grid,
  d = frac(u_b) - frac(u_a) wrapped to [-0.5, 0.5) per axis, and swim = mean |d| (Euclidean, texels).
  0 for a map whose texel grid is fixed in the world (Valient 2008: snapped maps do not swim); 0.5 for a
  map moved by half a texel along one axis.
- misclassified per frame: evaluate_buffers' misclassified_pixels (the quality benchmark's count).

The depth test is each map's stated engine test (depth="solution") unless another is given.
"""
from __future__ import annotations

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import Light
from ..solvers.shadow_map import ShadowMap
from .coarse import DEPTH_CONTINUITY
from .ground_truth import GroundTruth, classify_points, evaluate_buffers, screen_camera
from .ray_scene import RayScene


def project_pixels(camera: Camera, X: np.ndarray):
    """(i, j, view_depth, ok) of world points X (N, 3) in `camera` at its resolution: the pixel whose
    square contains the pinhole projection (Camera's convention: ndc = ((i + 0.5) / w * 2 - 1,
    1 - (j + 0.5) / h * 2)); ok where in front of the near plane and on screen."""
    w, h = camera.resolution
    v = np.asarray(X, dtype=np.float64) - camera.position
    z = v @ camera.forward
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (v @ camera.right) / (z * tw)
        y = (v @ camera.up) / (z * th)
        fi = np.floor((x + 1.0) * 0.5 * w)
        fj = np.floor((1.0 - y) * 0.5 * h)
    ok = np.isfinite(fi) & np.isfinite(fj) & (z > camera.near) & (fi >= 0) & (fi < w) & (fj >= 0) & (fj < h)
    i = np.where(ok, fi, 0).astype(np.int64)
    j = np.where(ok, fj, 0).astype(np.int64)
    return i, j, z, ok


def correspondences(gt_a: GroundTruth, gt_b: GroundTruth, cam_b: Camera):
    """The receiver pixels of frame a whose world point is the same receiver in frame b with unchanged
    exact visibility (module doc). Returns (rows, cols of a; X (N, 3); normals (N, 3); view depth in b; rows, cols of b)."""
    sa, sb = gt_a.screen, gt_b.screen
    ra, ca = np.nonzero(gt_a.receivers)
    X = sa.position[ra, ca]
    i, j, zb, ok = project_pixels(cam_b, X)
    keep = ok.copy()
    keep[ok] &= gt_b.receivers[j[ok], i[ok]]
    keep[keep] &= sb.prim[j[keep], i[keep]] == sa.prim[ra[keep], ca[keep]]
    with np.errstate(invalid="ignore"):
        keep[keep] &= np.abs(sb.depth[j[keep], i[keep]] - zb[keep]) < DEPTH_CONTINUITY * zb[keep]
    keep[keep] &= sb.visible[j[keep], i[keep]] == sa.visible[ra[keep], ca[keep]]
    return ra[keep], ca[keep], X[keep], sa.normal[ra[keep], ca[keep]], zb[keep], j[keep], i[keep]


def wrapped_texel_motion(uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """|frac(u_b) - frac(u_a)| per point, each axis wrapped to [-0.5, 0.5) (texels, Euclidean)."""
    d = (uv_b - np.floor(uv_b)) - (uv_a - np.floor(uv_a))
    d = d - np.floor(d + 0.5)
    return np.linalg.norm(d, axis=-1)


def pair_from_truth(rs: RayScene, cam_b: Camera, light: Light, maps_b: list[ShadowMap], gt_a: GroundTruth,
                    gt_b: GroundTruth, depth: str = "solution", device_maps_b: list | None = None) -> dict:
    """frame_pair_stability from the frames' evaluations (cam_b at the evaluation screen). Also returns
    "device_maps" (b's rendered maps, for reuse) and "changed" / "changed_b" (rows, cols of the flickering
    points' pixels in a / in b)."""
    ra, ca, X, N, zb, rb, cb = correspondences(gt_a, gt_b, cam_b)
    looked = classify_points(rs, light, maps_b, X, N, zb, depth=depth, device_maps=device_maps_b)
    changed = looked["shadowed"] != gt_a.map_shadowed[ra, ca]
    n = len(X)
    same = (gt_a.map_index[ra, ca] == looked["map_index"]) & ~gt_a.outside[ra, ca] & ~looked["outside"]
    uv_a, uv_b = gt_a.texel_uv[ra, ca][same], looked["texel_uv"][same]
    fin = np.all(np.isfinite(uv_a), axis=-1) & np.all(np.isfinite(uv_b), axis=-1)
    motion = wrapped_texel_motion(uv_a[fin], uv_b[fin])
    return {"flicker": float(changed.mean()) if n else 0.0, "flicker_pixels": int(changed.sum()),
            "swim_texels": float(motion.mean()) if len(motion) else 0.0, "swim_pixels": int(len(motion)),
            "pixels": int(n), "device_maps": looked["device_maps"], "changed": (ra[changed], ca[changed]),
            "changed_b": (rb[changed], cb[changed])}


def frame_pair_stability(rs: RayScene, cam_a: Camera, cam_b: Camera, light: Light, maps_a: list[ShadowMap],
                         maps_b: list[ShadowMap], screen: tuple[int, int] | None, depth: str = "solution",
                         gt_a: GroundTruth | None = None, gt_b: GroundTruth | None = None) -> dict:
    """{"flicker", "swim_texels", "pixels", "flicker_pixels", "swim_pixels", "misclassified_a",
    "misclassified_b"} between frames a and b (module doc). gt_a, gt_b: the frames' evaluate_buffers at
    `screen` with `depth`, when the caller has them (a path evaluates each frame once)."""
    if gt_a is None:
        gt_a = evaluate_buffers(rs, cam_a, light, maps_a, screen, depth=depth)
    if gt_b is None:
        gt_b = evaluate_buffers(rs, cam_b, light, maps_b, screen, depth=depth)
    out = pair_from_truth(rs, screen_camera(cam_b, screen), light, maps_b, gt_a, gt_b, depth)
    for k in ("device_maps", "changed", "changed_b"):
        out.pop(k)
    out["misclassified_a"] = gt_a.result["misclassified_pixels"]
    out["misclassified_b"] = gt_b.result["misclassified_pixels"]
    return out


def path_stability(rs: RayScene, cameras: list[Camera], light: Light, maps: list[list[ShadowMap]],
                   screen: tuple[int, int] | None, depth: str = "solution", keep=None) -> dict:
    """Every frame evaluated once, every consecutive pair measured: {"flicker": [per pair], "swim_texels":
    [per pair], "pixels": [per pair], "misclassified": [per frame], "receivers": [per frame], "outside":
    [per frame]}. keep(frame index, GroundTruth, flickered): called with each frame's evaluation (e.g. for
    heatmaps), flickered the (h, w) mask of the frame's pixels whose world point's classification changed
    since the previous frame (None for the first)."""
    out = {"flicker": [], "swim_texels": [], "pixels": [], "misclassified": [], "receivers": [], "outside": []}
    prev = None
    for f, (cam, mp) in enumerate(zip(cameras, maps)):
        gt = evaluate_buffers(rs, cam, light, mp, screen, depth=depth)
        for k, key in (("misclassified", "misclassified_pixels"), ("receivers", "receiver_pixels"),
                       ("outside", "outside_pixels")):
            out[k].append(int(gt.result[key]))
        flickered = None
        if prev is not None:
            p = pair_from_truth(rs, screen_camera(cam, screen), light, mp, prev, gt, depth)
            for k in ("flicker", "swim_texels", "pixels"):
                out[k].append(p[k])
            flickered = np.zeros(gt.receivers.shape, bool)
            flickered[p["changed_b"]] = True
        if keep is not None:
            keep(f, gt, flickered)
        prev = gt
    return out
