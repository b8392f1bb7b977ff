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
    engine_matrices(V, P, e)   an engine preset (ENGINE_PRESETS, output.engine): the matrices on points in
                               that engine's world frame and units
    output_frame / convention_info   the output's frame and length unit, and the solution's `convention`

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

from .frames import engine_from_world, world_from_engine

CONVENTIONS = ("opengl", "d3d", "vulkan")
TEXTURE_ORIGINS = ("bottom-left", "top-left")
DEFAULT_TEXTURE_ORIGIN = {"opengl": "bottom-left", "d3d": "top-left", "vulkan": "top-left"}
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


def texture_from_clip(convention: str, texture_origin: str | None = None) -> np.ndarray:
    """The bias matrix S: that convention's clip space -> texture (s, t, depth) in [0, 1] after the divide.

    opengl: S = [[.5,0,0,.5],[0,.5,0,.5],[0,0,.5,.5],[0,0,0,1]] (Everitt et al. 2001, "Hardware Shadow Mapping");
            t = 0 at the bottom of the map, depth = (z + 1)/2.
    d3d:    t = 0.5 - 0.5 y (texture origin top-left, v flipped); depth z passes through ([0, 1]).
    vulkan: NDC y already points down, so t = 0.5 + 0.5 y (origin top-left); depth passes through.
    texture_origin ("bottom-left" / "top-left") overrides the convention's own origin (an engine that
    renders its maps upside down on a top-left API, as Unity does, samples them bottom-left; Filament's
    shadow texture matrix is bottom-left too and its shaders flip v through uvToRenderTargetUV on Metal,
    Vulkan and WebGPU, docs/engines.md): t = 0 on the map's row at NDC y = -1 (bottom-left) or y = +1
    (top-left), in the convention's NDC.
    """
    _check(convention)
    origin = texture_origin or DEFAULT_TEXTURE_ORIGIN[convention]
    if origin not in TEXTURE_ORIGINS:
        raise ValueError(f"texture_origin must be one of {', '.join(TEXTURE_ORIGINS)}, got {origin!r}")
    y_up = convention != "vulkan"  # NDC y points up (Vulkan's points down)
    sy = 0.5 if (origin == "bottom-left") == y_up else -0.5
    z_row = [0, 0, 0.5, 0.5] if convention == "opengl" else [0, 0, 1.0, 0]
    return np.array([[0.5, 0, 0, 0.5], [0, sy, 0, 0.5], z_row, [0, 0, 0, 1.0]], dtype=np.float64)


def projection_for(proj_canonical: np.ndarray, convention: str, reversed_z: bool = False) -> np.ndarray:
    """The projection matrix in the engine's convention: C · P."""
    return clip_from_canonical(convention, reversed_z) @ _mat4(proj_canonical, "projection")


