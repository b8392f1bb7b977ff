"""The fitted depth bias and the prediction that includes it (solvers.bias_fit, renderers.depth_probe,
service.bias): the chooser finds the least count a brute force finds, the probe answers as `evaluate` does,
the prediction matches what evaluate measures, pinned terms are kept, and what the target engine cannot
apply is never chosen."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shadowopt.solvers.bias_fit import BIAS_TARGETS, fit_constant, probe_shadowed
from shadowopt.solvers.engine_depth_test import DepthProbe, engine_shadowed, quantize_depth

REPO = Path(__file__).resolve().parents[1]


def _brute_force(margin, lit, a):
    """The least weighted count over every c >= 0 that separates the sorted margins differently."""
    cands = np.unique(np.concatenate([[0.0], margin[margin >= 0], np.nextafter(margin[margin >= 0], np.inf)]))
    best = np.inf
    for c in cands:
        shadowed = margin > c
        best = min(best, float(np.sum(a[shadowed & lit]) + np.sum(a[~shadowed & ~lit])))
    return best


@pytest.mark.parametrize("seed", range(6))
def test_fit_constant_finds_the_count_a_brute_force_finds_and_its_c_gives_it(seed):
    rng = np.random.default_rng(seed)
    n = 300
    lit = rng.random(n) < 0.6
    # lit receivers: acne margins around 0; shadowed: gaps to the caster from contact (0) to far
    margin = np.where(lit, rng.normal(0, 1e-4, n), rng.exponential(3e-3, n) * (rng.random(n) < 0.8))
    margin = np.round(margin, 6)  # ties, as a 16-bit buffer makes them
    a = rng.uniform(0.5, 2.0, n)
    c, wrong = fit_constant(margin, lit, a)
    assert c >= 0
    assert wrong == pytest.approx(_brute_force(margin, lit, a))
    shadowed = engine_shadowed(margin, np.zeros(n), c)  # D_rec - c > stored with stored 0: margin > c
    assert float(np.sum(a[shadowed & lit]) + np.sum(a[~shadowed & ~lit])) == pytest.approx(wrong)


def test_fit_constant_keeps_a_bias_between_acne_and_the_nearest_contact():
    # lit receivers need up to 1e-5, the nearest shadowed contact is 1e-3 away: any c in between is perfect,
    # and the chooser takes the geometric middle (scale-free: margins span decades)
    margin = np.array([-2e-6, 5e-6, 1e-5, 1e-3, 4e-3])
    lit = np.array([True, True, True, False, False])
    c, wrong = fit_constant(margin, lit, np.ones(5))
    assert wrong == 0 and c == pytest.approx(np.sqrt(1e-5 * 1e-3))


def test_unorm_depth_formats_round_to_their_steps():
    D = np.array([0.0, 0.3, 0.123456789, 1.0])
    q16 = quantize_depth(D, "unorm16")
    assert np.allclose(q16 * 65535, np.round(q16 * 65535)) and np.max(np.abs(q16 - D)) <= 0.5 / 65535 + 1e-15
    q24 = quantize_depth(D, "unorm24")
    assert np.max(np.abs(q24 - D)) <= 0.5 / (2 ** 24 - 1) + 1e-15
    assert np.array_equal(quantize_depth(D, "float32"), D.astype(np.float32).astype(np.float64))
    with pytest.raises(ValueError, match="float32, unorm24, unorm16, float16"):
        quantize_depth(D, "unorm8")


def test_half_float_depth_keeps_11_significant_bits():
    """Babylon.js's half-float map: in [0.5, 1) a step is 2^-11, so a value is within 2^-12 of its own; 0.1 is
    within 2^-15 (IEEE 754 binary16, round to nearest)."""
    D = np.array([0.1, 0.5, 0.7, 0.99999, 1.0])
    q = quantize_depth(D, "float16")
    assert np.all(np.abs(q - D) <= np.where(D >= 0.5, 2.0 ** -12, 2.0 ** -15))
    assert q[-2] == 1.0 and q[1] == 0.5 and q[2] * 2 ** 11 == round(q[2] * 2 ** 11)


# --- on the demo scene ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo():
    from shadowopt.api.schemas import validate_rig
    from shadowopt.service.scenes import SceneCache

    entry = SceneCache().get(REPO / "configs" / "demo_scene.usda")
    rig = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    rig["camera"]["resolution"] = [640, 360]
    rig["shadow"] = {"resolution": [1024, 1024], "cascades": 2}
    return entry, rig, validate_rig


def _solve(demo, method="focused", engine=None, **shadow):
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    entry, rig, validate_rig = demo
    r = {**rig, "shadow": {**rig["shadow"], **shadow}}
    if engine:
        r["output"] = {"engine": engine}
    return solve(entry, validate_rig(r), SolveRequest(method=method))


def test_the_probe_answers_as_evaluate_does_at_the_same_points(demo):
    """classify_points is evaluate's lookup (the engine's light pass over every texel, Dr.Jit); the probe casts
    only the texels its points fall in and does the test in NumPy: the same answer at (nearly) every point."""
    from shadowopt.renderers.depth_probe import depth_probe
    from shadowopt.renderers.ground_truth import classify_points
    from shadowopt.service.bias import receivers_of
    from shadowopt.service.pipeline import coarse_pass
    from shadowopt.service.solution_json import maps_from_solution

    entry, rig, validate_rig = demo
    sol = _solve(demo, "optimized")
    maps = maps_from_solution(sol)[0]
    resolved, buffers = coarse_pass(entry, validate_rig(rig))
    light = resolved.lights[0]
    pos, nrm, depth, lit, a = receivers_of(entry.rays, light, buffers, 0)
    modes = [m.depth["mode"] for m in maps]
    probe = depth_probe(entry.rays, light, maps, pos, nrm, depth, modes)
    mine = probe_shadowed(probe, [m.depth[md] for m, md in zip(maps, modes)], maps[0].depth.get("format", "float32"))
    theirs = classify_points(entry.rays, light, maps, pos, nrm, depth, depth="solution")
    assert np.array_equal(probe.map_index, theirs["map_index"])
    assert np.mean(mine != theirs["shadowed"]) <= 1e-3, np.sum(mine != theirs["shadowed"])
    assert mine.sum() > 100 and (~mine).sum() > 100  # both answers occur


@pytest.mark.slow
def test_the_prediction_matches_what_evaluate_measures_and_the_fitted_bias_beats_the_rule(demo):
    from shadowopt.renderers.ground_truth import evaluate
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.solution_json import maps_from_solution

    entry, rig, validate_rig = demo
    r = resolve_rig(validate_rig(rig), entry.loaded)
    got = {}
    for method in ("optimized", "uniform"):
        for bias in ("fitted", "rule"):
            sol = _solve(demo, method, bias=bias)
            pe = sol["lights"][0]["predicted_error"]
            res = evaluate(entry.rays, r.camera, r.lights[0], maps_from_solution(sol)[0], depth="solution")
            got[method, bias] = (pe["misclassified_pixels"], res["misclassified_pixels"])
            assert pe["misclassified_pixels"] == pytest.approx(pe["wrongly_lit_pixels"] + pe["wrongly_shadowed_pixels"])
            assert pe["bias"] == bias
    # a count of a few dozen pixels is itself noisy (a contact band under a pixel wide: the same maps measure
    # 91, 154 / 4, 584 / 9 at 640x360, 1280x720, 1920x1080), so the magnitude is checked on the pooled count
    pred, meas = (sum(v[i] for v in got.values()) for i in (0, 1))
    assert 0.5 <= meas / pred <= 2.0, got
    fitted, rule = (sum(got[m, b][1] for m in ("optimized", "uniform")) for b in ("fitted", "rule"))
    assert fitted <= 1.15 * rule + 10, got
    assert got["optimized", "fitted"][0] < got["uniform", "fitted"][0]  # the ranking the measurement shows
    assert got["optimized", "fitted"][1] < got["uniform", "fitted"][1]


def test_pinned_terms_are_kept_and_the_others_fitted(demo):
    sol = _solve(demo, depth={"constant": 0.0004, "slope_scaled": 0.0})
    for c in sol["lights"][0]["cascades"]:
        block = c["depth"]
        entry = block[block["mode"]]
        assert entry["constant"] == 0.0004 and entry["slope_scaled"] == 0.0
        assert block["chosen_by"] == "fitted"


@pytest.mark.parametrize("field,value,why", [("constant", -0.1, "greater than or equal to 0"),
                                              ("constant", 2.0, "less than or equal to 1"),
                                              ("slope_scaled", float("inf"), "finite number"),
                                              ("mode", "window", "'hardware' or 'linear'")])
def test_a_pinned_term_out_of_range_is_refused_naming_the_field(demo, field, value, why):
    from pydantic import ValidationError

    entry, rig, validate_rig = demo
    with pytest.raises(ValidationError) as e:
        validate_rig({**rig, "shadow": {**rig["shadow"], "depth": {field: value}}})
    assert f"shadow.depth.{field}" in str(e.value).replace("\n", ".").replace(" ", "") or field in str(e.value)
    assert why in str(e.value)


def test_each_engine_gets_only_the_terms_it_applies(demo):
    three = _solve(demo, engine="three")["lights"][0]["cascades"]
    for c in three:  # three.js: a receiver-side constant per shadow, no slope term, a 24-bit buffer, window z
        assert c["depth"]["mode"] == "hardware" and c["depth"]["hardware"]["slope_scaled"] == 0.0
        assert c["depth"]["format"] == "unorm24"
    godot = _solve(demo, engine="godot")["lights"][0]["cascades"]
    # Godot: one bias per light (the engine scales it per cascade itself), a 16-bit atlas
    assert len({c["depth"]["hardware"]["constant"] for c in godot}) == 1
    assert all(c["depth"]["format"] == "unorm16" for c in godot)
    assert BIAS_TARGETS["godot"]["per_map"] is False and BIAS_TARGETS[None]["per_map"] is True


def test_rule_keeps_the_fixed_rule_and_still_predicts_with_the_engine_test(demo):
    sol = _solve(demo, bias="rule")
    pe = sol["lights"][0]["predicted_error"]
    assert pe["bias"] == "rule" and pe["misclassified_pixels"] >= 0
    for c in sol["lights"][0]["cascades"]:
        assert "chosen_by" not in c["depth"] and c["depth"]["hardware"]["slope_scaled"] == 1.0


def test_the_cli_refuses_a_pinned_term_out_of_range_with_exit_2_naming_it(tmp_path, capsys):
    from shadowopt.api.cli import main

    rig = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    rig["shadow"]["depth"] = {"constant": float("nan")}
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(rig).replace("NaN", "1e999"))  # JSON has no NaN: an overflowing number reads as inf
    code = main(["optimize", str(REPO / "configs" / "demo_scene.usda"), "--rig", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "shadow.depth.constant" in err and "finite" in err, err
    assert "Traceback" not in err


def test_a_caster_side_constant_is_rounded_with_the_casters_depth():
    """Babylon.js adds its bias to the caster's metric before the half-float map rounds it (constant_side caster):
    a caster 0.4 steps above a grid value with a constant of 0.3 steps stores the next value up, so a receiver 0.4
    steps behind it is lit, where a receiver-side constant (rounding the caster down, then subtracting) shadows it."""
    step = 2.0 ** -12  # float16 in [0.25, 0.5)
    q = 0.3 - (0.3 % step)
    one = np.ones(1)
    probe = DepthProbe("linear", np.zeros(1, int), np.ones(1, bool), np.array([q + 0.8 * step]),
                       np.array([q + 0.4 * step]), np.zeros(1), one, np.zeros(1, int), np.zeros(1))
    terms = {"constant": 0.3 * step, "slope": 0.0, "slope_scaled": 0.0, "slope_clamp": 1.0}
    assert probe_shadowed(probe, [terms], "float16")[0]
    assert not probe_shadowed(probe, [{**terms, "constant_side": "caster"}], "float16")[0]
