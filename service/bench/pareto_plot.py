"""The solvers benchmark's speed-against-error plot (docs/bench/solvers_pareto.png)."""
from __future__ import annotations

import math
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont


def pareto_plot(results: dict, path: Path) -> None:
    """Time to solution (log x) against objective / best (y) per solver, one panel per scene, with the
    Pareto front joined (PIL only: no plotting dependency)."""
    W, H, M = 520, 380, 60
    font = ImageFont.load_default(size=12)
    img = Image.new("RGB", (W * len(results), H), "white")
    dr = ImageDraw.Draw(img)
    palette = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
               (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
    for p, (scene, res) in enumerate(results.items()):
        pts = {m: (r["time_ms_p50"], r["objective_over_best_p50"]) for m, r in res.items() if isinstance(r, dict) and "time_ms_p50" in r}
        x0 = p * W
        tmin, tmax = min(t for t, _ in pts.values()), max(t for t, _ in pts.values())
        lx0, lx1 = math.log10(tmin) - 0.1, math.log10(tmax) + 0.1
        ymax = max(1.05, max(y for _, y in pts.values()) * 1.02)

        def xy(t, y):
            return (x0 + M + (math.log10(t) - lx0) / (lx1 - lx0) * (W - 2 * M),
                    H - M - (y - 1.0) / (ymax - 1.0) * (H - 2 * M))

        dr.rectangle([x0 + M, M, x0 + W - M, H - M], outline="black")
        dr.text((x0 + M, 15), f"{scene}: time p50 (ms, log) vs objective / best", fill="black", font=font)
        for e in range(math.floor(lx0), math.ceil(lx1) + 1):
            for mant in (1, 2, 5):
                t = mant * 10 ** e
                if lx0 <= math.log10(t) <= lx1:
                    X, _ = xy(t, 1.0)
                    dr.line([X, H - M, X, H - M + 4], fill="black")
                    dr.text((X - 8, H - M + 8), f"{t:g}", fill="black", font=font)
        for k in range(5):
            y = 1.0 + k * (ymax - 1.0) / 4
            _, Y = xy(tmin, y)
            dr.line([x0 + M - 4, Y, x0 + M, Y], fill="black")
            dr.text((x0 + 8, Y - 6), f"{y:.3f}", fill="black", font=font)
        front = sorted(pts.items(), key=lambda kv: kv[1][0])
        best_y, chain = math.inf, []
        for m, (t, y) in front:
            if y < best_y:
                best_y = y
                chain.append(xy(t, y))
        if len(chain) > 1:
            dr.line(chain, fill=(160, 160, 160), width=2)
        for i, (m, (t, y)) in enumerate(sorted(pts.items())):
            X, Y = xy(t, y)
            c = palette[i % len(palette)]
            dr.ellipse([X - 4, Y - 4, X + 4, Y + 4], fill=c)
            dr.text((x0 + W - M - 150, M + 8 + 13 * i), f"o {m}", fill=c, font=font)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