def texture_matrix(view: np.ndarray, proj_canonical: np.ndarray, convention: str,
                   reversed_z: bool = False, texture_origin: str | None = None) -> np.ndarray:
    """S · C · P · V (Everitt et al. 2001 "Hardware Shadow Mapping": S · P_light · V_light, P in the given
    convention): world -> texture. Divide the result by its w to get (s, t, depth) in [0, 1]
    (textureProj / tex2Dproj does this); with reversed_z the depth is 1 at the near plane, 0 at the far."""
    return (texture_from_clip(convention, texture_origin) @ projection_for(proj_canonical, convention, reversed_z)
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
                    stage_to_world: np.ndarray | None = None, reversed_z: bool = False,
                    engine: str | None = None) -> dict:
    """The matrices an engine receives, each a flat 16-list in `layout`:
    view_matrix (world, stage or engine frame -> light view), projection_matrix (light view -> the
    convention's clip), texture_matrix (the same input frame -> texture, S · C · P · V). frame "stage"
    applies to_stage_frame to the view and texture matrices; stage_to_world None there means the stage is
    already the world frame (Y up, meters). `engine` (ENGINE_PRESETS) sets convention, layout,
    reversed_z and the texture origin from its row (the arguments for them are ignored), and the
    matrices take points in that engine's world frame and units: see engine_matrices."""
    if engine is not None:
        return engine_matrices(view, proj_canonical, engine)
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
# Engine presets (output.engine): one row per engine, each naming the documentation it follows.
#   convention      the clip rule of the light pass on the GPU (clip_from_canonical) and of the texture
#                   chain (texture_from_clip)
#   reversed_z      the stored depth is 1 at the light's near plane and 0 at its far plane
#   texture_origin  where t = 0 is in the map as the engine samples it
#   projection      what projection_matrix holds: "clip" = C · P, the GPU's clip matrix, consistent with
#                   the texture matrix; "opengl" = the OpenGL-convention projection (clip z in [-w, w],
#                   not reversed) that the engine's own API takes and converts to its GPU clip itself
#                   (Unity's Camera/CommandBuffer matrices, Filament's Camera::setCustomProjection)
#   layout          memory order of the 16 numbers (the matrices act on column vectors, M @ v)
#   axes            the engine's world axes in shadowopt's world frame (right-handed, +Y up, metres):
#                   engine coordinate i = sign * world coordinate, e.g. ("x", "y", "-z"): x_e = x,
#                   y_e = y, z_e = -z (solvers.frames.engine_from_world)
#   metres_per_unit the engine's length unit
#   view            the light view space the view matrix maps to: "-z" (right-handed, the light looks
#                   down -Z, OpenGL's eye space) or "+z" (left-handed, it looks down +Z: Direct3D-style
#                   eye space, as Unreal's view matrices)
# A point X_e in the engine's frame maps to the same texel and depth as the world point it is:
#   view_e = U · F · V · E^-1, projection_e = C · P · F · U^-1 (or P · F · U^-1), texture_e = S · C · P · V · E^-1,
# E = engine_from_world, F = diag(1, 1, -1, 1) for view "+z" (else identity), U = diag(1/m, 1/m, 1/m, 1) with
# m = metres_per_unit (the light view space in engine units, so the view matrix is rigid there).
# ---------------------------------------------------------------------------------------------------
ENGINES = ("opengl", "d3d", "vulkan", "unity", "unreal", "godot", "three", "bevy", "filament", "babylon")
_RH_Y_UP_M = {"axes": ("x", "y", "z"), "metres_per_unit": 1.0, "view": "-z", "layout": "column_major"}
ENGINE_PRESETS: dict[str, dict] = {
    "opengl": {**_RH_Y_UP_M, "convention": "opengl", "reversed_z": False, "texture_origin": "bottom-left",
               "projection": "clip",
               "docs": "OpenGL 4.6 core specification 13.8 (clip z in [-w, w], window z = (z_ndc + 1)/2 with "
                       "glDepthRange(0, 1)); glUniformMatrix4fv (column-major with transpose GL_FALSE)"},
    "d3d": {**_RH_Y_UP_M, "convention": "d3d", "reversed_z": False, "texture_origin": "top-left",
            "projection": "clip",
            "docs": "Direct3D 11 rasterizer and viewport (NDC z in [0, 1], texture origin top-left); HLSL "
                    "constant buffers pack float4x4 column_major by default (mul(M, v))"},
    "vulkan": {**_RH_Y_UP_M, "convention": "vulkan", "reversed_z": False, "texture_origin": "top-left",
               "projection": "clip",
               "docs": "Vulkan 1.3 specification, Coordinate Transformations (NDC y down, z in [0, 1]); "
                       "GLSL mat4 is column-major"},
    "unity": {"convention": "opengl", "reversed_z": True, "texture_origin": "bottom-left",
              "projection": "opengl", "layout": "column_major", "axes": ("x", "y", "-z"),
              "metres_per_unit": 1.0, "view": "-z",
              "docs": "Unity Manual, Platform-specific rendering differences (reversed Z on Direct3D 11/12, "
                      "Vulkan, Metal and consoles, the platforms this row describes; OpenGL and GLES keep "
                      "[-1, 1] depth, not reversed; Unity flips the projection when rendering into a render "
                      "texture on UNITY_UV_STARTS_AT_TOP platforms, so maps sample with v = 0 at the bottom); "
                      "Scripting API Camera.worldToCameraMatrix (camera space is OpenGL's, forward -Z) and "
                      "GL.GetGPUProjectionMatrix (projections follow OpenGL and are converted per platform); "
                      "URP ShadowUtils.GetShadowTransform (negates the projection's z row for "
                      "SystemInfo.usesReversedZBuffer, then the [-1, 1] -> [0, 1] scale and bias); Unity's USD "
                      "package converts right-handed stages by z -> -z (UnityTypeConverter.ChangeBasis); "
                      "Matrix4x4 stores its elements column-major (m00, m10, m20, m30, m01, ...)"},
    "unreal": {"convention": "d3d", "reversed_z": True, "texture_origin": "top-left", "projection": "clip",
               "layout": "column_major", "axes": ("x", "z", "y"), "metres_per_unit": 0.01, "view": "+z",
               "docs": "Unreal Engine coordinate system (left-handed, +Z up, 1 unit = 1 cm); reversed-Z "
                       "projections (FReversedZOrthoMatrix, FReversedZPerspectiveMatrix: near 1, far 0 in "
                       "NDC [0, 1]); FMatrix multiplies row vectors (v' = v * M, M.M[row][col]), so the "
                       "column-major list of this column-vector matrix is FMatrix's memory order; the USD "
                       "importer maps a Y-up stage by swapping Y and Z and scaling metres to centimetres "
                       "(UsdToUnreal::ConvertVector)"},
    "godot": {**_RH_Y_UP_M, "convention": "vulkan", "reversed_z": True, "texture_origin": "top-left",
              "projection": "clip",
              "docs": "Forward+ and Mobile renderers (not Compatibility). Godot 4 docs: Projection "
                      "(OpenGL-convention 4x4, columns x, y, z, w) and "
                      "create_depth_correction (the renderer maps it to [0, 1] depth with y flipped); Godot 4.3 "
                      "\"Introducing Reverse Z\" (depth 1 near, 0 far); Advanced post-processing (shader NDC "
                      "= SCREEN_UV * 2 - 1 with that depth): right-handed, +Y up, metres"},
    "three": {**_RH_Y_UP_M, "convention": "opengl", "reversed_z": False, "texture_origin": "bottom-left",
              "projection": "clip",
              "docs": "three.js docs: Matrix4 (elements are column-major), LightShadow.updateMatrices "
                      "(shadow.matrix = [0.5 scale and bias] · camera.projectionMatrix · "
                      "camera.matrixWorldInverse), WebGLRenderer without reversedDepthBuffer: clip z in "
                      "[-1, 1]; right-handed, +Y up, metres (WebGPURenderer: the d3d convention, "
                      "docs/engines.md)"},
    "bevy": {**_RH_Y_UP_M, "convention": "d3d", "reversed_z": True, "texture_origin": "top-left",
             "projection": "clip",
             "docs": "Bevy bevy_pbr: Cascade {world_from_cascade, clip_from_cascade, clip_from_world} from "
                     "calculate_cascade (right-handed orthographic with reverse Z: near 1, far 0), shadow "
                     "pipeline depth compare GreaterEqual, shadows.wgsl (uv = ndc.xy * (0.5, -0.5) + 0.5: "
                     "origin top-left); wgpu NDC z in [0, 1], y up; glam Mat4 is column-major"},
    "filament": {**_RH_Y_UP_M, "convention": "opengl", "reversed_z": True, "texture_origin": "bottom-left",
                 "projection": "opengl",
                 "docs": "Filament Camera::setCustomProjection (OpenGL-convention projection; the renderer "
                         "converts clip z to its inverted [1, 0] range); ShadowMap::getTextureCoordsMapping "
                         "(NDC [-1, 1] -> texture [0, 1], depth mapped to [1, 0], v = 0.5 y + 0.5 on OpenGL; "
                         "on Metal, Vulkan and WebGPU textureSpaceFlipped folds v -> 1 - v in, the shader's "
                         "uvToRenderTargetUV); "
                         "filament::math::mat4f is column-major; right-handed, +Y up, metres"},
    # Babylon.js 9.35 (@babylonjs/core), WebGL2 engine; every file named is in that package
    "babylon": {"convention": "opengl", "reversed_z": False, "texture_origin": "bottom-left", "projection": "clip",
                "layout": "column_major", "axes": ("-x", "y", "z"), "metres_per_unit": 1.0, "view": "+z",
                "docs": "Babylon.js 9.35 (@babylonjs/core), WebGL2 engine: left-handed, +Y up; a right-handed asset "
                        "is placed as Babylon's glTF loader places it (its __root__ node turned 180 degrees about Y "
                        "and scaled (1, 1, -1): x -> -x); clip z in [-1, 1] (Engines/abstractEngine.pure.js "
                        "isNDCHalfZRange = false, useReverseDepthBuffer = false; only the WebGPU engine takes "
                        "[0, 1]); light views by Matrix.LookAtLHToRef (Maths/math.vector.pure.js: the light looks "
                        "down +Z); the lookup uv = 0.5 clip.xy / w + 0.5 (Shaders/ShadersInclude/"
                        "shadowsFragmentFunctions.js computeShadow: rows from the bottom); Matrix.m and "
                        "Matrix.FromArray hold the 16 numbers with the translation in m[12..14], the column-major "
                        "order of these column-vector matrices"},
}
_FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])


