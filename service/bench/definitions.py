"""What the benchmarks run on: configs/benchmarks.json and configs/corpus.json (paths there are
relative to the repository root), the corpus's scenes, the seeded suns on the hemisphere, and the
method configurations of Chong & Gortler's protocol."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...renderers.corpus import ensure_scene

ROOT = Path(__file__).resolve().parents[2]


def definitions() -> dict:
    return json.loads((ROOT / "configs" / "benchmarks.json").read_text())


def hemisphere_directions(n: int, min_elevation_deg: float, seed: int):
    """n light directions (the way light travels) uniform on the upper hemisphere above an elevation."""
    rng = np.random.default_rng(seed)
    zmin = np.sin(np.radians(min_elevation_deg))
    y = rng.uniform(zmin, 1.0, n)  # uniform in height = uniform in solid angle
    phi = rng.uniform(0, 2 * np.pi, n)
    r = np.sqrt(1 - y * y)
    return np.stack([-r * np.cos(phi), -y, -r * np.sin(phi)], axis=1)


def quality_configs(spec: dict, parts=("single", "cascades")) -> dict:
    """The configurations of Chong & Gortler's protocol, per part: `single`: one map per method;
    `cascades`: 4 cascades under one texel budget (configs/benchmarks.json's `quality`)."""
    configs = {}
    if "single" in parts:
        configs["single"] = {m: {"method": m, "shadow": {"resolution": spec["map"], "cascades": 1}} for m in spec["methods"]}
    if "cascades" in parts:
        configs["cascades"] = spec["cascades"]["configs"]
    return configs


def corpus_definitions() -> dict:
    return json.loads((ROOT / definitions()["quality_corpus"]["corpus"]).read_text())


def corpus_scenes(names=None, cache_dir=None) -> tuple[dict, dict]:
    """The corpus's scenes (configs/corpus.json) as {name: (path, scene spec)}, generated ones built
    into the cache folder (renderers.corpus.ensure_scene), plus {name: why} for those that are absent
    (../shared/usd-assets not mounted). `names` picks some, in the given order."""
    spec = corpus_definitions()["scenes"]
    wanted = list(names) if names else list(spec)
    unknown = [n for n in wanted if n not in spec]
    if unknown:
        raise ValueError(f"--scenes: unknown corpus scene {unknown[0]!r} (known: {', '.join(spec)})")
    found, skipped = {}, {}
    for name in wanted:
        s = spec[name]
        if "build" in s:
            found[name] = (ensure_scene(s["build"], cache_dir), s)
        else:
            path = (ROOT / s["path"]).resolve()
            if path.exists():
                found[name] = (path, s)
            else:
                skipped[name] = f"{s['path']} is absent"
    return found, skipped
