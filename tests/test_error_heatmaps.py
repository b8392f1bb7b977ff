"""The errors heatmap (`evaluate --heatmap-mode errors`) against the ground truth it draws, the legends every
written heatmap carries, and the pixels each number is in (predicted: the rig's; measured: the screen's).
In-process on the demo scene with a small rig and a coarse map, so both kinds of misclassification occur."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from shadowopt.renderers.ground_truth import evaluate_buffers
from shadowopt.renderers.heatmap import (KEY, LIT_GREY, OUTSIDE, SHADOWED_GREY, WRONGLY_LIT, WRONGLY_SHADOWED,
                                         errors_image, errors_legend, ground_truth_heatmap)
from shadowopt.service.compare import compare
from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.pipeline import scene_entry
from shadowopt.service.rigs import FieldError, resolve_rig
from shadowopt.service.request import SolveRequest
from shadowopt.service.solution_json import maps_from_solution
from shadowopt.service.solve import solve

RIG = {"camera": {"usd_path": "/World/Camera", "resolution": [320, 180]}, "lights": [{"usd_path": "/World/Sun"}],
       "shadow": {"resolution": [64, 64], "cascades": 1}}
W, H = RIG["camera"]["resolution"]


@pytest.fixture(scope="module")
def case(repo):
    from shadowopt.api.cli import validate_rig

    entry = scene_entry(repo / "configs" / "demo_scene.usda")
    rig = validate_rig(RIG)
    sol = solve(entry, rig, SolveRequest(method="lispsm"))
    resolved = resolve_rig(rig, entry.loaded)
    # The independent truth: the ground truth's own masks for the solution's maps.
    # (evaluate's default depth test: each map's stated engine depth test, as evaluate_solution applies it)
    gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(sol)[0], depth="solution")
    return entry, rig, sol, gt


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def _is(img, colour) -> np.ndarray:
    return np.all(img == np.array(colour), axis=-1)


def test_errors_image_colours_exactly_the_misclassified_pixels(tmp_path, case):
    entry, rig, sol, gt = case
    path = tmp_path / "errors.png"
    ev = evaluate_solution(entry, rig, sol, heatmap_path=str(path), heatmap_mode="errors")
    full = _png(path)
    top = full[:H, :W]
    shadowed, lit = _is(top, WRONGLY_SHADOWED), _is(top, WRONGLY_LIT)
    wrongly_shadowed = gt.receivers & gt.map_shadowed & ~gt.exact_shadowed
    wrongly_lit = gt.receivers & gt.exact_shadowed & ~gt.map_shadowed
    assert wrongly_shadowed.sum() > 10 and wrongly_lit.sum() > 10  # both kinds occur: the test can fail
    assert np.array_equal(shadowed, wrongly_shadowed) and np.array_equal(lit, wrongly_lit)
    assert np.array_equal(shadowed | lit, gt.misclassified)
    grey = (top[..., 0] == top[..., 1]) & (top[..., 1] == top[..., 2])
    assert np.array_equal(grey, ~gt.misclassified)  # every other pixel is a grey of the shading
    right = gt.receivers & ~gt.misclassified
    assert np.all(_is(top, LIT_GREY)[right & ~gt.exact_shadowed]) and np.all(_is(top, SHADOWED_GREY)[right & gt.exact_shadowed])
    # The counts the evaluation reports are the picture's.
    assert ev["misclassified_pixels"] == int(gt.misclassified.sum()) == int(shadowed.sum() + lit.sum())
    assert (ev["wrongly_shadowed_pixels"], ev["wrongly_lit_pixels"]) == (int(shadowed.sum()), int(lit.sum()))
    assert ev["heatmap_mode"] == "errors"
    # The legend below the picture shows both colours.
    legend = full[H:]
    assert legend.shape[0] > 40 and _is(legend, WRONGLY_SHADOWED).sum() > 50 and _is(legend, WRONGLY_LIT).sum() > 50
    counted = np.asarray(errors_legend(W, {"wrongly_shadowed_pixels": 1, "wrongly_lit_pixels": 2})).astype(int)
    drawn = np.asarray(errors_legend(W, ev)).astype(int)  # what evaluate wrote below the picture (4 px gap)
    assert np.array_equal(legend[4:4 + drawn.shape[0], :W], drawn)
    assert not np.array_equal(counted, drawn)  # the counts are written in it
    # A texel grid is drawn on the greys only: the coloured pixels stay exactly the misclassified ones.
    gridded = np.asarray(errors_image(gt, grid_every=4)).astype(int)
    assert np.array_equal(_is(gridded, WRONGLY_SHADOWED), wrongly_shadowed)
    assert np.array_equal(_is(gridded, WRONGLY_LIT), wrongly_lit)
    assert np.any(gridded != top)


def test_the_m_heatmap_carries_its_legend(tmp_path, case):
    entry, rig, sol, gt = case
    path = tmp_path / "m.png"
    ev = evaluate_solution(entry, rig, sol, heatmap_path=str(path))
    full = _png(path)
    assert ev["heatmap_mode"] == "m" and full.shape[0] > H + 40 and full.shape[1] >= W
    assert np.array_equal(full[:H, :W], np.asarray(ground_truth_heatmap(gt)).astype(int))
    legend = full[H:]
    for colour in (KEY[0][1], KEY[-1][1], OUTSIDE):  # the key's ends and the outside swatch
        assert _is(legend, colour).sum() > 20, colour


def test_a_bad_heatmap_mode_names_the_field(case):
    entry, rig, sol, _ = case
    with pytest.raises(FieldError) as e:
        evaluate_solution(entry, rig, sol, heatmap_path=None, heatmap_mode="aliasing")
    assert e.value.field == "heatmap_mode" and "errors" in e.value.message


def test_measured_numbers_name_their_screen_and_convert_to_the_rigs_pixels(case):
    entry, rig, sol, _ = case
    at_rig = evaluate_solution(entry, rig, sol)
    assert at_rig["screen"] == at_rig["rig_resolution"] == [W, H] and "measured_error_rig_pixels" not in at_rig
    half = evaluate_solution(entry, rig, sol, screen=(W // 2, H // 2))
    assert half["screen"] == [W // 2, H // 2] and half["rig_resolution"] == [W, H]
    assert "160x90 screen's pixels" in half["pixels"] and "rig's 320x180 pixels" in half["pixels"]
    # A footprint of m screen pixels is 2m rig pixels here (half the pixels along each side); h = |F|^2: 4x.
    me, mr = half["measured_error"], half["measured_error_rig_pixels"]
    for k in ("mean_m", "median_m", "p95_m", "max_m"):
        assert mr[k] == pytest.approx(2 * me[k], rel=1e-12), k
    assert mr["objective"] == pytest.approx(4 * me["objective"], rel=1e-12) and mr["samples"] == me["samples"]


def test_compare_with_a_screen_predicts_what_optimize_predicts(tmp_path, case):
    entry, rig, _, _ = case
    res = compare(entry, rig, ["lispsm", "optimized"], screen=(W // 2, H // 2), report_dir=tmp_path)
    assert res["screen"] == [W // 2, H // 2] and res["rig_resolution"] == [W, H]
    for name, r in res["methods"].items():
        assert r["predicted_error"] == solve(entry, rig, SolveRequest(method=name))["lights"][0]["predicted_error"], name
        e = r["evaluation"]
        assert e["screen"] == [W // 2, H // 2] and e["wrongly_shadowed_pixels"] + e["wrongly_lit_pixels"] == e["misclassified_pixels"]
    table = (tmp_path / "compare.md").read_text()
    assert "predicted p95 m (320x180)" in table and "measured p95 m (160x90)" in table and "errors.png" in table
    # errors.png: the methods side by side, each picture's coloured pixels its own misclassified ones.
    img = _png(res["report"]["errors"])
    coloured = _is(img, WRONGLY_SHADOWED) | _is(img, WRONGLY_LIT)
    pictures = coloured[:img.shape[0] - errors_legend(360).height - 16]  # above the shared legend (2 gaps below it)
    gap, w = 8, W // 2
    counts = [int(pictures[:, gap + k * (w + gap): gap + k * (w + gap) + w].sum()) for k in range(2)]
    assert counts == [r["evaluation"]["misclassified_pixels"] for r in res["methods"].values()] and sum(counts) > 0
    assert pictures.sum() == sum(counts)
