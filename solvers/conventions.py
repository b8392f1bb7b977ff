"""Matrix conventions engines receive: OpenGL, Direct3D, Vulkan; row- or column-major; world or stage frame.

The one place these conventions are defined. Internally (solvers.shadow_map) matrices act on column
vectors, `view` maps world -> light view (the light looks down -Z) and `projection` maps light view ->
a canonical clip space: OpenGL's, NDC x, y, z in [-1, 1], map coordinates s = (x+1)/2, t = (y+1)/2
with t = 0 at the bottom. Each step an engine needs is one small function:

    clip_from_canonical(conv)  C: canonical clip -> the convention's clip      P_engine = C · P
    texture_from_clip(conv)    S: the convention's clip -> texture (s, t, depth) in [0, 1] (bias matrix)
    texture_matrix(V, P, conv) S · C · P · V: world -> texture, divide by w afterwards (seed 003's
                               "Hardware Shadow Mapping" chain S · P_light · V_light)
    to_layout / from_layout    4x4 <-> 16 floats in row- or column-major memory order
    to_stage_frame(M, s2w)     M · stage_to_world: the same map, acting on the stage's own coordinates
    from_stage_frame(M', s2w)  M' · stage_to_world⁻¹: its inverse (back to a matrix acting on world points)
    stage_from(M, s2w)         (M · stage_to_world)⁻¹: the inverse for points, X (light view, clip or
                               texture coordinates, homogeneous) -> stage coordinates
    export_matrices(...)       all of the above, as the service returns them

Conventions:
    opengl  clip z in [-w, w] (NDC z in [-1, 1]), NDC y up, texture origin bottom-left (t = 0 at the bottom)
    d3d     clip z in [0, w] (NDC z in [0, 1]), NDC y up, texture origin top-left (v flipped: t = 0.5 - 0.5 y)
    vulkan  clip z in [0, w] (NDC z in [0, 1]), NDC y down (y' = -y), texture origin top-left
            (t = 0.5 + 0.5 y_vk, the same texel rows as d3d)
In every convention depth in the texture is 0 at the light's near plane and 1 at its far plane.
"""
from __future__ import annotations

import numpy as np

CONVENTIONS = ("opengl", "d3d", "vulkan")
LAYOUTS = ("row_major", "column_major")
FRAMES = ("world", "stage")


def _check(convention: str) -> None:
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}")


def _check_layout(layout: str) -> None:
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")


def _mat4(m, name: str = "matrix") -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"{name} must be 4x4, got shape {a.shape}")
    return a


def clip_from_canonical(convention: str) -> np.ndarray:
    """C with engine_projection = C @ canonical_projection.

    opengl: identity (clip z in [-w, w]).
    d3d:    z' = 0.5 z + 0.5 w, so NDC z' = (z_ndc + 1)/2 in [0, 1].
    vulkan: as d3d, and y' = -y (NDC y points down).
    """
    _check(convention)
    c = np.eye(4)
    if convention in ("d3d", "vulkan"):
        c[2] = [0.0, 0.0, 0.5, 0.5]
    if convention == "vulkan":
        c[1, 1] = -1.0
    return c


def texture_from_clip(convention: str) -> np.ndarray:
    """The bias matrix S: that convention's clip space -> texture (s, t, depth) in [0, 1] after the divide.

    opengl: S = [[.5,0,0,.5],[0,.5,0,.5],[0,0,.5,.5],[0,0,0,1]] (seed 003, "Hardware Shadow Mapping");
            t = 0 at the bottom of the map, depth = (z + 1)/2.
    d3d:    t = 0.5 - 0.5 y (texture origin top-left, v flipped); depth z passes through ([0, 1]).
    vulkan: NDC y already points down, so t = 0.5 + 0.5 y (origin top-left); depth passes through.
    """
    _check(convention)
    if convention == "opengl":
        return np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])
    if convention == "d3d":
        return np.array([[0.5, 0, 0, 0.5], [0, -0.5, 0, 0.5], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
    return np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])


