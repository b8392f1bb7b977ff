"""One check of a solution JSON before anything reads it: what `/v1/evaluate` (and `shadowopt evaluate`) reads
of a solution, and what `/v1/optimize` (and `shadowopt optimize --previous`) reads of a previous solution.

A malformed field raises `service.rigs.SolutionError` naming the exact field path
(`solution.lights.0.cascades.1.warp: expected an object with kind ..., got 'x'`), so the server answers
422 with that field and the CLI exits 2, never an internal error. What is checked is what the readers use:

- `lights`: one entry per rig light (1..16), each an object whose `type`, when given, is the rig light's kind;
- per light `shadow` (when given: "map", or "none" for a light with no visible receiver, whose `cascades` is
  then the empty list: it casts no shadow), `cascades` (1..16 unless shadow is "none"), each an object with
  `internal.view` and `internal.projection` (4x4 finite matrices whose product is invertible: the evaluator
  casts rays through its inverse), `resolution` (two integers in 1..16384), `split` (camera view-depth
  range [lo, hi], lo finite, hi a number >= lo or null for unbounded), `light_depth` (two finite numbers),
  `warp` (null or {kind: none|perspective|log, eta, n: null or finite, log: {c0, c1, c2} exactly when
  kind is log, c0 and c1 non-zero}), `depth_bias` (null or an object whose constant, slope,
  constant_texels, slope_texels are finite numbers when given), `face` (null or a cube face +x ... -z),
  `texel_snapped` (null or a boolean);
- `schema_version` (when given: the current one), `method` (null or a string), `provenance.scene_hash`
  (when given: this scene's);
- `solver` (null or an object; per light, `x` is a list of null or [phi, u] pairs of finite numbers: the
  previous solution's projective parameters per cascade); with several lights `solver.lights` has one
  entry (null or such an object) per rig light.

Fields nobody reads (the exported `view_matrix`, `texture_matrix`, predicted errors, timings) are left alone.
The return value is a normalized copy (an unbounded split's hi as inf, a null solver dropped) for
`service.solution_json.maps_from_solution` and the previous-solution path.
"""
from __future__ import annotations

import math

import numpy as np

from .rigs import SolutionError

SCHEMA_VERSION = 1  # of the solution JSON service.solution_json writes (defined here: the check imports no solver)
MAX_LIGHTS = 16
MAX_CASCADES = 16
MAX_RESOLUTION = 16384
MAX_CONDITION = 1e12  # projection @ view: real solutions have ~1e2-1e4; beyond this the inverse is noise
LIGHT_KINDS = ("directional", "spot", "point")
WARP_KINDS = ("none", "perspective", "log")
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
SHADOW_KINDS = ("map", "none")  # a light's `shadow`: maps, or none (no visible receiver: cascades [])
BIAS_TERMS = ("constant", "slope", "constant_texels", "slope_texels")


