"""`tune --engine babylon --emit`'s module in real Babylon.js (@babylonjs/core 9.35.0 from npm, Chromium headless,
the module imported as it is into tests/babylon_harness/): the wrong pixels Babylon's own CascadedShadowGenerator
shows with the tuned settings on the demo scene, against exact ray-traced visibility of the same screen
(tests/web_engine_kit.py, as tests/test_babylon_module.py scores them), are within 1.3x + 50 of what the emulation
predicts (issue 26's fidelity target); the module installs the tuned settings and dispose() restores what it changed.
One pose, a small screen. The refusals (an unknown knob, a value out of range: exit 2 / HTTP 422 naming
settings.<knob>) are unit tests."""
from __future__ import annotations

import json

import numpy as np
import pytest

from web_engine_kit import (BABYLON, DEMO, DEPTH_TOLERANCE, SCREEN, babylon_fallback, babylon_files, geometry,
                            launch_browser, render_page)

TO_BABYLON = (-1.0, 1.0, 1.0)  # solvers.conventions.ENGINE_PRESETS["babylon"] axes ("-x", "y", "z")
RIG = {"camera": {"usd_path": "/World/Camera", "resolution": list(SCREEN)}, "lights": [{"usd_path": "/World/Sun"}],
       "shadow": {"resolution": [512, 512]}}


@pytest.fixture(scope="module")
def browser():
    yield from launch_browser(BABYLON / "index.js", "Babylon.js (npm install --prefix out/web @babylonjs/core@9.35.0)")


def _to_babylon(v) -> list:
    return [float(a) * s for a, s in zip(v, TO_BABYLON)]


@pytest.mark.browser
def test_tuned_cascades_in_babylon_js_show_what_the_emulation_predicts(browser, tmp_path):
    from shadowopt.api.cli import main
    from shadowopt.renderers.ground_truth import evaluate_buffers
    from shadowopt.service.pipeline import scene_entry
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.solvers.engine_fits import babylon

    entry = scene_entry(str(DEMO))
    (tmp_path / "rig.json").write_text(json.dumps(RIG))
    out, js = tmp_path / "tuned.json", tmp_path / "apply.js"
    assert main(["tune", str(DEMO), "--rig", str(tmp_path / "rig.json"), "--engine", "babylon", "--out", str(out),
                 "--emit", str(js)]) == 0
    res = json.loads(out.read_text())
    s = res["settings"]
    resolved = resolve_rig(RIG, entry.loaded)
    camera, light = resolved.camera, resolved.lights[0]
    cam = {"position": _to_babylon(camera.position), "forward": _to_babylon(camera.forward),
           "up": _to_babylon(camera.up), "fov_y_deg": camera.fov_y_deg, "near": camera.near, "far": camera.far}
    sun = res["light_direction"]
    files = babylon_files(**{"/apply.js": js.read_bytes(), "/scene.bin": geometry(entry, sun, TO_BABYLON)})
    page = render_page(browser, files, babylon_fallback, {"screen": list(SCREEN), "geometry": "/scene.bin",
                                                          "module": "/apply.js", "sun_direction": _to_babylon(sun),
                                                          "camera": cam})

    # the pixels where Babylon's rasterizer and the ray caster see the same surface, scored against exact visibility
    maps = babylon.fit(camera, light, s, casters_box=entry.loaded.geometry.bounds())
    gt = evaluate_buffers(entry.rays, camera, light, maps, screen=SCREEN, pancake=babylon.pancakes(s),
                          depth="solution")
    zb, zr = page["depth"].astype(np.float64), gt.screen.depth
    with np.errstate(invalid="ignore"):
        same = (zb > 0) & gt.screen.hit & (np.abs(zb - zr) <= DEPTH_TOLERANCE * zr)
    keep = gt.receivers & same
    wrong = keep & ((page["alpha"] > 127) != gt.exact_shadowed)
    babylon_wrong = int(wrong.sum())
    predicted = res["predicted"]["misclassified_pixels"]
    report = {"babylon_wrong": babylon_wrong, "babylon_wrongly_lit": int((wrong & gt.exact_shadowed).sum()),
              "predicted": predicted, "emulated_evaluate": gt.result["misclassified_pixels"],
              "compared": int(keep.sum()), "receivers": int(gt.receivers.sum()),
              "exact_shadowed": int((keep & gt.exact_shadowed).sum()),
              "defaults_predicted": res["defaults"]["predicted"]["misclassified_pixels"], "settings": s}
    print("Babylon.js 9.35 CascadedShadowGenerator, tuned settings, vs the emulation:", report)
    assert report["compared"] >= 0.95 * report["receivers"] and report["exact_shadowed"] >= 300, report
    assert babylon_wrong <= 1.3 * predicted + 50 and predicted <= 1.3 * babylon_wrong + 50, report
    assert predicted <= 0.7 * report["defaults_predicted"], report  # issue 26: tune <= 0.7x the defaults

    inst = page["installed"]
    assert inst["filter"] == 0 and inst["mapSize"] == s["mapSize"] and inst["receive"], inst  # FILTER_NONE
    assert inst["bias"] == pytest.approx(s["bias"]) and inst["normalBias"] == 0, inst
    assert page["restored"] == {"builder": True, "receive": False, "generator": False}, page["restored"]