def projection_for(proj_canonical: np.ndarray, convention: str) -> np.ndarray:
    """The projection matrix in the engine's convention: C · P."""
    return clip_from_canonical(convention) @ _mat4(proj_canonical, "projection")


def texture_matrix(view: np.ndarray, proj_canonical: np.ndarray, convention: str) -> np.ndarray:
    """S · C · P · V (seed 003's chain S · P_light · V_light, P in the given convention): world -> texture.

    Divide the result by its w to get (s, t, depth) in [0, 1] (textureProj / tex2Dproj does this)."""
    return texture_from_clip(convention) @ projection_for(proj_canonical, convention) @ _mat4(view, "view")


def to_layout(m: np.ndarray, layout: str) -> list[float]:
    """A flat list of 16 floats in memory order: row_major m[0,0], m[0,1], ...; column_major m[0,0], m[1,0], ...

    The matrix always acts on column vectors (M @ v). GLSL's mat4 constructors and glUniformMatrix4fv
    (transpose = GL_FALSE) read column_major; an HLSL/D3DX engine that multiplies row vectors
    (mul(v, M)) wants the transpose, which is this matrix's column_major list read as row-major.
    """
    _check_layout(layout)
    m = _mat4(m)
    return (m.ravel() if layout == "row_major" else m.T.ravel()).tolist()


def from_layout(flat, layout: str) -> np.ndarray:
    """Inverse of to_layout."""
    _check_layout(layout)
    a = np.asarray(flat, dtype=np.float64)
    if a.size != 16:
        raise ValueError(f"a flat 4x4 matrix has 16 values, got {a.size}")
    a = a.reshape(4, 4)
    return a if layout == "row_major" else a.T.copy()


def to_stage_frame(m_world: np.ndarray, stage_to_world: np.ndarray) -> np.ndarray:
    """A world -> X matrix re-expressed to act on stage coordinates: m @ stage_to_world
    (solvers.frames.stage_to_world(up_axis, meters_per_unit)). Only matrices whose input is a world
    point change: view and texture matrices, not the projection (its input is light view space)."""
    return _mat4(m_world) @ _mat4(stage_to_world, "stage_to_world")


def from_stage_frame(m_stage: np.ndarray, stage_to_world: np.ndarray) -> np.ndarray:
    """Inverse of to_stage_frame: a stage -> X matrix back to world -> X, m_stage @ inv(stage_to_world)."""
    return _mat4(m_stage) @ np.linalg.inv(_mat4(stage_to_world, "stage_to_world"))


def stage_from(m_world: np.ndarray, stage_to_world: np.ndarray) -> np.ndarray:
    """The inverse for points: X -> stage coordinates, inv(m_world @ stage_to_world)
    = inv(stage_to_world) @ inv(m_world). For a view matrix X is light view space (affine: w stays 1);
    for a projection or texture chain feed homogeneous X and divide the result by its w
    (e.g. texel centre (s, t, depth, 1) -> the stage point it samples)."""
    return np.linalg.inv(to_stage_frame(m_world, stage_to_world))


def export_matrices(view: np.ndarray, proj_canonical: np.ndarray, convention: str = "opengl",
                    layout: str = "column_major", frame: str = "world",
                    stage_to_world: np.ndarray | None = None) -> dict:
    """The matrices an engine receives, each a flat 16-list in `layout`:
    view_matrix (world or stage -> light view), projection_matrix (light view -> the convention's clip),
    texture_matrix (world or stage -> texture, S · C · P · V). frame "stage" applies to_stage_frame to
    the view and texture matrices; stage_to_world None there means the stage is already the world
    frame (Y up, meters)."""
    _check(convention)
    _check_layout(layout)
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    v = _mat4(view, "view")
    tex = texture_matrix(v, proj_canonical, convention)
    if frame == "stage":
        s2w = np.eye(4) if stage_to_world is None else stage_to_world
        v, tex = to_stage_frame(v, s2w), to_stage_frame(tex, s2w)
    return {"view_matrix": to_layout(v, layout),
            "projection_matrix": to_layout(projection_for(proj_canonical, convention), layout),
            "texture_matrix": to_layout(tex, layout)}
