"""Hints for interpolating between neighbouring configurations' solutions: which fields vary smoothly,
which switch, and where a batch's results break into segments an engine may interpolate within."""
from __future__ import annotations


SMOOTH_FIELDS = [
    "lights[].cascades[].view_matrix", "lights[].cascades[].projection_matrix",
    "lights[].cascades[].texture_matrix", "lights[].cascades[].split", "lights[].cascades[].light_depth",
    "lights[].cascades[].blend_band", "lights[].cascades[].warp.eta", "lights[].cascades[].warp.n",
    "lights[].cascades[].warp.log.c0", "lights[].cascades[].warp.log.c1", "lights[].cascades[].warp.log.c2",
    "lights[].cascades[].depth_bias", "lights[].cascades[].depth.hardware", "lights[].cascades[].depth.linear",
    "lights[].cascades[].predicted_error", "lights[].predicted_error",
]
SWITCH_FIELDS = ["lights[].cascades (count)", "lights[].cascades[].warp.kind", "lights[].cascades[].resolution",
                 "lights[].cascades[].face", "lights[].cascades[].depth.mode", "lights[].type", "method"]


def _signature(result: dict) -> tuple:
    return (result.get("method"), tuple(
        (l.get("type"), len(l.get("cascades") or []),
         tuple((c.get("warp") or {}).get("kind") for c in l.get("cascades") or []),
         tuple(tuple(c.get("resolution") or ()) for c in l.get("cascades") or []),
         tuple(c.get("face") for c in l.get("cascades") or []),
         tuple((c.get("depth") or {}).get("mode") for c in l.get("cascades") or []))
        for l in result.get("lights") or []))


def _switch_reasons(a: dict, b: dict) -> list[str]:
    sa, sb = _signature(a), _signature(b)
    if sa[0] != sb[0]:
        return [f"method {sa[0]} -> {sb[0]}"]
    if len(sa[1]) != len(sb[1]):
        return [f"lights {len(sa[1])} -> {len(sb[1])}"]
    reasons = []
    for k, (la, lb) in enumerate(zip(sa[1], sb[1])):
        if la[0] != lb[0]:
            reasons.append(f"light {k}: type {la[0]} -> {lb[0]}")
        if la[1] != lb[1]:
            reasons.append(f"light {k}: cascades {la[1]} -> {lb[1]}")
        elif la[2] != lb[2]:
            reasons.append(f"light {k}: warp kind {'/'.join(map(str, la[2]))} -> {'/'.join(map(str, lb[2]))}")
        elif la[3] != lb[3] or la[4] != lb[4]:
            reasons.append(f"light {k}: cascade resolution or face changes")
        elif la[5] != lb[5]:
            reasons.append(f"light {k}: depth mode {'/'.join(map(str, la[5]))} -> {'/'.join(map(str, lb[5]))}")
    return reasons


def interpolation_hints(results: list[dict], shape: tuple[int, int] | None = None) -> dict:
    """How an engine may interpolate between neighbouring configurations' solutions.

    `results`: lines as Store.results gives them ({"index", ...solution} or {"index", "error"}).
    Neighbours are consecutive indices; with `shape = (cameras, lights)` (a camera path crossed with
    light directions, index = camera * lights + light) also the same light at consecutive cameras.
    Returns {"smooth_fields", "switch_fields", "breaks": [{"between": [i, j], "reasons": [...]}],
    "segments": [[first, last], ...]} where segments are runs of consecutive indices with no break (along
    the lights of one camera; along the cameras when there is one light), and for a grid of several cameras
    and lights also "camera_segments": the same light at consecutive cameras, [first, last] stepping by
    the number of lights. Interpolate smooth fields element-wise within a segment, never across a break.
    """
    by_index = {r["index"]: r for r in results}
    pairs = []
    if shape is None:
        idx = sorted(by_index)
        pairs = [(i, i + 1) for i in range(idx[0], idx[-1])] if idx else []
    else:
        cams, lights = shape
        for c in range(cams):
            for l in range(lights):
                i = c * lights + l
                if l + 1 < lights:
                    pairs.append((i, i + 1))
                if c + 1 < cams:
                    pairs.append((i, i + lights))
    breaks = []
    for i, j in pairs:
        a, b = by_index.get(i), by_index.get(j)
        if a is None or b is None or "error" in a or "error" in b:
            why = [f"configuration {k} has no result" for k, r in ((i, a), (j, b)) if r is None or "error" in r]
            breaks.append({"between": [i, j], "reasons": why})
            continue
        reasons = _switch_reasons(a, b)
        if reasons:
            breaks.append({"between": [i, j], "reasons": reasons})
    ok = sorted(k for k, r in by_index.items() if "error" not in r)
    broken = {tuple(b["between"]) for b in breaks}
    hints = {"smooth_fields": SMOOTH_FIELDS, "switch_fields": SWITCH_FIELDS, "breaks": breaks,
             "segments": _segments(ok, broken, shape),
             "neighbours": "consecutive indices" if shape is None else
             f"index = camera * {shape[1]} + light; neighbours along both axes"}
    if shape is not None and shape[0] > 1 and shape[1] > 1:
        hints["camera_segments"] = _camera_segments(set(ok), broken, shape)
    return hints


def _segments(ok: list[int], broken: set, shape) -> list[list[int]]:
    """Runs of consecutive successful indices along the index order: the light axis of a grid, or the
    camera axis when a camera path has one light (then consecutive indices are consecutive cameras)."""
    out = []
    for i in ok:
        same_row = shape is None or shape[1] == 1 or (i - 1) // shape[1] == i // shape[1]
        if out and out[-1][1] == i - 1 and same_row and (i - 1, i) not in broken:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def _camera_segments(ok: set, broken: set, shape) -> list[list[int]]:
    """For a grid with several lights: runs of the same light at consecutive cameras, [first, last] indices
    (stepping by the number of lights), in the order of the light then the first camera."""
    cams, lights = shape
    out = []
    for l in range(lights):
        run = None
        for c in range(cams):
            i = c * lights + l
            if i in ok and run is not None and run[1] == i - lights and (i - lights, i) not in broken:
                run[1] = i
            elif i in ok:
                run = [i, i]
                out.append(run)
            else:
                run = None
    return out
