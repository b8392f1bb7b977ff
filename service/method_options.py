"""Options a method would ignore are refused, not dropped silently: `check_options` raises OptionError naming the
field (the REST field path: `solver`, `time_budget_ms`, `previous`, `hysteresis`, `rig.shadow.<name>`) and why.
The CLI answers it with exit 2 naming its flag, the REST API with 422 naming the field.

What each method reads (service.solve's MethodKind per method):
- `solver`, `time_budget_ms`, `previous`: the searching methods only, optimized and path (the baselines and
  stable_csm are closed-form fits; a baseline's split search with splits "optimized" has no time bound).
- `hysteresis`: optimized with `previous` (path holds its texel grid with its own factor,
  solvers.path_optimize.HYSTERESIS).
- `shadow.lambda`: the practical splits' weight (splits "practical"); `shadow.max_cascades`: cascades "auto";
  `shadow.fixed_resolution`: keeps the resolution against `target_p95_m`; `target_p95_m` lowers the resolution
  of every method but path, which holds each cascade's world-fixed grid from frame to frame (with cascades
  "auto" it still picks the count, so there `fixed_resolution: true` says the resolution is meant to stay).
- `shadow.splits` "optimized" is honoured by every method with cascades (stable_csm takes the searched splits
  inside its shadow distance).
Only options the caller gave are checked (None: not given)."""
from __future__ import annotations

from .methods import METHODS
from .rigs import FieldError

SEARCHING = ("optimized", "path")
DEFAULT_LAMBDA = 0.5  # api.schemas.ShadowSpec's defaults: a rig that does not set them reads these
DEFAULT_MAX_CASCADES = 4


class OptionError(FieldError):
    """An option the method would ignore (`field` the request's field path)."""

    code = "unused_option"


def check_options(method: str, shadow: dict | None = None, *, solver=None, time_budget_ms=None, previous=None,
                  hysteresis=None) -> None:
    """OptionError for the first option `method` would ignore (module doc); None when each is used."""
    if method not in METHODS:
        return  # service.solve refuses an unknown method by name
    closed = f"method {method} is a closed-form fit (only {' and '.join(SEARCHING)} search)"
    if solver is not None and method not in SEARCHING:
        raise OptionError("solver", f"{closed}: it runs no solver")
    if time_budget_ms is not None and method not in SEARCHING:
        raise OptionError("time_budget_ms", f"{closed}: there is no search to bound")
    if previous is not None and method not in SEARCHING:
        raise OptionError("previous", f"{closed}: it reads no previous frame (optimized keeps the previous setup "
                                      "with hysteresis, path its texel grid)")
    if hysteresis is not None:
        if method != "optimized":
            raise OptionError("hysteresis", f"applies to method optimized only (method {method} "
                              + ("holds its texel grid with its own factor)" if method == "path" else "keeps nothing)"))
        if previous is None:
            raise OptionError("hysteresis", "applies only with a previous solution (the setup it keeps or replaces)")
    shadow = shadow or {}
    splits = shadow.get("splits", "practical")
    lam = shadow.get("lambda", DEFAULT_LAMBDA)
    if lam is not None and lam != DEFAULT_LAMBDA and splits != "practical":
        raise OptionError("rig.shadow.lambda", f"weighs the practical splits only; splits is {splits!r}")
    cascades = shadow.get("cascades", 1)
    kmax = shadow.get("max_cascades", DEFAULT_MAX_CASCADES)
    if kmax is not None and kmax != DEFAULT_MAX_CASCADES and cascades != "auto":
        raise OptionError("rig.shadow.max_cascades", f"bounds cascades \"auto\" only; cascades is {cascades!r}")
    target = shadow.get("target_p95_m")
    if shadow.get("fixed_resolution") and target is None:
        raise OptionError("rig.shadow.fixed_resolution", "keeps the resolution against target_p95_m, which is not "
                          "given")
    if method == "path" and target is not None and not shadow.get("fixed_resolution"):
        raise OptionError("rig.shadow.target_p95_m", "method path holds each cascade's world-fixed texel grid "
                          "from frame to frame and never lowers its resolution"
                          + (" (with cascades \"auto\" it picks the count: set fixed_resolution true)"
                             if cascades == "auto" else "; cascades is not \"auto\", so nothing reads it"))