def _preset(engine: str) -> dict:
    if engine not in ENGINE_PRESETS:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    return ENGINE_PRESETS[engine]


def engine_matrices(view: np.ndarray, proj_canonical: np.ndarray, engine: str) -> dict:
    """The matrices for an engine preset, acting on points in the engine's world frame and units:
    view_e = U · F · V · E^-1, projection_e = C · P · F · U^-1 ("clip") or P · F · U^-1 ("opengl"),
    texture_e = S · C · P · V · E^-1 (E = solvers.frames.engine_from_world, F the view-space mirror of a
    left-handed view, U the unit scale of view space; the table's comment above)."""
    p = _preset(engine)
    conv, rev, layout = p["convention"], p["reversed_z"], p["layout"]
    mpu = float(p["metres_per_unit"])
    w_from_e = world_from_engine(p["axes"], mpu)
    f = _FLIP_Z if p["view"] == "+z" else np.eye(4)
    # the light view in engine units too (a rigid view matrix, as engines build them; its depth in the
    # same unit as the solution's light_depth and depth.linear near/far): U = diag(1/mpu) on view space
    u, u_inv = np.diag([1 / mpu, 1 / mpu, 1 / mpu, 1.0]), np.diag([mpu, mpu, mpu, 1.0])
    P = _mat4(proj_canonical, "projection")
    V = _mat4(view, "view")
    proj = (projection_for(P, conv, rev) if p["projection"] == "clip" else P) @ f @ u_inv
    tex = texture_matrix(V, P, conv, rev, p["texture_origin"]) @ w_from_e
    return {"view_matrix": to_layout(u @ f @ V @ w_from_e, layout), "projection_matrix": to_layout(proj, layout),
            "texture_matrix": to_layout(tex, layout)}


