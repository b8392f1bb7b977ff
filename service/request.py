"""What a caller asks of one solve (service.solve.solve) beside the scene and the rig: the method and the
search's settings, their defaults stated here once. The API converts its pydantic OptimizeRequest into it
(service never imports api); the CLI its arguments. Nothing is validated here that the API already validates:
service.solve refuses an unknown method and a malformed previous solution."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SolveRequest:
    method: str = "focused"  # a baseline name, "optimized", "stable_csm" or "path" (service.solve.METHODS)
    solver: str | None = None  # the search's optimizer (methods optimized, path); None: solvers.optimize.DEFAULT_METHOD
    time_budget_ms: float | None = None  # the search's time over the whole solve (service.solve.solve); None: no bound
    previous: dict | None = None  # the previous frame's solution (optimized: its x, kept with hysteresis; path: its grid)
    hysteresis: float = 0.8  # optimized with previous: the previous setup is kept unless the new one's median h is below this x its own
    cache_tenant: str | None = None  # the camera part cached per tenant and scene (service.coarse_cache); None: no cache
