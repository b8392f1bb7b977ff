"""The corpus benchmark's report (service.bench.quality_report, service.bench.corpus_tables.scene_stats) on tiny
synthetic records: the numbers it prints against independent computations (scipy's Spearman, a
hand-computed geometric mean and median), records stored before a key existed show "-", and the
speed-against-error plot is a real image."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import spearmanr

from shadowopt.service.bench import quality_report as qr
from shadowopt.service.bench.corpus_tables import scene_stats as _scene_stats, tables_corpus as _tables_corpus
from shadowopt.service.bench.definitions import definitions

METHODS = ("uniform", "focused", "lispsm", "logpsm", "optimized")


def _record(n_suns=4, seed=0, with_limit=True, with_hd=False):
    """A quality_scene record for the single part: objective, misclassified and ratio per sun."""
    rng = np.random.default_rng(seed)
    rec = {k: {"single": {}} for k in ("misclassified", "outside", "boundary", "receivers", "setup_ms", "objective",
                                       "limit", "ratio_to_limit", "run_s")}
    for j, m in enumerate(METHODS):
        obj = rng.uniform(1, 50, n_suns)
        rec["objective"]["single"][m] = obj.tolist()
        rec["misclassified"]["single"][m] = np.round(obj * 10 * rng.uniform(0.5, 2, n_suns)).tolist()
        rec["outside"]["single"][m] = [0] * n_suns
        rec["boundary"]["single"][m] = [100] * n_suns
        rec["receivers"]["single"][m] = [1000] * n_suns
        rec["setup_ms"]["single"][m] = (10.0 * (j + 1) + np.arange(n_suns)).tolist()
        rec["run_s"]["single"][m] = [0.1] * n_suns
        rec["limit"]["single"][m] = [0.5] * n_suns if with_limit else [None] * n_suns
        rec["ratio_to_limit"]["single"][m] = (obj / 0.5).tolist() if with_limit else [None] * n_suns
    if not with_limit:
        del rec["limit"], rec["ratio_to_limit"]
    if with_hd:
        rec["outside_hd"] = {"single": {m: [0, 3 if m == "lispsm" else 0] for m in METHODS}}
        rec["receivers_hd"] = {"single": {m: [2_000_000] * 2 for m in METHODS}}
        rec["setup_ms_hd"] = {"single": {m: [20.0, 22.0] for m in METHODS}}
    return rec


def _dirs(n):
    return np.tile([[-0.3, -0.9, 0.3]], (n, 1))


def test_calibration_matches_independent_computation():
    rng = np.random.default_rng(1)
    pred = rng.uniform(0.5, 100, 40)
    meas = np.round(pred * 7 * rng.lognormal(0, 0.4, 40))
    meas[3] = 0  # no log ratio: left out of the fit, kept in the Spearman
    c = qr.calibration(pred, meas)
    assert c["spearman"] == pytest.approx(spearmanr(pred, meas).statistic, abs=1e-12)
    keep = meas > 0
    ratios = meas[keep] / pred[keep]
    assert c["factor"] == pytest.approx(math.prod(ratios) ** (1 / len(ratios)), rel=1e-9)  # geometric mean
    assert c["median"] == pytest.approx(np.median(ratios), rel=1e-9)
    assert c["left_out"] == 1 and c["n"] == 40
    assert c["p10"] < 1 < c["p90"]


def test_calibration_of_an_exact_prediction_is_its_factor_with_no_spread():
    pred = np.array([1.0, 2.0, 5.0, 9.0])
    c = qr.calibration(pred, 3 * pred)
    assert c["factor"] == pytest.approx(3) and c["median"] == pytest.approx(3)
    assert c["p10"] == pytest.approx(1) and c["p90"] == pytest.approx(1) and c["spearman"] == pytest.approx(1)
    assert qr.calibration([1.0, float("inf"), 2.0], [1, 2, 3])["n"] == 2  # an infinite prediction is not a run


def test_corpus_calibration_relative_factor():
    pred = np.array([1.0, 2.0, 4.0])
    a = {"misclassified": {"single": {"x": (2 * pred).tolist()}}, "objective": {"single": {"x": pred.tolist()}}}
    b = {"misclassified": {"single": {"x": (8 * pred).tolist()}}, "objective": {"single": {"x": pred.tolist()}}}
    cal = qr.corpus_calibration({"a": a, "b": b}, "single")
    assert cal["corpus"]["factor"] == pytest.approx(4)  # geometric mean of 2 and 8
    assert cal["scenes"]["a"]["vs_corpus"] == pytest.approx(0.5) and cal["scenes"]["b"]["vs_corpus"] == pytest.approx(2)


def test_scene_stats_ratio_to_limit_and_calibration_columns():
    spec = definitions()["quality_corpus"]
    rec = _record()
    s = _scene_stats(rec, _dirs(4), spec)["single"]
    for m in METHODS:
        want = np.median(np.asarray(rec["objective"]["single"][m]) / 0.5)
        assert s["ratio_to_limit"][m]["median"] == pytest.approx(want)
        assert s["ratio_to_limit"][m]["max"] == pytest.approx(max(rec["objective"]["single"][m]) / 0.5)
    pred = np.concatenate([rec["objective"]["single"][m] for m in METHODS])
    meas = np.concatenate([rec["misclassified"]["single"][m] for m in METHODS])
    assert s["calibration"]["spearman"] == pytest.approx(spearmanr(pred, meas).statistic, abs=1e-12)
    assert s["spearman_pooled"] == pytest.approx(s["calibration"]["spearman"])
    assert s["outside_hd"] is None and s["hd_suns"] == 0


def test_old_record_without_limit_prints_dashes_and_hd_counts_when_measured():
    spec = {**definitions()["quality_corpus"], "cascades_note": "n/a"}
    old = _scene_stats(_record(with_limit=False), _dirs(4), spec)
    assert all(v is None for v in old["single"]["ratio_to_limit"].values())
    new = _scene_stats(_record(seed=2, with_hd=True), _dirs(4), spec)
    assert new["single"]["outside_hd"]["lispsm"] == 3 and new["single"]["hd_suns"] == 2
    assert new["verdicts"]["outside_0_hd"] is False and old["verdicts"]["outside_0_hd"] is None
    stats = {"old": {**old, "triangles": 1}, "new": {**new, "triangles": 1}}
    raws = {"old": _record(with_limit=False), "new": _record(seed=2, with_hd=True)}
    text = _tables_corpus(stats, {}, spec, None, None, {"single": qr.corpus_calibration(raws, "single")}, {"single": "x.png"})
    row = next(ln for ln in text.splitlines() if ln.startswith("| old | -"))
    assert row.count("| -") == len(METHODS)  # ratio-to-limit row of the old record
    assert "3 (3)" in next(ln for ln in text.splitlines() if ln.startswith("| new | 2 |"))  # the 1920x1080 row
    assert "[x.png](x.png)" in text


def test_speed_error_plot_is_an_image(tmp_path):
    from PIL import Image

    spec = definitions()["quality_corpus"]
    stats = {f"s{i}": {**_scene_stats(_record(seed=i), _dirs(4), spec), "triangles": 1} for i in range(5)}
    se = qr.speed_error(stats)
    assert min(r["vs_best"] for r in se["s0"].values()) == pytest.approx(1.0)
    assert se["s0"]["optimized"]["setup_ms"] == pytest.approx(np.median(_record(seed=0)["setup_ms"]["single"]["optimized"]))
    p = qr.speed_error_plot(se, tmp_path / "p.png")
    img = Image.open(p)
    assert img.size[0] >= 4 * 300 and img.size[1] >= 2 * 250  # 5 panels: 4 per row, two rows
    assert len(np.unique(np.asarray(img.convert("RGB")).reshape(-1, 3), axis=0)) > 5  # markers in several colours, not a blank page


def _with_pixels(rec, seed=5):
    """rec with predicted misclassified pixels: measured times a known factor (2 or 4) and noise in rank."""
    rng = np.random.default_rng(seed)
    rec[qr.PREDICTED_KEY] = {"single": {}}
    for m in METHODS:
        meas = np.asarray(rec["misclassified"]["single"][m], float)
        rec[qr.PREDICTED_KEY]["single"][m] = (meas / rng.choice([2.0, 4.0], len(meas)) + rng.uniform(0, 3, len(meas))).tolist()
    return rec


def test_predicted_pixels_column_against_scipy_and_old_records_show_dashes():
    spec = {**definitions()["quality_corpus"], "cascades_note": "n/a"}
    rec = _with_pixels(_record(n_suns=6, seed=3))
    s = _scene_stats(rec, _dirs(6), spec)
    pp = s["single"]["pixel_prediction"]
    pred = np.concatenate([rec[qr.PREDICTED_KEY]["single"][m] for m in METHODS])
    meas = np.concatenate([rec["misclassified"]["single"][m] for m in METHODS])
    obj = np.concatenate([rec["objective"]["single"][m] for m in METHODS])
    assert pp["n"] == 30 and pp["spearman"] == pytest.approx(spearmanr(pred, meas).statistic, abs=1e-12)
    assert pp["spearman_objective"] == pytest.approx(spearmanr(obj, meas).statistic, abs=1e-12)
    assert pp["median"] == pytest.approx(np.median(meas / pred)) and pp["p90"] == pytest.approx(np.percentile(meas / pred, 90))
    assert s["verdicts"]["spearman_pixels"] is bool(pp["spearman"] >= spec["targets"]["spearman"])
    old = _scene_stats(_record(n_suns=6, seed=3), _dirs(6), spec)
    assert old["single"]["pixel_prediction"] is None and old["verdicts"]["spearman_pixels"] is None
    text = _tables_corpus({"new": {**s, "triangles": 1}, "old": {**old, "triangles": 1}}, {}, spec, None, None)
    lines = text.splitlines()
    head = next(ln for ln in lines if "Spearman predicted pixels pooled" in ln)
    new_row = next(ln for ln in lines if ln.startswith("| new | ") and ln.count("|") == head.count("|"))
    assert new_row.rstrip(" |").endswith(f"{pp['spearman']:.2f}")
    assert f"| new | 30 | {pp['spearman']:.2f} | {pp['spearman_objective']:.2f} |" in text
    assert "| old | - | - | - | - | - |" in text
    verdict_head = next(ln for ln in lines if "Spearman predicted pixels >=" in ln)
    assert "Spearman objective >=" in verdict_head


def test_fingerprint_changes_with_the_record_keys(tmp_path, monkeypatch):
    # a record stored without predicted_misclassified is measured again by --reuse
    from shadowopt.service.bench import quality_corpus as b

    f = tmp_path / "s.usda"
    f.write_text("#usda 1.0\n")
    args = (f, {"fov_y_deg": 60}, [500, 500], {"single": {}}, {"single": _dirs(2)})
    new = b._corpus_fingerprint(*args)
    assert qr.PREDICTED_KEY in b.RECORD_KEYS
    monkeypatch.setattr(b, "RECORD_KEYS", tuple(k for k in b.RECORD_KEYS if k != qr.PREDICTED_KEY))
    assert b._corpus_fingerprint(*args) != new


def test_engine_table_puts_the_engine_numbers_beside_the_ideal_ones():
    stats = {"demo": {"single": {"totals": {"focused": 200, "optimized": 100},
                                 "engine_totals": {"focused": 150, "optimized": 130}}},
             "old": {"single": {"totals": {"focused": 10, "optimized": 0}, "engine_totals": None}}}
    lines = qr.table_engine(stats, "single", "One map")
    assert "| demo | 200 / 150 (0.75) | 100 / 130 (1.30) |" in lines
    assert "| old | 10 / - | 0 / - |" in lines
    assert qr.table_engine(stats, "cascades", "Four cascades") == []
