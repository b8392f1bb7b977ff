"""Rasterize a shadow map's depth with real OpenGL (Mesa llvmpipe through EGL) - a check that the
matrices we return mean to a GPU what they mean to us.

Run it in its own process (`python tests/gl_check.py IN.npz OUT.npz`, as testkit.gl_depth does): Mesa loads
LLVM 15, and a Dr.Jit in the same process would reuse that library and crash. This module imports
nothing but NumPy and moderngl for that reason.

IN.npz: vertices (V, 3) float32 (already re-centred), faces (F, 3) uint32, matrix (4, 4) float64
world->clip acting on those vertices (column vectors), resolution (2,), depth_clamp (bool), and
clip_z ("neg_one_to_one" for OpenGL's clip space, or "zero_to_one" for Direct3D/Vulkan ones,
emulated by remapping z in the vertex shader), optionally reversed_z (bool: the projection puts the near
plane at depth 1: depth test GREATER, cleared to 0). OUT.npz: depth (height, width) float32 window depth
in [0, 1], row 0 at the bottom (t = 0), as the framebuffer stores it.
"""
from __future__ import annotations

import sys

import moderngl
import numpy as np

GL_DEPTH_CLAMP = 0x864F

VERTEX = """
#version 330
uniform mat4 M;
uniform float zero_to_one;
in vec3 in_pos;
void main() {
    vec4 c = M * vec4(in_pos, 1.0);
    // A clip space with z in [0, w] (D3D, Vulkan) becomes OpenGL's [-w, w] for the rasterizer.
    c.z = mix(c.z, 2.0 * c.z - c.w, zero_to_one);
    gl_Position = c;
}
"""
FRAGMENT = """
#version 330
void main() { }
"""


def rasterize_depth(vertices, faces, matrix, resolution, depth_clamp=True, clip_z="neg_one_to_one",
                    reversed_z=False):
    ctx = moderngl.create_standalone_context(backend="egl")
    try:
        w, h = int(resolution[0]), int(resolution[1])
        depth = ctx.depth_texture((w, h))
        fbo = ctx.framebuffer(depth_attachment=depth)
        prog = ctx.program(vertex_shader=VERTEX, fragment_shader=FRAGMENT)
        # GLSL matrices are column-major: upload the transpose of the row-major NumPy array.
        prog["M"].write(np.asarray(matrix, dtype=np.float32).T.tobytes())
        prog["zero_to_one"].value = 1.0 if clip_z == "zero_to_one" else 0.0
        vbo = ctx.buffer(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
        ibo = ctx.buffer(np.ascontiguousarray(faces, dtype=np.uint32).tobytes())
        vao = ctx.vertex_array(prog, [(vbo, "3f", "in_pos")], index_buffer=ibo, index_element_size=4)
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        ctx.enable(moderngl.DEPTH_TEST)
        if depth_clamp:
            ctx.enable_direct(GL_DEPTH_CLAMP)  # "pancaking": casters in front of the near plane clamp to it
        if reversed_z:  # near at 1, far at 0 (Reed 2015, "Depth Precision Visualized")
            ctx.depth_func = ">"
        fbo.clear(depth=0.0 if reversed_z else 1.0)
        vao.render(moderngl.TRIANGLES)
        ctx.finish()
        data = np.frombuffer(depth.read(alignment=1), dtype=np.float32).reshape(h, w)
        return data.copy(), ctx.info["GL_RENDERER"]
    finally:
        ctx.release()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: python tests/gl_check.py IN.npz OUT.npz", file=sys.stderr)
        return 2
    d = np.load(argv[0])
    depth, renderer = rasterize_depth(d["vertices"], d["faces"], d["matrix"], d["resolution"],
                                      bool(d["depth_clamp"]), str(d["clip_z"]),
                                      bool(d["reversed_z"]) if "reversed_z" in d.files else False)
    np.savez(argv[1], depth=depth, renderer=renderer)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
