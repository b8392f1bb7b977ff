"""What a light needs of a shadow map: the visible receivers it can shadow, read from the coarse buffers.

A receiver of a light is a surface point the camera sees (a coarse hit, or a hit of the edge pass) that faces
the light inside its cone (spot) — lit by it or shadowed from it (renderers.coarse.light_test's `facing` and
`in_light`; a surface facing away is dark by its own shading, which needs no map). A light with none casts no
visible shadow: it gets no map (`"shadow": "none"` and the reason, with the counts). A cascade or cube face
whose region holds none of the light's receivers (service.receivers.receiver_points, with their view-depth slack)
is dropped, its depth range given to a neighbouring cascade so that the splits still cover the view.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Need:
    """Counts of one light's coarse buffers (coarse pixels; `edge_*`: the edge pass's fine hits)."""

    seen: int  # coarse pixels where the camera sees geometry
    in_cone: int  # of those, inside the light's cone (all for directional and point lights)
    receivers: int  # of those, facing the light: lit or shadowed by it
    lit: int  # receivers lit (the rest are shadowed)
    edge_points: int  # hits of the edge pass
    edge_receivers: int  # of those, facing the light inside its cone

    @property
    def shadowed(self) -> int:
        return self.receivers - self.lit

    @property
    def needs_map(self) -> bool:
        return self.receivers + self.edge_receivers > 0

    def to_json(self) -> dict:
        return {"seen_pixels": self.seen, "in_cone_pixels": self.in_cone, "receiver_pixels": self.receivers,
                "lit_pixels": self.lit, "shadowed_pixels": self.shadowed, "edge_points": self.edge_points,
                "edge_receivers": self.edge_receivers, "pixels": "coarse buffer pixels"}


def light_need(buffers, li: int) -> Need:
    """The Need of light `li` of coarse buffers (renderers.coarse.CoarseBuffers)."""
    lb = buffers.lights[li]
    hit = np.asarray(buffers.hit, dtype=bool)
    in_cone = hit & np.asarray(lb.in_light, dtype=bool)
    rec = in_cone & np.asarray(lb.facing, dtype=bool)
    fine = getattr(buffers, "fine", None)
    edge_points = int(len(fine.flat)) if fine is not None else 0
    edge_rec = int(np.count_nonzero(fine.receiver[li])) if fine is not None and li < len(fine.receiver) else 0
    return Need(int(hit.sum()), int(in_cone.sum()), int(rec.sum()), int((rec & np.asarray(lb.visible)).sum()),
                edge_points, edge_rec)


def no_shadow_reason(light, need: Need, size: tuple[int, int]) -> str:
    """One sentence: why this light gets no map, with the counts."""
    w, h = size
    if need.seen == 0:
        return (f"no shadow map: the camera sees no geometry within its far plane ({w}x{h} coarse pixels, "
                f"{need.edge_points} edge-pass points), so this light can shadow no visible receiver")
    where = f"of the {need.seen} of {w}x{h} coarse pixels where the camera sees geometry"
    if light.kind == "spot":
        what = (f"{need.in_cone} are inside its {light.cone_deg:g} degree cone and {need.receivers} of those "
                f"face it")
    else:
        what = f"{need.receivers} face it"
    return (f"no shadow map: {where}, {what} (edge pass: {need.edge_receivers} of {need.edge_points} points), "
            f"so this light can shadow no visible receiver")


def receivers_per_map(maps, receivers: np.ndarray, slack: np.ndarray, camera) -> np.ndarray:
    """Per map, the receivers it serves: a cascade those whose view depth, give or take their slack, meets
    its split; a cube face those inside its map (solvers.metric's face rule)."""
    counts = np.zeros(len(maps), dtype=np.int64)
    if not len(receivers) or not maps:
        return counts
    if maps[0].face is not None:
        for k, smap in enumerate(maps):
            s, t, z, w = smap.map_coords(receivers)
            counts[k] = int(np.count_nonzero((w > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)))
        return counts
    d = (np.asarray(receivers) - camera.position) @ camera.forward
    sl = np.asarray(slack, dtype=np.float64) if slack is not None and len(slack) == len(d) else np.zeros_like(d)
    for k, smap in enumerate(maps):
        lo, hi = smap.split
        counts[k] = int(np.count_nonzero((d + sl >= lo) & (d - sl <= hi)))
    return counts


def drop_empty_maps(maps, receivers: np.ndarray, slack: np.ndarray, camera) -> tuple[list, list[str]]:
    """`maps` without the cascades and faces that serve no receiver, and a note for each dropped one. A
    dropped cascade's depth range goes to the previous kept cascade (the next one for the first), so the
    kept splits stay contiguous; nothing is dropped when no map serves a receiver (the caller decides)."""
    counts = receivers_per_map(maps, receivers, slack, camera)
    if len(maps) <= 1 or counts.all() or not counts.any():
        return list(maps), []
    keep = [k for k in range(len(maps)) if counts[k] > 0]
    notes = []
    for k in range(len(maps)):
        if counts[k] > 0:
            continue
        m = maps[k]
        if m.face is not None:
            notes.append(f"cube face {m.face} dropped: none of the light's {len(receivers)} visible receiver "
                         f"points is in its frustum")
            continue
        lo, hi = m.split
        notes.append(f"cascade {k} (view depth {lo:.4g}-{hi:.4g}) dropped: none of the light's {len(receivers)} "
                     f"visible receiver points is at that depth; its range is served by the neighbouring cascade")
    if maps[0].face is None:  # give each dropped range to a kept neighbour (the splits stay contiguous)
        for k in range(len(maps)):
            if counts[k] > 0:
                continue
            prev = [j for j in keep if j < k]
            nxt = [j for j in keep if j > k]
            if prev:
                j = prev[-1]
                maps[j].split = (maps[j].split[0], max(maps[j].split[1], maps[k].split[1]))
            else:
                j = nxt[0]
                maps[j].split = (min(maps[j].split[0], maps[k].split[0]), maps[j].split[1])
    return [maps[k] for k in keep], notes


def split_budget(budget: int, misclassified: list[float | None], probe_texels: int) -> list[int]:
    """One texel budget for the whole rig, split across lights by need: Chong 2003's Lagrange allocation across
    frusta, generalized to lights. A light's predicted misclassified pixels go as M_i(T) = d_i T^-1/2 (a
    shadow edge's band of wrong pixels is one texel footprint wide, and the footprint's side goes as T^-1/2:
    solvers.metric.predicted_misclassified), so d_i = M_i(probe) sqrt(probe). Minimizing sum_i d_i T_i^-1/2
    under sum_i T_i = budget: d_i T_i^-3/2 / 2 = lambda for every light, T_i = budget d_i^(2/3) / sum_j
    d_j^(2/3). None (a light with no map) gets 0; when no light has a predicted misclassified pixel (no
    shadow edge on screen) the budget is shared equally by the lights with maps."""
    active = [i for i, m in enumerate(misclassified) if m is not None]
    out = [0] * len(misclassified)
    if not active:
        return out
    w = np.array([max(float(misclassified[i]), 0.0) * np.sqrt(probe_texels) for i in active]) ** (2.0 / 3.0)
    w = w / w.sum() if w.sum() > 0 else np.full(len(active), 1.0 / len(active))
    for i, f in zip(active, w):
        out[i] = int(budget * f)
    return out
