"""Render a solution the way an engine does, with the shader listings of docs/engine-integration.md, in real
OpenGL (Mesa llvmpipe through EGL): the light pass of every map into a 32-bit float depth buffer, then the
camera view with the document's receiver lookup. The test (tests/test_engine_listing.py) and the engine
benchmark (service/bench/engine.py) compare its per-pixel shadow with exact ray-traced visibility.

Run it in its own process (`python -m shadowopt.renderers.gl_listing IN.npz OUT.npz`): Mesa loads LLVM 15,
and a Dr.Jit in the same process would reuse that library and crash. This module imports nothing but the
standard library, NumPy and moderngl for that reason (HLSL goes through glslangValidator and spirv-cross,
command-line tools, when asked for).

IN.npz: `vertices` (V, 3) float32 (already re-centred: every matrix below acts on these points), `faces`
(F, 3) uint32, `spec` a JSON string:

    {"camera": {"view": M, "projection": M, "resolution": [w, h]},      # OpenGL clip space, row 0 = top
     "sources": {"glsl": {piece: text}, "hlsl": {piece: text},           # the document's listings by tag
                 "c": {"light-pass-state-gl" | "-d3d11" | "-vulkan": text}},
     "jobs": [{"name": str, "language": "glsl" | "hlsl",
               "clip": "opengl" | "d3d" | "vulkan" | "reversed_z",       # how the light pass is rasterized
               "state": "gl" | "d3d11" | "vulkan",                       # the light pass's rasterizer state block
               "keep_maps": bool (optional),                             # also return the stored depth maps
               "to_light": [x, y, z] | [x, y, z, 1],                     # towards the sun | a local light's position
               "lookup": "cascades" | "local" (optional),                # shadowVisibility | localShadowVisibility
               "faces": bool (optional),                                 # the maps are a point light's faces
               "maps": [{"view_matrix": M, "view_projection": M, "texture_matrix": M,
                         "resolution": [w, h], "split": [a, b], "blend_band": [a, b] | null,
                         "depth": {"mode": "hardware" | "linear", "constant", "slope", "normal_offset",
                                   "near", "far", "slope_scaled", "slope_clamp"}}]}]}

M: 16 numbers, row-major, acting on column vectors. `clip`: opengl = the default clip control (z in
[-w, w], window depth (z_ndc + 1)/2), d3d = glClipControl(GL_UPPER_LEFT, GL_ZERO_TO_ONE) (Direct3D's
clip space and texture origin), vulkan = glClipControl(GL_LOWER_LEFT, GL_ZERO_TO_ONE) (Vulkan's NDC y
points down and its framebuffer row 0 is at NDC y = -1, which is OpenGL's lower-left row order), reversed_z =
d3d with the depth test GREATER and the map cleared to 0. `state`: the document's rasterizer-state block
for the light pass (light_pass_state): "gl" executed call by call, "d3d11" / "vulkan" read field by field
and set as the OpenGL equivalent (the same slope-scaled bias: OpenGL 4.6 §14.6.5, D3D11 depth bias,
Vulkan depthBias*), with k, m the map's slope_scaled, slope_clamp for hardware and 0 for linear (whose
shader adds the offset itself).
OUT.npz: `hit` (h, w) bool, `position` (h, w, 3) float32 (re-centred), `view_depth` (h, w) float32, and per
job `shadow_<name>` (h, w) float32 visibility in [0, 1] (1 lit), row 0 at the top as the camera sees it, and
with keep_maps `stored_<name>` (K, map h, map w) float32, the light passes' depth buffers as they lie in memory;
`renderer` the GL_RENDERER string.
"""
from __future__ import annotations

import ctypes
import json
import os
import re
import subprocess
import sys
import tempfile

import numpy as np

