"""The returned matrices rasterized by real OpenGL (Mesa llvmpipe through EGL), compared with the
ray-cast map. OpenGL runs in a subprocess: Mesa loads LLVM 15, and Dr.Jit in this process uses 19."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shadowopt.renderers.shadow_map_rays import render_map
from shadowopt.service.pipeline import scene_entry
from shadowopt.service.rigs import resolve_rig
from shadowopt.service.request import SolveRequest
from shadowopt.service.solution_json import maps_from_solution
from shadowopt.service.solve import solve
from shadowopt.solvers.conventions import from_layout

from testkit import gl_depth

pytestmark = pytest.mark.gl

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("convention,reversed_z", [("opengl", False), ("d3d", False), ("vulkan", False),
                                                   ("d3d", True)])
def test_gl_rasterized_depths_match_the_ray_cast_map(tmp_path, convention, reversed_z):
    rig = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    from shadowopt.api.cli import validate_rig

    rig["output"] = {"convention": convention, "layout": "column_major", "reversed_z": reversed_z}
    rig = validate_rig(rig)
    entry = scene_entry(REPO / "configs" / "demo_scene.usda")
    sol = solve(entry, rig, SolveRequest("focused"))
    cascade = sol["lights"][0]["cascades"][0]
    res = (256, 256)
    # The engine's matrices, as returned: projection (this convention) · view, column-major.
    view = from_layout(cascade["view_matrix"], "column_major")
    proj = from_layout(cascade["projection_matrix"], "column_major")
    smap = maps_from_solution(sol)[0][0]
    smap.resolution = res
    rs = entry.rays
    # Re-centre on the ray scene's origin in float64 before the float32 upload, as an engine would.
    t = np.eye(4)
    t[:3, 3] = rs.origin
    verts = entry.loaded.geometry.vertices - rs.origin
    depth = gl_depth(tmp_path, verts, entry.loaded.geometry.faces, proj @ view @ t, res,
                     "neg_one_to_one" if convention == "opengl" else "zero_to_one", reversed_z)
    if convention == "vulkan":
        # Vulkan's NDC y points down: its framebuffer row 0 is the map's top (t = 1). OpenGL stores
        # rows bottom-up, so the Vulkan image arrives upside down here; flip it back.
        depth = depth[::-1]
    # Ray-cast reference: distance from each texel's near point to the first hit.
    resolved = resolve_rig(rig, entry.loaded)
    d_ray = render_map(rs, resolved.lights[0], smap)
    # GL window depth -> canonical NDC z -> the point on the texel's ray -> distance from its near point.
    h, w = res
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    s, tt = (ii + 0.5) / w, (jj + 0.5) / h
    if reversed_z:  # near plane at 1, far at 0, cleared to 0: back to the usual order
        depth = 1.0 - depth
    covered = depth < 1.0
    z_ndc = 2.0 * depth - 1.0 if convention == "opengl" else depth  # engine NDC z
    if convention != "opengl":
        z_ndc = 2.0 * z_ndc - 1.0  # back to canonical [-1, 1]
    inv = np.linalg.inv(smap.matrix)
    pts_h = np.stack([2 * s - 1, 2 * tt - 1, z_ndc, np.ones_like(s)], -1) @ inv.T
    pts = pts_h[..., :3] / pts_h[..., 3:]
    near, _ = smap.texel_rays(s.ravel(), tt.ravel())
    d_gl = np.linalg.norm(pts.reshape(-1, 3) - near, axis=1).reshape(h, w)
    both = covered & np.isfinite(d_ray)
    assert both.mean() > 0.5
    assert np.array_equal(covered, np.isfinite(d_ray)) or np.mean(covered != np.isfinite(d_ray)) < 0.01
    err = np.abs(d_gl - d_ray)[both]
    span = smap.light_depth[1] - smap.light_depth[0]
    # Away from silhouettes the two agree to depth-buffer precision; silhouettes differ by a texel.
    assert np.median(err) < 1e-4 * span and np.mean(err < 1e-3 * span) > 0.97, (np.median(err), span)
