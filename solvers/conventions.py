"""Matrix conventions engines receive: OpenGL, Direct3D, Vulkan; row- or column-major; world or stage frame.

The one place these conventions are defined. Internally (solvers.shadow_map) matrices act on column
vectors, `view` maps world -> light view (the light looks down -Z) and `projection` maps light view ->
a canonical clip space: OpenGL's, NDC x, y, z in [-1, 1], map coordinates s = (x+1)/2, t = (y+1)/2
with t = 0 at the bottom. Each step an engine needs is one small function:

    clip_from_canonical(conv)  C: canonical clip -> the convention's clip      P_engine = C · P
    texture_from_clip(conv)    S: the convention's clip -> texture (s, t, depth) in [0, 1] (bias matrix)
    texture_matrix(V, P, conv) S · C · P · V: world -> texture, divide by w afterwards (Everitt et al.
                               2001, "Hardware Shadow Mapping": the chain S · P_light · V_light)
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
In every convention depth in the texture is 0 at the light's near plane and 1 at its far plane, unless
reversed_z is set: then the clip z is reversed so that the near plane maps to window depth 1 and the far
plane to 0 (Lapidous and Jiao 1999; Reed 2015 "Depth Precision Visualized"), and the texture depth
likewise (1 - depth). d3d / vulkan: NDC z' = 1 - z_ndc in [0, 1] (near 1, far 0; clear to 0, compare
GREATER). opengl: NDC z' = -z_ndc in [-1, 1] (near +1, far -1), so the window depth (z' + 1)/2 is again
near 1, far 0; defined for completeness, it gains no precision unless the engine also switches to a
[0, 1] clip range (glClipControl(..., GL_ZERO_TO_ONE)), where the d3d convention with reversed_z is the
right choice.
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


def clip_from_canonical(convention: str, reversed_z: bool = False) -> np.ndarray:
    """C with engine_projection = C @ canonical_projection.

    opengl: identity (clip z in [-w, w]); reversed_z: z' = -z (NDC near +1, far -1).
    d3d:    z' = 0.5 z + 0.5 w, so NDC z' = (z_ndc + 1)/2 in [0, 1]; reversed_z: z' = 0.5 w - 0.5 z,
            NDC z' = 1 - (z_ndc + 1)/2 (near 1, far 0).
    vulkan: as d3d, and y' = -y (NDC y points down).
    """
    _check(convention)
    c = np.eye(4)
    if convention in ("d3d", "vulkan"):
        c[2] = [0.0, 0.0, -0.5, 0.5] if reversed_z else [0.0, 0.0, 0.5, 0.5]
    elif reversed_z:
        c[2, 2] = -1.0
    if convention == "vulkan":
        c[1, 1] = -1.0
    return c


def texture_from_clip(convention: str) -> np.ndarray:
    """The bias matrix S: that convention's clip space -> texture (s, t, depth) in [0, 1] after the divide.

    opengl: S = [[.5,0,0,.5],[0,.5,0,.5],[0,0,.5,.5],[0,0,0,1]] (Everitt et al. 2001, "Hardware Shadow Mapping");
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


def projection_for(proj_canonical: np.ndarray, convention: str, reversed_z: bool = False) -> np.ndarray:
    """The projection matrix in the engine's convention: C · P."""
    return clip_from_canonical(convention, reversed_z) @ _mat4(proj_canonical, "projection")


def texture_matrix(view: np.ndarray, proj_canonical: np.ndarray, convention: str,
                   reversed_z: bool = False) -> np.ndarray:
    """S · C · P · V (Everitt et al. 2001 "Hardware Shadow Mapping": S · P_light · V_light, P in the given
    convention): world -> texture. Divide the result by its w to get (s, t, depth) in [0, 1]
    (textureProj / tex2Dproj does this); with reversed_z the depth is 1 at the near plane, 0 at the far."""
    return (texture_from_clip(convention) @ projection_for(proj_canonical, convention, reversed_z)
            @ _mat4(view, "view"))


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
                    stage_to_world: np.ndarray | None = None, reversed_z: bool = False) -> dict:
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
    tex = texture_matrix(v, proj_canonical, convention, reversed_z)
    if frame == "stage":
        s2w = np.eye(4) if stage_to_world is None else stage_to_world
        v, tex = to_stage_frame(v, s2w), to_stage_frame(tex, s2w)
    return {"view_matrix": to_layout(v, layout),
            "projection_matrix": to_layout(projection_for(proj_canonical, convention, reversed_z), layout),
            "texture_matrix": to_layout(tex, layout)}