GL_DEPTH_CLAMP = 0x864F
GL_CULL_FACE = 0x0B44
GL_POLYGON_OFFSET_FILL = 0x8037
GL_LESS, GL_GREATER = 0x0201, 0x0204
GL_TEXTURE_2D = 0x0DE1
GL_DEPTH_COMPONENT = 0x1902
GL_DEPTH_COMPONENT32F = 0x8CAC
GL_FLOAT = 0x1406
GL_TEXTURE_DEPTH_SIZE = 0x884A
GL_LOWER_LEFT, GL_UPPER_LEFT = 0x8CA1, 0x8CA2
GL_NEGATIVE_ONE_TO_ONE, GL_ZERO_TO_ONE = 0x935E, 0x935F
MAX_CASCADES = 6  # the listing's array size (4 cascades or 6 cube faces)
# glClipControl(origin, depth) per convention (OpenGL 4.5 §13.7): Direct3D's clip z in [0, w] and row 0 at
# NDC y = +1 (upper left); Vulkan's z in [0, w] with its y already pointing down (lower-left row order).
CLIP_CONTROL = {"opengl": (GL_LOWER_LEFT, GL_NEGATIVE_ONE_TO_ONE), "d3d": (GL_UPPER_LEFT, GL_ZERO_TO_ONE),
                "vulkan": (GL_LOWER_LEFT, GL_ZERO_TO_ONE), "reversed_z": (GL_UPPER_LEFT, GL_ZERO_TO_ONE)}

# The harness around the document's pieces (not part of the document): the camera pass.
CAMERA_VERTEX = """#version 330 core
uniform mat4 uCamViewProj;
uniform mat4 uCamView;
in vec3 in_pos;
in vec3 in_normal;
out vec3 i_world;
flat out vec3 i_normal;
out float i_viewDepth;
void main() {
    i_world = in_pos;
    i_normal = in_normal;
    i_viewDepth = -(uCamView * vec4(in_pos, 1.0)).z;   // distance along the camera's forward axis
    gl_Position = uCamViewProj * vec4(in_pos, 1.0);
}
"""
CAMERA_FRAGMENT_GLSL = """#version 330 core
{lookup}
in vec3 i_world;
flat in vec3 i_normal;
in float i_viewDepth;
layout(location = 0) out vec4 o_shadow;
layout(location = 1) out vec4 o_world;
void main() {{
    o_shadow = vec4({entry}(i_world, i_normal, i_viewDepth), i_viewDepth, 1.0, 1.0);
    o_world = vec4(i_world, 1.0);
}}
"""
CAMERA_FRAGMENT_HLSL = """{lookup}
struct PSIn {{
    float4 pos : SV_Position;
    float3 world : TEXCOORD0;
    nointerpolation float3 normal : TEXCOORD1;
    float viewDepth : TEXCOORD2;
}};
struct PSOut {{ float4 shadow : SV_Target0; float4 world : SV_Target1; }};
PSOut main(PSIn i) {{
    PSOut o;
    o.shadow = float4({entry}(i.world, i.normal, i.viewDepth), i.viewDepth, 1.0, 1.0);
    o.world = float4(i.world, 1.0);
    return o;
}}
"""


def _gl_function(name: str, restype, *argtypes):
    """A GL entry point through EGL's eglGetProcAddress (Mesa returns core functions too)."""
    egl = ctypes.CDLL("libEGL.so.1")
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    addr = egl.eglGetProcAddress(name.encode())
    if not addr:
        raise RuntimeError(f"eglGetProcAddress({name}) returned NULL")
    return ctypes.CFUNCTYPE(restype, *argtypes)(addr)


class _GL:
    def __init__(self, extensions=(), version_code: int = 0):
        u = ctypes.c_uint
        f = ctypes.c_float
        self.clip_control = _gl_function("glClipControl", None, u, u)
        self.enable = _gl_function("glEnable", None, u)
        self.disable = _gl_function("glDisable", None, u)
        self.depth_func = _gl_function("glDepthFunc", None, u)
        if version_code < 460 and not {"GL_ARB_polygon_offset_clamp", "GL_EXT_polygon_offset_clamp"} & set(extensions):
            raise RuntimeError("this OpenGL has no glPolygonOffsetClamp (OpenGL 4.6, ARB_polygon_offset_clamp or "
                               "EXT_polygon_offset_clamp): the light pass's clamped slope-scaled bias needs it")
        self.polygon_offset_clamp = _gl_function("glPolygonOffsetClamp", None, f, f, f)
        # The calls the document's OpenGL state block may make, by name (light_pass_state).
        self.calls = {"glEnable": self.enable, "glDisable": self.disable, "glDepthFunc": self.depth_func,
                      "glPolygonOffsetClamp": self.polygon_offset_clamp}
        self.bind_texture = _gl_function("glBindTexture", None, u, u)
        self.tex_image_2d = _gl_function("glTexImage2D", None, u, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                                         ctypes.c_int, ctypes.c_int, u, u, ctypes.c_void_p)
        self.tex_level_parameter = _gl_function("glGetTexLevelParameteriv", None, u, ctypes.c_int, u,
                                                ctypes.POINTER(ctypes.c_int))