def _show(v) -> str:
    """A short rendering of a (user-given) value for a message."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        keys = ", ".join(map(str, list(v)[:6])) + (", ..." if len(v) > 6 else "")
        return f"an object {{{keys}}}" if v else "an empty object"
    if isinstance(v, list):
        return f"a list of {len(v)}" if v else "an empty list"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


class _Check:
    def __init__(self, code: str | None):
        self.code = code

    def fail(self, field: str, message: str):
        raise SolutionError(field, message, code=self.code)

    def obj(self, v, field: str, what: str = "an object") -> dict:
        if not isinstance(v, dict):
            self.fail(field, f"expected {what}, got {_show(v)}")
        return v

    def lst(self, v, field: str, what: str, lo: int, hi: int) -> list:
        if not isinstance(v, list):
            self.fail(field, f"expected {what}, got {_show(v)}")
        if not lo <= len(v) <= hi:
            self.fail(field, f"expected {what} ({lo} to {hi} entries), got {len(v)} entries")
        return v

    def number(self, v, field: str, *, finite: bool = True) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(field, f"expected a {'finite ' if finite else ''}number, got {_show(v)}")
        x = float(v)
        if math.isnan(x) or (finite and not math.isfinite(x)):
            self.fail(field, f"expected a finite number, got {_show(v)}")
        return x

    def pair(self, v, field: str) -> list:
        if not (isinstance(v, list) and len(v) == 2):
            self.fail(field, f"expected two numbers [lo, hi], got {_show(v)}")
        return v

    def matrix4(self, v, field: str) -> np.ndarray:
        if not (isinstance(v, list) and len(v) == 4):
            self.fail(field, f"expected a 4x4 matrix (4 rows of 4 numbers), got {_show(v)}")
        rows = []
        for r, row in enumerate(v):
            if not (isinstance(row, list) and len(row) == 4):
                self.fail(f"{field}.{r}", f"expected a row of 4 numbers, got {_show(row)}")
            rows.append([self.number(x, f"{field}.{r}.{c}") for c, x in enumerate(row)])
        return np.array(rows, dtype=np.float64)


def validate_solution(obj, field: str = "solution", *, light_kinds: list[str | None] | None = None,
                      n_lights: int | None = None, scene_hash: str | None = None, maps: bool = True,
                      code: str | None = None) -> dict:
    """Check `obj` (a solution JSON) and return a normalized copy; raise SolutionError naming the field.

    `light_kinds`: the rig's light kinds in order (their count is checked, and each light's `type`), or
    `n_lights`: only the count. `scene_hash`: the scene's, compared with `provenance.scene_hash`.
    `maps`: the shadow maps are read (evaluate: `lights` required); False for a previous solution, of which
    only `solver` is read (`lights` are still checked when given). `code`: the error code (default
    SolutionError's, invalid_solution)."""
    ck = _Check(code)
    if light_kinds is not None:
        n_lights = len(light_kinds)
    sol = ck.obj(obj, field, "a shadowopt solution (an object with lights, as /v1/optimize returns)")
    out = dict(sol)
    if "schema_version" in sol and not (type(sol["schema_version"]) is int and sol["schema_version"] == SCHEMA_VERSION):
        ck.fail(f"{field}.schema_version", f"expected {SCHEMA_VERSION}, got {_show(sol['schema_version'])}")
    if sol.get("method") is not None and not isinstance(sol["method"], str):
        ck.fail(f"{field}.method", f"expected a method name (a string), got {_show(sol['method'])}")
    if sol.get("provenance") is not None:
        prov = ck.obj(sol["provenance"], f"{field}.provenance")
        h = prov.get("scene_hash")
        if h is not None and not isinstance(h, str):
            ck.fail(f"{field}.provenance.scene_hash", f"expected a string, got {_show(h)}")
        if h and scene_hash and h != scene_hash:
            ck.fail(f"{field}.provenance.scene_hash", "the solution was computed for another scene")
    if maps or sol.get("lights") is not None:
        if "lights" not in sol:
            ck.fail(field, "not a shadowopt solution (no 'lights')")
        lights = ck.lst(sol["lights"], f"{field}.lights", "a list of lights", 1, MAX_LIGHTS)
        if maps and n_lights is not None and len(lights) != n_lights:
            ck.fail(f"{field}.lights", f"has {len(lights)} lights but the rig has {n_lights}")
        out["lights"] = [_light(ck, l, f"{field}.lights.{k}",
                                light_kinds[k] if light_kinds is not None and maps and k < len(light_kinds) else None)
                         for k, l in enumerate(lights)]
    if sol.get("solver") is None:
        out.pop("solver", None)
    else:
        out["solver"] = _solver(ck, sol["solver"], f"{field}.solver", n_lights)
    return out


def _light(ck: _Check, light, field: str, kind: str | None) -> dict:
    light = ck.obj(light, field, "a light (an object with cascades)")
    t = light.get("type")
    if t is not None:
        if t not in LIGHT_KINDS:
            ck.fail(f"{field}.type", f"expected one of {', '.join(LIGHT_KINDS)}, got {_show(t)}")
        if kind is not None and t != kind:
            ck.fail(f"{field}.type", f"the solution is for a {t} light but the rig's light is {kind}")
    if "cascades" not in light:
        ck.fail(field, "a light needs its cascades (the list of shadow maps)")
    shadow = light.get("shadow")
    if shadow is not None and shadow not in SHADOW_KINDS:
        ck.fail(f"{field}.shadow", f"expected one of {', '.join(SHADOW_KINDS)}, got {_show(shadow)}")
    if shadow == "none":  # a light with no visible receiver: no map, it casts no shadow (service.need)
        if light["cascades"] != []:
            ck.fail(f"{field}.cascades", f"a light with shadow 'none' has no maps (an empty list), got "
                    f"{_show(light['cascades'])}")
        return {**light, "cascades": []}
    cascades = ck.lst(light["cascades"], f"{field}.cascades", "a list of cascades (shadow maps)", 1, MAX_CASCADES)
    return {**light, "cascades": [_cascade(ck, c, f"{field}.cascades.{k}") for k, c in enumerate(cascades)]}


def _cascade(ck: _Check, c, field: str) -> dict:
    c = ck.obj(c, field, "a cascade (an object with internal, resolution, split, light_depth, warp)")
    out = dict(c)
    for key in ("internal", "resolution", "split", "light_depth"):
        if key not in c:
            ck.fail(field, f"a cascade needs {key}")
    internal = ck.obj(c["internal"], f"{field}.internal", "an object {view, projection} of 4x4 matrices")
    for key in ("view", "projection"):
        if key not in internal:
            ck.fail(f"{field}.internal", f"needs {key} (a 4x4 matrix)")
    view = ck.matrix4(internal["view"], f"{field}.internal.view")
    proj = ck.matrix4(internal["projection"], f"{field}.internal.projection")
    with np.errstate(all="ignore"):
        m = proj @ view
        cond = float(np.linalg.cond(m)) if np.all(np.isfinite(m)) else math.inf
    if not cond <= MAX_CONDITION:
        ck.fail(f"{field}.internal", "projection @ view is singular or not finite (no light ray through a texel)")
    res = c["resolution"]
    if not (isinstance(res, list) and len(res) == 2
            and all(type(v) is int and 1 <= v <= MAX_RESOLUTION for v in res)):
        ck.fail(f"{field}.resolution", f"expected two integers in 1..{MAX_RESOLUTION} [width, height], got {_show(res)}")
    split = ck.pair(c["split"], f"{field}.split")
    lo = ck.number(split[0], f"{field}.split.0")
    hi = math.inf if split[1] is None else ck.number(split[1], f"{field}.split.1", finite=False)
    if not lo <= hi:
        ck.fail(f"{field}.split", f"expected lo <= hi, got {_show(split)}")
    out["split"] = [lo, hi]
    ld = ck.pair(c["light_depth"], f"{field}.light_depth")
    out["light_depth"] = [ck.number(v, f"{field}.light_depth.{k}") for k, v in enumerate(ld)]
    if c.get("warp") is not None:
        out["warp"] = _warp(ck, c["warp"], f"{field}.warp")
    if c.get("depth_bias") is not None:
        bias = ck.obj(c["depth_bias"], f"{field}.depth_bias", f"an object with {', '.join(BIAS_TERMS)}")
        for key in BIAS_TERMS:
            if key in bias:
                ck.number(bias[key], f"{field}.depth_bias.{key}")
    if c.get("face") is not None and c["face"] not in FACES:
        ck.fail(f"{field}.face", f"expected null or a cube face ({', '.join(FACES)}), got {_show(c['face'])}")
    if c.get("texel_snapped") is not None and not isinstance(c["texel_snapped"], bool):
        ck.fail(f"{field}.texel_snapped", f"expected a boolean, got {_show(c['texel_snapped'])}")
    return out


def _warp(ck: _Check, w, field: str) -> dict:
    w = ck.obj(w, field, f"an object with kind ({', '.join(WARP_KINDS)}), eta, n and log")
    kind = w.get("kind", "none")
    if kind not in WARP_KINDS:
        ck.fail(f"{field}.kind", f"expected one of {', '.join(WARP_KINDS)}, got {_show(kind)}")
    for key in ("eta", "n"):
        if w.get(key) is not None:
            ck.number(w[key], f"{field}.{key}")
    lw = w.get("log")
    if lw is None:
        if kind == "log":
            ck.fail(f"{field}.log", "kind 'log' needs the log warp's parameters {c0, c1, c2}, got null")
        return dict(w)
    if kind != "log":
        ck.fail(f"{field}.kind", f"the warp has log parameters, so its kind must be 'log', got {_show(kind)}")
    lw = ck.obj(lw, f"{field}.log", "an object {c0, c1, c2} (t' = c0 * log(c1 * t + c2))")
    for key in ("c0", "c1", "c2"):
        if key not in lw:
            ck.fail(f"{field}.log", f"needs {key} (t' = c0 * log(c1 * t + c2))")
        x = ck.number(lw[key], f"{field}.log.{key}")
        if key != "c2" and x == 0.0:
            ck.fail(f"{field}.log.{key}", "must not be 0 (the log warp would not be invertible)")
    if lw.get("axis", "t") != "t":
        ck.fail(f"{field}.log.axis", f"expected 't' (the warp acts on the map's t axis), got {_show(lw['axis'])}")
    return dict(w)


def _solver(ck: _Check, s, field: str, n_lights: int | None) -> dict:
    s = ck.obj(s, field, "an object (the optimizer's report, with x per cascade)")
    if "lights" in s:
        per = ck.lst(s["lights"], f"{field}.lights", "a list with one entry per light", 1, MAX_LIGHTS)
        if n_lights is not None and len(per) != n_lights:
            ck.fail(f"{field}.lights", f"has {len(per)} entries but the rig has {n_lights} lights")
        return {**s, "lights": [None if p is None else _solver_light(ck, p, f"{field}.lights.{k}")
                                for k, p in enumerate(per)]}
    return _solver_light(ck, s, field)


def _solver_light(ck: _Check, s, field: str) -> dict:
    s = ck.obj(s, field, "an object with x (the projective parameters per cascade)")
    if s.get("x") is None:
        return {**s, "x": []}
    xs = ck.lst(s["x"], f"{field}.x", "a list with one entry per cascade", 0, MAX_CASCADES)
    for k, x in enumerate(xs):
        if x is None or (isinstance(x, list) and not x):
            continue
        if not (isinstance(x, list) and len(x) == 2):
            ck.fail(f"{field}.x.{k}", f"expected null or two numbers [phi, u], got {_show(x)}")
        for j, v in enumerate(x):
            ck.number(v, f"{field}.x.{k}.{j}")
    return dict(s)