def _axis_name(v: np.ndarray) -> str:
    k = int(np.argmax(np.abs(v)))
    return ("+" if v[k] > 0 else "-") + "XYZ"[k]


def _unit_name(metres_per_unit: float) -> str:
    return {1.0: "metres", 0.01: "centimetres"}.get(float(metres_per_unit), f"{metres_per_unit:g} metres")


def output_frame(output: dict, stage_to_world: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(world -> output-frame points 4x4, metres per unit of the solution's lengths) for an output spec:
    the world frame (identity, 1), the stage's own frame (output.frame "stage": inv(stage_to_world), and
    lengths still in metres, 1) or an engine preset's frame and unit (solvers.frames.engine_from_world)."""
    if output.get("engine"):
        p = _preset(output["engine"])
        return engine_from_world(p["axes"], p["metres_per_unit"]), float(p["metres_per_unit"])
    if output.get("frame", "world") == "stage" and stage_to_world is not None:
        # the view and texture matrices take stage points; the lengths stay in metres and the light view
        # space too (docs/engine-integration.md)
        return np.linalg.inv(_mat4(stage_to_world, "stage_to_world")), 1.0
    return np.eye(4), 1.0


def convention_info(output: dict, stage_to_world: np.ndarray | None = None) -> dict:
    """What the matrices and lengths of a solution are expressed in (the solution's `convention`): api
    (clip convention), layout, frame (world, stage or engine), engine, reversed_z, texture_origin,
    projection (what projection_matrix holds, see ENGINE_PRESETS), handedness, up_axis, view_forward
    (the light view axis the light looks along), length_unit and metres_per_unit (the unit of the light
    view space and of every length of the solution an engine uses: split, blend_band, light_depth, warp.n
    and the depth block's normal_offset, near and far; with frame "stage" the matrices take stage points
    and these stay in metres)."""
    engine = output.get("engine")
    E, mpu = output_frame(output, stage_to_world)
    if engine:
        p = _preset(engine)
        conv, layout, rev, origin = p["convention"], p["layout"], p["reversed_z"], p["texture_origin"]
        frame, projection, forward = "engine", p["projection"], p["view"].upper()
    else:
        conv = output.get("convention", "opengl")
        layout, rev = output.get("layout", "column_major"), bool(output.get("reversed_z", False))
        origin, projection, forward = DEFAULT_TEXTURE_ORIGIN[conv], "clip", "-Z"
        frame = output.get("frame", "world")
    R = E[:3, :3]
    return {"api": conv, "layout": layout, "frame": frame, "engine": engine, "reversed_z": rev,
            "texture_origin": origin, "projection": projection,
            "handedness": "right" if np.linalg.det(R) > 0 else "left", "up_axis": _axis_name(R @ [0.0, 1.0, 0.0]),
            "view_forward": forward, "length_unit": _unit_name(mpu), "metres_per_unit": mpu}


def preset_conflicts(engine: str, given: dict) -> list[str]:
    """The fields of an output spec that contradict the engine preset: `given` holds only the fields the
    request set explicitly (convention, layout, reversed_z, frame). One message per field, naming both.

    frame "world" (the field's default, which every dumped-and-revalidated rig and the client's rig JSON
    carry) is accepted with every preset: the preset's own frame replaces it. Only "stage" contradicts
    a preset (the matrices cannot take both the stage's and the engine's coordinates)."""
    if engine not in ENGINE_PRESETS:
        return [f"unknown output.engine {engine!r} (known: {', '.join(ENGINES)})"]
    p = ENGINE_PRESETS[engine]
    out = []
    for key in ("convention", "layout", "reversed_z"):
        if key in given and given[key] != p[key]:
            out.append(f"the preset output.engine = {engine!r} sets output.{key} to {p[key]!r}, but it is "
                       f"{given[key]!r}: remove output.{key} (the preset sets it)")
    if given.get("frame") == "stage":
        out.append(f"the preset output.engine = {engine!r} sets the frame (the engine's world frame and "
                   f"units), but output.frame is 'stage': remove output.frame (the preset sets it)")
    return out