GL_ENUMS = {"GL_DEPTH_CLAMP": GL_DEPTH_CLAMP, "GL_CULL_FACE": GL_CULL_FACE,
            "GL_POLYGON_OFFSET_FILL": GL_POLYGON_OFFSET_FILL, "GL_LESS": GL_LESS, "GL_GREATER": GL_GREATER}
C_BOOLS = {"TRUE": True, "FALSE": False, "VK_TRUE": True, "VK_FALSE": False}


def _c_value(expr: str, env: dict):
    """The value of one expression of a state block: a number (0.0f), k / m / reversedZ from `env`,
    `-x`, `reversedZ ? a : b`, a GL enum (its number), TRUE / FALSE, or another enum name (as a string)."""
    e = expr.strip()
    tern = re.fullmatch(r"(\w+)\s*\?\s*([^:]+?)\s*:\s*(.+)", e)
    if tern:
        return _c_value(tern[2] if _c_value(tern[1], env) else tern[3], env)
    if e.startswith("-"):
        return -_c_value(e[1:], env)
    if re.fullmatch(r"\d+(\.\d*)?([eE][-+]?\d+)?f?", e):
        return float(e.rstrip("f")) if ("." in e or "e" in e.lower()) else int(e)
    if e in env:
        return env[e]
    if e in GL_ENUMS:
        return GL_ENUMS[e]
    if e in C_BOOLS:
        return C_BOOLS[e]
    if re.fullmatch(r"[A-Z][A-Z0-9_]+", e):
        return e
    raise ValueError(f"the state block's expression {expr!r} is not one the harness reads")


def parse_state(text: str, env: dict) -> tuple[list, dict]:
    """A rasterizer-state block of the document as ([(gl function, [args])], {field: value}): statements
    `glName(args);`, `TYPE rs = {...};` and `rs.Field = value;`, `//` comments dropped."""
    calls, fields = [], {}
    body = re.sub(r"//[^\n]*", "", text)
    for stmt in (s.strip() for s in body.split(";")):
        if not stmt:
            continue
        call = re.fullmatch(r"(gl\w+)\((.*)\)", stmt, re.S)
        decl = re.fullmatch(r"(\w+)\s+(\w+)\s*=\s*\{(.*)\}", stmt, re.S)
        field = re.fullmatch(r"(\w+)\.(\w+)\s*=\s*(.+)", stmt, re.S)
        if call:
            calls.append((call[1], [_c_value(a, env) for a in call[2].split(",")]))
        elif decl:
            fields["type"] = decl[1]
        elif field:
            fields[field[2]] = _c_value(field[3], env)
        else:
            raise ValueError(f"the state block's statement {stmt!r} is not one the harness reads")
    return calls, fields


def _require(fields: dict, key: str, allowed, api: str):
    if key not in fields:
        raise ValueError(f"the {api} state block sets no {key}")
    if fields[key] not in allowed:
        raise ValueError(f"the harness emulates {api} {key} = {' or '.join(map(str, allowed))} only, "
                         f"the block sets {fields[key]!r}")
    return fields.pop(key)