# ---------------------------------------------------------------------------------------------------
# Engine presets (output.engine). One row per engine; each names the documentation it follows.
#   convention  clip-space rule of the returned projection (clip_from_canonical) and the texture origin
#               (texture_from_clip): opengl bottom-left, d3d / vulkan top-left
#   reversed_z  near plane at depth 1, far at 0
#   layout      memory order of the 16 numbers (the matrices act on column vectors, M @ v)
#   axes        the engine's world axes in shadowopt's world frame (right-handed, +Y up, metres):
#               engine coordinate i = sign * world coordinate, e.g. ("x", "y", "-z"): x_e = x, y_e = y, z_e = -z
#   metres_per_unit  the engine's length unit in metres
#   view        the light view space the view matrix maps to: "-z" (right-handed, the light looks down -Z,
#               as OpenGL) or "+z" (left-handed, looks down +Z, as Direct3D's and Unreal's view space)
# ---------------------------------------------------------------------------------------------------
ENGINES = ("opengl", "d3d", "vulkan", "unity", "unreal", "godot", "three", "bevy", "filament")
_RH_Y_UP_M = {"axes": ("x", "y", "z"), "metres_per_unit": 1.0, "view": "-z"}
ENGINE_PRESETS: dict[str, dict] = {
    "opengl": {"convention": "opengl", "reversed_z": False, "layout": "column_major", **_RH_Y_UP_M,
               "docs": "OpenGL 4.6 core profile specification, 13.8 (clip z in [-w, w]); glOrtho / glFrustum "
                       "reference pages; glUniformMatrix4fv (column-major with transpose GL_FALSE)"},
    "d3d": {"convention": "d3d", "reversed_z": False, "layout": "column_major", **_RH_Y_UP_M,
            "docs": "Direct3D 11 rasterization rules and viewports (NDC z in [0, 1], texture origin top-left); "
                    "HLSL matrix packing (column_major by default)"},
    "vulkan": {"convention": "vulkan", "reversed_z": False, "layout": "column_major", **_RH_Y_UP_M,
               "docs": "Vulkan 1.3 specification, coordinate transformations (NDC y down, z in [0, 1]); "
                       "GLSL mat4 column-major"},
}


def preset_conflicts(engine: str, given: dict) -> list[str]:
    """The fields of an output spec that contradict the engine preset: `given` holds only the fields the
    request set explicitly (convention, layout, reversed_z, frame). One message per field, naming both."""
    if engine not in ENGINE_PRESETS:
        return [f"output.engine: unknown engine {engine!r} (known: {', '.join(ENGINES)})"]
    p = ENGINE_PRESETS[engine]
    out = []
    for key in ("convention", "layout", "reversed_z"):
        if key in given and given[key] != p[key]:
            out.append(f"output.engine {engine!r} sets output.{key} to {p[key]!r} but output.{key} is "
                       f"{given[key]!r}: give one of them")
    if given.get("frame") == "stage":
        out.append(f"output.engine {engine!r} sets the frame (the engine's world frame and units) but "
                   "output.frame is 'stage': give one of them")
    elif given.get("frame") == "world" and not _is_world_frame(p):
        out.append(f"output.engine {engine!r} sets the frame (the engine's world frame and units) but "
                   "output.frame is 'world': give one of them")
    return out


def _is_world_frame(p: dict) -> bool:
    return tuple(p["axes"]) == ("x", "y", "z") and p["metres_per_unit"] == 1.0 and p["view"] == "-z"
