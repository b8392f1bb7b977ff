"""The work a request asks for, estimated from its rig before anything runs, and the limits on it.

Standard library only: api/schemas.py (which the Python client imports) validates every Rig with it, and
service.rigs.resolve_rig applies the same check to rig dicts that never went through the model (stored batch
configurations, benchmarks, the CLI's library callers). One function, `solve_work`, is the estimate; one
constant, MAX_SOLVE_WORK, bounds it; `eval_work` / MAX_EVAL_WORK bound the ground truth of evaluate and
compare the same way.

Solve work, in "coarse pixel x map" units: for each light, the coarse buffer's pixels (coarse_long_side on
the camera's long side, the camera.resolution's aspect on the other) times the maps fitted for that light:
`cascades` (`"auto"` tries 1..max_cascades, so max_cascades (max_cascades + 1) / 2 fits), times 6 for a
point light's cube faces. A light given by usd_path counts as a point light (its type is only known once the
scene is loaded; resolve_rig checks again with the real type). Measured on the demo scene (2 shared cores,
method optimized, time_budget_ms 10000): 16 lights x 180 px x 4 cascades (1.16 M units) 2.8 s, one light at
1024 px (0.59 M) 2.0 s, 16 lights at 180 px (0.29 M) 1.4 s; the cost grows with lights x coarse pixels and
less than linearly with cascades, so the estimate is an upper bound.

Eval work, in screen-pixel equivalents: per evaluation (one light of /v1/evaluate, one method of /v1/compare)
the screen's pixels plus the texels of that light's maps / 32 (a ground-truth screen pixel, with its camera
ray, shadow ray and derivatives, costs ~2.6 us; a texel-centre ray ~80 ns on this machine).
"""
from __future__ import annotations

import ctypes
import math
import sys

MAX_SOLVE_WORK = 1_200_000
"""Coarse pixels x maps over a request's solves (/v1/compare runs len(methods) + 1 solves). 1.2 M: the
demo rig (18 k), the benchmark rigs (<= 18 k) and every test rig (<= 60 k) are far below it; the largest
accepted optimize (e.g. 16 lights x 180 px x 4 cascades) takes ~3 s here."""

MAX_EVAL_WORK = 4_500_000
"""Screen pixels + texels / 32 over a request's ground-truth evaluations. 4.5 M: a /v1/compare of the demo
rig at its 1280x720 camera with the four default methods (4.2 M) fits; ~12 s at the limit on this machine."""

TEXELS_PER_PIXEL = 32
LARGE_REQUEST_WORK = 200_000
"""Above this solve work (or eval work), a request's Dr.Jit allocations are returned to the system when it
ends (drjit.flush_malloc_cache, then glibc's malloc_trim) instead of staying cached in the process. Measured
in-process after a 1280x720 evaluate of the demo rig: 0.364 GB -> 0.315 GB (flush) -> 0.254 GB (trim)."""

CUBE_FACES = 6
DEFAULT_RESOLUTION = (1280, 720)
DEFAULT_LONG_SIDE = 180
DEFAULT_MAP = (2048, 2048)


class WorkLimit(ValueError):
    """A request over a work limit: `field` (the dotted field that drives it most, relative to the rig, or
    the request's own field such as `screen`) and a message naming the fields, their values and the limit."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field, self.message = field, message


def _get(d, key, default=None):
    v = d.get(key) if isinstance(d, dict) else getattr(d, key, None)
    return default if v is None else v


def coarse_pixels(rig) -> int:
    """Pixels of the coarse buffers: `coarse_long_side` on the long side, the camera resolution's aspect."""
    long_side = int(_get(rig, "coarse_long_side", DEFAULT_LONG_SIDE))
    w, h = _get(_get(rig, "camera", {}), "resolution", DEFAULT_RESOLUTION)
    w, h = int(w), int(h)
    short = max(1, round(long_side * min(w, h) / max(w, h, 1)))
    return long_side * short


def maps_per_light(shadow) -> int:
    cascades = _get(shadow, "cascades", 1)
    if cascades == "auto":
        k = int(_get(shadow, "max_cascades", 4))
        return k * (k + 1) // 2
    return int(cascades)


def light_faces(light, kind: str | None = None) -> int:
    kind = kind or _get(light, "type")
    if kind is None and _get(light, "usd_path") is not None:
        kind = "point"  # not known before the scene is loaded: the most expensive
    return CUBE_FACES if kind == "point" else 1


def solve_work(rig, kinds: list[str] | None = None) -> int:
    """Coarse pixels x map fits of one solve of `rig` (a Rig model or its dict). `kinds`: the resolved light
    types, when known."""
    px = coarse_pixels(rig)
    maps = maps_per_light(_get(rig, "shadow", {}))
    lights = _get(rig, "lights", [])
    return sum(px * maps * light_faces(l, kinds[i] if kinds else None) for i, l in enumerate(lights))