def light_pass_state(api: str, text: str, k: float, m: float, reversed_z: bool) -> list:
    """The OpenGL calls [(name, args)] that set the document's light-pass rasterizer state `text` of `api`
    (gl: its own calls; d3d11: D3D11_RASTERIZER_DESC; vulkan: VkPipelineRasterizationStateCreateInfo),
    with k, m, reversedZ bound. D3D11's Bias = DepthBias r + SlopeScaledDepthBias MaxDepthSlope, clamped by
    DepthBiasClamp (0: none), and Vulkan's depthBias* are OpenGL 4.6 §14.6.5's polygon offset with
    glPolygonOffsetClamp (clamp 0: none); the integer / constant bias is left unemulated (must be 0)."""
    env = {"k": float(k), "m": float(m), "reversedZ": bool(reversed_z)}
    calls, f = parse_state(text, env)
    if api == "gl":
        if f:
            raise ValueError(f"the OpenGL state block assigns fields {sorted(f)}")
        return calls
    if calls:
        raise ValueError(f"the {api} state block makes calls {[c for c, _ in calls]}")
    out = []
    if api == "d3d11":
        _require(f, "type", ("D3D11_RASTERIZER_DESC",), api)
        _require(f, "FillMode", ("D3D11_FILL_SOLID",), api)
        _require(f, "CullMode", ("D3D11_CULL_NONE",), api)
        clip = _require(f, "DepthClipEnable", (True, False), api)
        _require(f, "DepthBias", (0,), api)
        slope, clamp, bias = f.pop("SlopeScaledDepthBias", 0.0), f.pop("DepthBiasClamp", 0.0), True
    elif api == "vulkan":
        _require(f, "type", ("VkPipelineRasterizationStateCreateInfo",), api)
        _require(f, "polygonMode", ("VK_POLYGON_MODE_FILL",), api)
        _require(f, "cullMode", ("VK_CULL_MODE_NONE",), api)
        clip = not _require(f, "depthClampEnable", (True, False), api)
        bias = _require(f, "depthBiasEnable", (True, False), api)
        _require(f, "depthBiasConstantFactor", (0, 0.0), api)
        slope, clamp = f.pop("depthBiasSlopeFactor", 0.0), f.pop("depthBiasClamp", 0.0)
        f.pop("lineWidth", None)
    else:
        raise ValueError(f"state must be gl, d3d11 or vulkan, got {api!r}")
    if f:
        raise ValueError(f"the {api} state block sets fields the harness does not emulate: {sorted(f)}")
    out.append(("glDisable", [GL_CULL_FACE]))
    out.append(("glDisable" if clip else "glEnable", [GL_DEPTH_CLAMP]))
    if bias:
        out += [("glEnable", [GL_POLYGON_OFFSET_FILL]), ("glPolygonOffsetClamp", [float(slope), 0.0, float(clamp)])]
    return out


def hlsl_to_glsl(source: str, stage: str, entry: str, inputs=(), outputs=()) -> str:
    """HLSL -> SPIR-V (glslangValidator -D) -> GLSL 330 (spirv-cross). `stage`: vert or frag; `inputs` /
    `outputs`: names for the stage's interface variables by location (0, 1, ...), so that a vertex and a
    fragment shader cross-compiled apart match by name as GLSL 330 links them."""
    with tempfile.TemporaryDirectory() as tmp:
        src, spv = os.path.join(tmp, f"s.{stage}.hlsl"), os.path.join(tmp, "s.spv")
        with open(src, "w") as f:
            f.write(source)
        p = subprocess.run(["glslangValidator", "-D", "-V", "-S", stage, "-e", entry, "-o", spv, src],
                           capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"glslangValidator failed:\n{p.stdout}{p.stderr}")
        args = ["spirv-cross", spv, "--version", "330", "--no-es"]
        for kind, names in (("in", inputs), ("out", outputs)):
            for loc, name in enumerate(names):
                args += ["--rename-interface-variable", kind, str(loc), name]
        p = subprocess.run(args, capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"spirv-cross failed:\n{p.stdout}{p.stderr}")
        return p.stdout


def _mat(flat) -> np.ndarray:
    return np.asarray(flat, dtype=np.float64).reshape(4, 4)


def _gl_mat(m: np.ndarray) -> bytes:
    """Column-major float32 bytes (GLSL mat4 storage, glUniformMatrix4fv(transpose = false))."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float32).T).tobytes()


def pack_uniforms(maps: list[dict], to_light, reversed_z: bool, faces: bool = False) -> bytes:
    """The document's `ShadowMaps` block (std140 GLSL = HLSL cbuffer packing: only mat4 / vec4 members).
    to_light: the unit vector towards a directional light (w = 0), or [x, y, z, 1] a local light's position;
    faces: the maps are a point light's cube faces (uParams.z = 1)."""
    k = len(maps)
    if not 1 <= k <= MAX_CASCADES:
        raise ValueError(f"the listing takes 1 to {MAX_CASCADES} maps, got {k}")
    tex = np.zeros((MAX_CASCADES, 4, 4))
    view = np.zeros((MAX_CASCADES, 4, 4))
    depth = np.zeros((MAX_CASCADES, 4))
    linear = np.zeros((MAX_CASCADES, 4))
    cascade = np.zeros((MAX_CASCADES, 4))
    for i, m in enumerate(maps):
        tex[i], view[i] = _mat(m["texture_matrix"]), _mat(m["view_matrix"])
        d = m["depth"]
        depth[i] = [d["constant"], d["slope"], d["normal_offset"], 1.0 if d["mode"] == "linear" else 0.0]
        linear[i] = [d.get("near", 0.0), d.get("far", 1.0), *m["resolution"]]
        a, b = m["split"]
        band = m.get("blend_band") or [b, b]
        cascade[i] = [a, b, band[0], band[1]]
    parts = [_gl_mat(x) for x in tex] + [_gl_mat(x) for x in view]
    parts += [np.asarray(x, dtype=np.float32).tobytes() for x in (depth, linear, cascade)]
    parts.append(np.array([*to_light, 0.0][:4], dtype=np.float32).tobytes())
    parts.append(np.array([k, 1.0 if reversed_z else 0.0, 1.0 if faces else 0.0, 0.0], dtype=np.float32).tobytes())
    return b"".join(parts)


