"""The steps a request goes through: scene (cached) -> rig -> coarse buffers (-> solvers, later)."""
from __future__ import annotations

from ..renderers.coarse import CoarseBuffers, render_coarse
from .rigs import ResolvedRig, resolve_rig
from .scenes import SCENES, SceneEntry


def coarse_pass(entry: SceneEntry, rig: dict, boundary_radius: int = 1) -> tuple[ResolvedRig, CoarseBuffers]:
    resolved = resolve_rig(rig, entry.loaded)
    buffers = render_coarse(entry.rays, resolved.camera, resolved.lights, resolved.coarse_long_side,
                            boundary_radius=boundary_radius)
    return resolved, buffers


def scene_entry(path, **load_options) -> SceneEntry:
    return SCENES.get(path, **load_options)