def describe_work(rig, kinds=None, prefix: str = "rig.") -> str:
    lights = _get(rig, "lights", [])
    faces = [light_faces(l, kinds[i] if kinds else None) for i, l in enumerate(lights)]
    cube = sum(1 for f in faces if f > 1)
    shadow = _get(rig, "shadow", {})
    cam = _get(rig, "camera", {})
    w, h = _get(cam, "resolution", DEFAULT_RESOLUTION)
    c = _get(shadow, "cascades", 1)
    casc = (f"{prefix}shadow.cascades: auto up to {prefix}shadow.max_cascades {_get(shadow, 'max_cascades', 4)} "
            f"({maps_per_light(shadow)} map fits)" if c == "auto" else f"{prefix}shadow.cascades: {c}")
    return (f"{prefix}lights: {len(lights)}" + (f" ({cube} counted as point lights, x{CUBE_FACES} cube faces)"
                                                 if cube else "")
            + f", {prefix}coarse_long_side: {_get(rig, 'coarse_long_side', DEFAULT_LONG_SIDE)} "
            f"({coarse_pixels(rig)} coarse pixels at {prefix}camera.resolution {int(w)}x{int(h)}), {casc}")


def _largest_field(rig, kinds=None) -> str:
    """The field to blame: the one that multiplies the work most above a modest rig's value."""
    lights = _get(rig, "lights", [])
    n_faces = sum(light_faces(l, kinds[i] if kinds else None) for i, l in enumerate(lights))
    ratios = {"coarse_long_side": coarse_pixels(rig) / (DEFAULT_LONG_SIDE * 101),
              "lights": n_faces / 1.0,
              "shadow.cascades": maps_per_light(_get(rig, "shadow", {})) / 1.0}
    return max(ratios, key=ratios.get)


def check_solve_work(rig, solves: int = 1, kinds: list[str] | None = None, prefix: str = "rig.") -> None:
    """WorkLimit when `solves` solves of `rig` are over MAX_SOLVE_WORK."""
    work = solve_work(rig, kinds) * solves
    if work > MAX_SOLVE_WORK:
        times = f" x {solves} solves" if solves > 1 else ""
        raise WorkLimit(_largest_field(rig, kinds),
                        f"the request is too costly: estimated solve work {work:,} coarse pixel x map units"
                        f"{times} is over the limit of {MAX_SOLVE_WORK:,} ({describe_work(rig, kinds, prefix)}; "
                        f"work = sum over lights of coarse pixels x maps, x{CUBE_FACES} for point lights); "
                        f"lower {prefix}coarse_long_side, the number of {prefix}lights or {prefix}shadow.cascades")


def map_texels(shadow) -> int:
    """Texels of one light's maps as the rig asks for them (texel_budget, or resolution x maps)."""
    budget = _get(shadow, "texel_budget")
    if budget is not None:
        return int(budget) * (maps_per_light(shadow) if _get(shadow, "cascades", 1) == "auto" else 1)
    w, h = _get(shadow, "resolution", DEFAULT_MAP)
    return int(w) * int(h) * maps_per_light(shadow)


def eval_screen_pixels(resolution, screen=None) -> int:
    """The ground truth's screen pixels: `screen`, or the camera's `resolution` without one; a screen of
    another aspect keeps the camera's (long side = max(screen)), as renderers.ground_truth.screen_camera does."""
    w, h = (int(v) for v in (screen or resolution))
    cw, ch = (int(v) for v in resolution)
    if screen is not None and abs(w / h - cw / ch) > 1e-3 * cw / ch:
        long_side = max(w, h)
        short = max(1, round(long_side * min(cw, ch) / max(cw, ch)))  # solvers.cameras.Camera.coarse_resolution
        return long_side * short
    return w * h


def eval_work(screen_pixels: int, texels: int) -> int:
    return int(screen_pixels) + math.ceil(int(texels) / TEXELS_PER_PIXEL)


def check_eval_work(evaluations: list[tuple[int, int]], screen_field: str, what: str) -> int:
    """WorkLimit when the ground-truth evaluations [(screen pixels, texels), ...] are over MAX_EVAL_WORK;
    returns the work."""
    work = sum(eval_work(p, t) for p, t in evaluations)
    if work > MAX_EVAL_WORK:
        px = sum(p for p, _ in evaluations)
        tx = sum(t for _, t in evaluations)
        raise WorkLimit(screen_field,
                        f"the request is too costly: {what}: {len(evaluations)} ground-truth evaluation(s) of "
                        f"{px:,} screen pixels ({screen_field}) and {tx:,} map texels in all, estimated eval work "
                        f"{work:,} (pixels + texels/{TEXELS_PER_PIXEL}) is over the limit of {MAX_EVAL_WORK:,}; "
                        f"lower {screen_field}, the shadow resolution or the number of methods/lights")
    return work


def flush_if_large(work: int) -> bool:
    """Return Dr.Jit's cached allocations to the system after a large request (True when flushed)."""
    if work <= LARGE_REQUEST_WORK:
        return False
    try:
        import drjit as dr  # lazy: the rendering stack, absent in the client install
    except ImportError:  # the client install
        return False
    dr.sync_thread()
    dr.flush_malloc_cache()
    _malloc_trim()  # NumPy's big temporaries live on the C heap: hand its free pages back too
    return True


def _malloc_trim() -> None:
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        pass
