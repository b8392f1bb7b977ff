"""Lloyd et al. 2007 scene-independent analysis against the paper's Table 3."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from shadowopt.solvers.analysis import analyze
from shadowopt.solvers.warp import eta_shaping, n_prime_from_eta

# Table 3 minima (f/n = 1000, θ = 30°, γ = 90°), S without the 1/cos²θ factor.
TABLE3 = [("uniform", 1, 8.65e5), ("perspective", 1, 865), ("log", 1, 5.98), ("uniform", 5, 51.4),
          ("perspective", 5, 12.9), ("uniform", 7, 27.4), ("perspective", 7, 10.2), ("log", 5, 5.98), ("log", 7, 5.98)]


@pytest.mark.parametrize("method, k, expected", TABLE3)
def test_table3_minima(method, k, expected):
    assert analyze(1000, 30, 90, method, k)["S"] == pytest.approx(expected, rel=0.005)


def test_closed_form_critical_factors_at_overhead():
    a, th = 1000.0, math.radians(30)
    assert analyze(a, 30, 90, "uniform")["R_t"] == pytest.approx((a - 1) / math.sin(2 * th))
    assert analyze(a, 30, 90, "log")["R_t"] == pytest.approx(math.log(a) / math.sin(2 * th))


def test_ordering_and_finiteness_over_all_light_angles():
    s = {m: analyze(1000, 30, 90, m)["S"] for m in ("uniform", "perspective", "log")}
    assert s["log"] < s["perspective"] < s["uniform"]
    for g in (0, 0.5, 1, 30, 60, 120, 179, 179.5, 180):
        for m in ("uniform", "perspective", "log"):
            r = analyze(1000, 30, g, m, 3)
            assert all(math.isfinite(v) and v > 0 for v in r.values()), (g, m, r)


def test_eta_conversion_and_shaping_corner_values():
    n, f = 1.0, 100.0
    assert n_prime_from_eta(-1, n, f) == math.inf
    assert n_prime_from_eta(0, n, f) == pytest.approx(n + math.sqrt(n * f))
    assert n_prime_from_eta(1, n, f) == pytest.approx(n)
    assert n_prime_from_eta(-0.5, n, f) > n_prime_from_eta(0, n, f)
    th = 30.0
    assert eta_shaping(th / 2 - 1, th) == -1.0
    assert eta_shaping(th, th) == pytest.approx(-0.2)
    assert eta_shaping(th + 0.4 * (90 - th), th) == pytest.approx(1.0)
    assert eta_shaping(90, th) == 1.0 and eta_shaping(180 - 5, th) == -1.0  # folded: light behind


def test_cli_analyze_json():
    exe = Path(sys.executable).with_name("shadowopt")
    out = subprocess.run([str(exe), "analyze", "--f-over-n", "1000", "--theta-deg", "30", "--gamma-deg", "90",
                          "--method", "perspective", "--partitions", "5", "--json"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["S"] == pytest.approx(12.9, rel=0.005)
    bad = subprocess.run([str(exe), "analyze", "--f-over-n", "1000", "--theta-deg", "30", "--gamma-deg", "200",
                          "--method", "log"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--gamma-deg" in bad.stderr
