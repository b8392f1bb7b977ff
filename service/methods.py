"""The shadow methods a solve accepts: one list for the CLI's choices (optimize, compare, batch), the REST schema's
`Method` and service.solve. No imports: the bare client (api.schemas) reads it too."""

BASELINE_METHODS = ("uniform", "focused", "lispsm", "logpsm")
# stable_csm: solvers.stable_csm (Valient 2008); path: solvers.path_optimize (previous= the previous frame)
METHODS = BASELINE_METHODS + ("optimized", "stable_csm", "path")