def pack_light_pass(m: dict, reversed_z: bool) -> dict:
    """The light pass's uniforms: GLSL names -> values; the HLSL `LightPass` cbuffer as bytes."""
    vp, view = _mat(m["view_projection"]), _mat(m["view_matrix"])
    d = m["depth"]
    linear = (float(d.get("near", 0.0)), float(d.get("far", 1.0)), 1.0 if reversed_z else 0.0)
    offset = (float(d["slope_scaled"]), float(d["slope_clamp"]))
    block = (_gl_mat(vp) + _gl_mat(view) + np.array([*linear, 0.0], dtype=np.float32).tobytes()
             + np.array([*offset, 0.0, 0.0], dtype=np.float32).tobytes())
    return {"uLightViewProj": _gl_mat(vp), "uLightView": _gl_mat(view), "uLinearDepth": linear,
            "uLinearOffset": offset, "block": block}


class Harness:
    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import moderngl  # lazy: OpenGL only in the subprocess that draws (this module's parsers run beside Dr.Jit)

        self.mgl = moderngl
        self.ctx = moderngl.create_standalone_context(backend="egl", require=450)
        self.gl = _GL(self.ctx.extensions, self.ctx.version_code)
        v = np.asarray(vertices, dtype=np.float32)[np.asarray(faces, dtype=np.int64)]  # (F, 3, 3), unindexed
        n = np.cross(v[:, 1].astype(np.float64) - v[:, 0], v[:, 2].astype(np.float64) - v[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)  # geometric (face) normal
        self.vbo = self.ctx.buffer(np.ascontiguousarray(v.reshape(-1, 3)).tobytes())
        self.nbo = self.ctx.buffer(np.ascontiguousarray(np.repeat(n[:, None], 3, axis=1).reshape(-1, 3),
                                                        dtype=np.float32).tobytes())
        self.programs = {}

    def release(self):
        self.ctx.release()

    def depth_texture(self, w: int, h: int):
        """A moderngl depth texture re-specified as GL_DEPTH_COMPONENT32F (a D32F depth buffer)."""
        tex = self.ctx.depth_texture((w, h))
        self.gl.bind_texture(GL_TEXTURE_2D, tex.glo)
        self.gl.tex_image_2d(GL_TEXTURE_2D, 0, GL_DEPTH_COMPONENT32F, w, h, 0, GL_DEPTH_COMPONENT, GL_FLOAT, None)
        bits = ctypes.c_int(0)
        self.gl.tex_level_parameter(GL_TEXTURE_2D, 0, GL_TEXTURE_DEPTH_SIZE, ctypes.byref(bits))
        self.gl.bind_texture(GL_TEXTURE_2D, 0)
        if bits.value != 32:
            raise RuntimeError(f"the depth texture has {bits.value} bits, not a D32F one")
        return tex

    def program(self, key, vertex: str, fragment: str | None):
        if key not in self.programs:
            self.programs[key] = self.ctx.program(vertex_shader=vertex, fragment_shader=fragment)
        return self.programs[key]

    def _members(self, prog, kind):
        return [k for k in prog if isinstance(prog[k], kind)]

    def _vao(self, prog, with_normal: bool):
        attrs = self._members(prog, self.mgl.Attribute)
        position = [a for a in attrs if a != "in_normal"]
        if len(position) != 1:
            raise RuntimeError(f"expected one vertex position input, found {attrs}")
        content = [(self.vbo, "3f", position[0])]
        if with_normal:
            content.append((self.nbo, "3f", "in_normal"))
        return self.ctx.vertex_array(prog, content)

    def _bind_block(self, prog, data: bytes, binding: int):
        blocks = self._members(prog, self.mgl.UniformBlock)
        if len(blocks) > 1:
            raise RuntimeError(f"expected at most one uniform block, found {blocks}")
        if not blocks:
            return None
        ubo = self.ctx.buffer(data)
        ubo.bind_to_uniform_block(binding)
        prog[blocks[0]].binding = binding
        return ubo

    def light_pass(self, prog, m: dict, clip: str, state: tuple[str, str]) -> np.ndarray:
        """One map's stored depth, (h, w) float32 as it lies in memory (row 0 = the first texel row).
        `state`: (api, text) of the document's rasterizer-state block (light_pass_state)."""
        w, h = (int(x) for x in m["resolution"])
        tex = self.depth_texture(w, h)
        fbo = self.ctx.framebuffer(depth_attachment=tex)
        reversed_z = clip == "reversed_z"
        u = pack_light_pass(m, reversed_z)
        for name in ("uLightViewProj", "uLightView"):
            if name in prog:
                prog[name].write(u[name])
        for name in ("uLinearDepth", "uLinearOffset"):
            if name in prog:
                prog[name].value = u[name]
        ubo = self._bind_block(prog, u["block"], 1)
        vao = self._vao(prog, False)
        ctx = self.ctx
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        ctx.enable(self.mgl.DEPTH_TEST)
        if clip not in CLIP_CONTROL:
            raise ValueError(f"clip must be one of {', '.join(CLIP_CONTROL)}, got {clip!r}")
        self.gl.clip_control(*CLIP_CONTROL[clip])
        fbo.clear(depth=0.0 if reversed_z else 1.0)
        # The depth test as the document's prose says (the OpenGL block sets it again itself), then the block.
        self.gl.depth_func(GL_GREATER if reversed_z else GL_LESS)
        api, text = state
        hardware = m["depth"]["mode"] == "hardware"
        k, mm = (float(m["depth"]["slope_scaled"]), float(m["depth"]["slope_clamp"])) if hardware else (0.0, 0.0)
        for name, args in light_pass_state(api, text, k, mm, reversed_z):
            self.gl.calls[name](*args)
        vao.render(self.mgl.TRIANGLES)
        ctx.finish()
        self.gl.clip_control(GL_LOWER_LEFT, GL_NEGATIVE_ONE_TO_ONE)
        self.gl.disable(GL_POLYGON_OFFSET_FILL)
        self.gl.polygon_offset_clamp(0.0, 0.0, 0.0)
        self.gl.disable(GL_DEPTH_CLAMP)
        self.gl.depth_func(GL_LESS)
        out = np.frombuffer(tex.read(alignment=1), dtype=np.float32).reshape(h, w).copy()
        for x in (vao, fbo, tex, ubo):
            if x is not None:
                x.release()
        return out

    def camera_pass(self, prog, camera: dict, shadow_array, block: bytes):
        """The camera view with the lookup: (h, w, 4) [visibility, view depth, hit, 1] and (h, w, 4)
        position, row 0 at the top."""
        w, h = (int(x) for x in camera["resolution"])
        color = self.ctx.texture((w, h), 4, dtype="f4")
        world = self.ctx.texture((w, h), 4, dtype="f4")
        depth = self.depth_texture(w, h)
        fbo = self.ctx.framebuffer(color_attachments=[color, world], depth_attachment=depth)
        prog["uCamViewProj"].write(_gl_mat(_mat(camera["projection"]) @ _mat(camera["view"])))
        prog["uCamView"].write(_gl_mat(_mat(camera["view"])))
        ubo = self._bind_block(prog, block, 0)
        if ubo is None:
            raise RuntimeError("the lookup declares no uniform block")
        shadow_array.use(location=0)
        for name in self._members(prog, self.mgl.Uniform):
            if "sampler" in name.lower() or "shadowmap" in name.lower():
                prog[name].value = 0
        vao = self._vao(prog, True)
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        self.ctx.enable(self.mgl.DEPTH_TEST)
        self.ctx.disable_direct(GL_DEPTH_CLAMP)
        self.ctx.depth_func = "<"
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        vao.render(self.mgl.TRIANGLES)
        self.ctx.finish()
        c = np.frombuffer(color.read(), dtype=np.float32).reshape(h, w, 4)[::-1].copy()
        p = np.frombuffer(world.read(), dtype=np.float32).reshape(h, w, 4)[::-1].copy()
        for x in (vao, fbo, color, world, depth, ubo):
            x.release()
        return c, p


def _shaders(h: Harness, lang: str, src: dict, lookup: str = "cascades"):
    """(light-pass vertex, {mode: light-pass fragment or None}, camera fragment) in GLSL 330. lookup: "cascades"
    calls the document's shadowVisibility, "local" its shadow-lookup-local piece's localShadowVisibility."""
    code = src["shadow-lookup"] + ("\n" + src["shadow-lookup-local"] if lookup == "local" else "")
    if lang == "glsl":
        entry = "localShadowVisibility" if lookup == "local" else "shadowVisibility"
        return (src["light-pass-vertex"], {"hardware": src["light-pass-hardware"], "linear": src["light-pass-linear"]},
                CAMERA_FRAGMENT_GLSL.format(lookup=code, entry=entry))
    key = ("hlsl-sources", lookup)
    entry = "LocalShadowVisibility" if lookup == "local" else "ShadowVisibility"
    if key not in h.programs:
        vary = ("v_lightDistance",)
        h.programs[key] = (
            hlsl_to_glsl(src["light-pass-vertex"], "vert", "LightPassVS", outputs=vary),
            # Direct3D's depth-only pass binds no pixel shader; OpenGL links one without a fragment stage.
            {"hardware": None,
             "linear": hlsl_to_glsl(src["light-pass-linear"], "frag", "LightPassLinearPS", inputs=vary)},
            hlsl_to_glsl(CAMERA_FRAGMENT_HLSL.format(lookup=code, entry=entry), "frag", "main",
                         inputs=("i_world", "i_normal", "i_viewDepth")))
    return h.programs[key]


def run(vertices, faces, spec: dict) -> dict:
    h = Harness(vertices, faces)
    try:
        out = {"renderer": h.ctx.info["GL_RENDERER"]}
        cam = spec["camera"]
        for job in spec["jobs"]:
            lang, clip = job["language"], job["clip"]
            lookup = job.get("lookup", "cascades")
            light_v, light_f, cam_f = _shaders(h, lang, spec["sources"][lang], lookup)
            state = (job["state"], spec["sources"]["c"][f"light-pass-state-{job['state']}"])
            layers = []
            for m in job["maps"]:
                mode = m["depth"]["mode"]
                layers.append(h.light_pass(h.program((lang, "light", mode), light_v, light_f[mode]), m, clip, state))
            # the array as large as the largest map; map k in its first rows and columns (the document's rule)
            mh, mw = max(a.shape[0] for a in layers), max(a.shape[1] for a in layers)
            stack = np.ones((len(layers), mh, mw), dtype=np.float32)
            for i, a in enumerate(layers):
                stack[i, :a.shape[0], :a.shape[1]] = a
            arr = h.ctx.texture_array((mw, mh, len(layers)), 1, stack.tobytes(), dtype="f4")
            arr.filter = (h.mgl.NEAREST, h.mgl.NEAREST)
            prog = h.program((lang, "camera", lookup), CAMERA_VERTEX, cam_f)
            c, p = h.camera_pass(prog, cam, arr, pack_uniforms(job["maps"], job["to_light"], clip == "reversed_z",
                                                               bool(job.get("faces"))))
            arr.release()
            out[f"shadow_{job['name']}"] = c[..., 0]
            if job.get("keep_maps"):
                out[f"stored_{job['name']}"] = np.stack(layers)
            out.setdefault("hit", c[..., 2] > 0.5)
            out.setdefault("view_depth", c[..., 1])
            out.setdefault("position", p[..., :3])
        return out
    finally:
        h.release()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: python -m shadowopt.renderers.gl_listing IN.npz OUT.npz", file=sys.stderr)
        return 2
    d = np.load(argv[0])
    out = run(d["vertices"], d["faces"], json.loads(str(d["spec"])))
    np.savez(argv[1], **out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
