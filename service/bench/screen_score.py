"""An engine's shadowed pixels scored against the product's exact ray-traced visibility of the same screen
(renderers.ground_truth.evaluate_buffers, what `evaluate --depth solution` runs): only the receivers where the
engine's rasterizer and the ray caster see the same surface (both hit, view depths within DEPTH_TOLERANCE) are
compared. Shared by `shadowopt bench engines` and the browser tests (tests/web_engine_kit.py)."""
from __future__ import annotations

import numpy as np

DEPTH_TOLERANCE = 0.01  # relative view-depth difference under which both renderers hit the same surface


def score_screen(gt, rendered: dict) -> dict:
    """`gt`: evaluate_buffers' result for a solution (its verdicts: gt.misclassified); `rendered`: the page's
    {alpha (255: the engine shadows), depth (view depth, 0: no hit)}. Counts on the compared receivers, wrongly lit
    and wrongly shadowed apart, evaluate's own count there and on the whole screen, and engine_vs_evaluate: the pixels
    where the engine's verdict and evaluate's differ."""
    ze, zr = rendered["depth"].astype(np.float64), gt.screen.depth
    with np.errstate(invalid="ignore"):
        same = (ze > 0) & gt.screen.hit & (np.abs(ze - zr) <= DEPTH_TOLERANCE * zr)
    keep = gt.receivers & same
    shadowed = rendered["alpha"] > 127
    exact = gt.exact_shadowed
    wrong = keep & (shadowed != exact)
    return {"receivers": int(gt.receivers.sum()), "compared": int(keep.sum()),
            "exact_shadowed": int((keep & exact).sum()), "engine_shadowed": int((keep & shadowed).sum()),
            "engine_wrong": int(wrong.sum()), "engine_wrongly_lit": int((wrong & exact).sum()),
            "engine_wrongly_shadowed": int((wrong & ~exact).sum()),
            "evaluate_wrong_compared": int((keep & gt.misclassified).sum()),
            "evaluate_wrong": gt.result["misclassified_pixels"],
            "engine_vs_evaluate": int((keep & (shadowed != (exact ^ gt.misclassified))).sum())}
