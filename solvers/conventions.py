"""Matrix conventions engines receive: OpenGL, Direct3D, Vulkan; row- or column-major; world or stage frame.

Internally (solvers.shadow_map) a projection maps light view space to a canonical clip space:
OpenGL's, column vectors, NDC x, y, z in [-1, 1]. Each step below is one small function.
"""
from __future__ import annotations

import numpy as np

CONVENTIONS = ("opengl", "d3d", "vulkan")
LAYOUTS = ("row_major", "column_major")
FRAMES = ("world", "stage")


def _check(convention: str) -> None:
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}")


def clip_from_canonical(convention: str) -> np.ndarray:
    """C with engine_projection = C @ canonical_projection.

    opengl: identity (clip z in [-w, w]). d3d: z' = (z + w)/2, so NDC z in [0, 1].
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
            t = 0 at the bottom of the map.
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
    return clip_from_canonical(convention) @ proj_canonical


def texture_matrix(view: np.ndarray, proj_canonical: np.ndarray, convention: str) -> np.ndarray:
    """S · P_light · V_light (seed 003's chain), P in the given convention."""
    return texture_from_clip(convention) @ projection_for(proj_canonical, convention) @ view


def to_layout(m: np.ndarray, layout: str) -> list[float]:
    """A flat list of 16 floats in memory order: row_major m[0,0], m[0,1], ...; column_major m[0,0], m[1,0], ..."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    m = np.asarray(m, dtype=np.float64)
    return (m.ravel() if layout == "row_major" else m.T.ravel()).tolist()


def from_layout(flat, layout: str) -> np.ndarray:
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    a = np.asarray(flat, dtype=np.float64).reshape(4, 4)
    return a if layout == "row_major" else a.T


def to_stage_frame(m_world: np.ndarray, stage_to_world: np.ndarray) -> np.ndarray:
    """A matrix acting on world points re-expressed to act on stage points: m @ stage_to_world."""
    return np.asarray(m_world, dtype=np.float64) @ stage_to_world


def export_matrices(view: np.ndarray, proj_canonical: np.ndarray, convention: str = "opengl",
                    layout: str = "column_major", frame: str = "world",
                    stage_to_world: np.ndarray | None = None) -> dict:
    """The matrices an engine receives, flat in `layout`: view, projection (convention), texture."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    v = np.asarray(view, dtype=np.float64)
    tex = texture_matrix(v, proj_canonical, convention)
    if frame == "stage":
        s2w = np.eye(4) if stage_to_world is None else stage_to_world
        v, tex = to_stage_frame(v, s2w), to_stage_frame(tex, s2w)
    return {"view_matrix": to_layout(v, layout),
            "projection_matrix": to_layout(projection_for(proj_canonical, convention), layout),
            "texture_matrix": to_layout(tex, layout)}
