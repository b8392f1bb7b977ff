"""The inspector's sun move (issue 13): receiver_points' camera-only part (service.receivers.receiver_prep) is kept
with the cached camera pass, and tangent_reach / FinePoints.edges compute per component and per hit. None of it
may change a number: the receivers and the solutions must be those of the plain computation, bit for bit.

The references here are the plain forms the faster code replaced (written out in this file): tangent_reach's
(E, 4, 3) broadcast and the edge pass's grid-state neighbour test."""
from pathlib import Path

import numpy as np
import pytest

from shadowopt.api import schemas as S
from shadowopt.api.routes_solve import rig_dict
from shadowopt.renderers.coarse import DEPTH_CONTINUITY
from shadowopt.service import coarse_cache
from shadowopt.service.coarse_cache import CoarseCache, cached_coarse_pass
from shadowopt.service.pipeline import coarse_pass
from shadowopt.service.scenes import SceneCache
from shadowopt.service.receivers import light_problems, tangent_reach
from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve

from testkit import sun

DEMO = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"


def demo_rig(light, coarse=180):  # the inspector's request (api/static/inspect/inspect.js rig())
    return rig_dict(S.OptimizeRequest(scene_id="x" * 12, rig={
        "camera": {"usd_path": "/World/Camera", "resolution": [640, 360]}, "lights": [light],
        "shadow": {"resolution": [2048, 2048], "cascades": 1}, "coarse_long_side": coarse}).rig)


def without_times(sol):
    if isinstance(sol, dict):
        return {k: without_times(v) for k, v in sol.items() if k not in ("timings_ms", "time_ms")}
    if isinstance(sol, list):
        return [without_times(v) for v in sol]
    return sol


@pytest.fixture(scope="module")
def demo():
    return SceneCache().get(DEMO)


def plain_tangent_reach(camera, width, height, u, v, p, n, reach, factor):
    """tangent_reach as the (E, 4, 3) broadcast of its formula (ray through the offset screen point, ray-plane
    distance clamped to [dist / factor, dist factor], the hit's distance where the plane is parallel or behind)."""
    n = np.asarray(n, dtype=np.float64)
    dist = np.linalg.norm(p - camera.position, axis=1)
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    a = np.array([-reach, -reach, reach, reach])
    b = np.array([-reach, reach, -reach, reach])
    x = ((u[:, None] + a) * (2.0 / width) - 1.0) * tw
    y = (1.0 - (v[:, None] + b) * (2.0 / height)) * th
    d = camera.forward + x[..., None] * camera.right + y[..., None] * camera.up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    nd = np.sum(n[:, None] * d, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sum(n * (p - camera.position), axis=1)[:, None] / nd
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, np.clip(s, dist[:, None] / factor, dist[:, None] * factor), dist[:, None])
    return (camera.position + s[..., None] * d).reshape(-1, 3)


def plain_edges(fine, receiver, continuity=DEPTH_CONTINUITY):
    """FinePoints.edges on a state grid: 1 not traced, 0 traced and not a receiver, 2 a receiver."""
    H, W = fine.grid_shape
    state = np.ones(H * W, dtype=np.int8)
    state[fine.traced] = 0
    state[fine.flat[receiver]] = 2
    dgrid = np.zeros(H * W)
    dgrid[fine.flat[receiver]] = fine.depth[receiver]
    f, d = fine.flat[receiver], fine.depth[receiver]
    col = f % W
    out, slack = np.zeros(len(f), dtype=bool), np.zeros(len(f))
    for step, ok in ((1, col < W - 1), (-1, col > 0), (W, f + W < H * W), (-W, f - W >= 0)):
        g = np.where(ok, f + step, f)
        st, dd = state[g], np.abs(dgrid[g] - d)
        rec = ok & (st == 2)
        out |= ok & ((st == 0) | (rec & (dd > continuity * np.minimum(dgrid[g], d))))
        slack = np.where(rec, np.maximum(slack, dd), slack)
    edge, full = np.zeros(len(receiver), dtype=bool), np.zeros(len(receiver))
    edge[receiver], full[receiver] = out, slack
    return edge, full


def test_tangent_reach_is_its_broadcast_form_bit_for_bit(demo):
    resolved, buf = coarse_pass(demo, demo_rig({"type": "directional", "direction": sun(30.0)}))
    cam = resolved.camera
    rows, cols = np.nonzero(buf.hit)
    fine = buf.fine
    u, v = fine.uv()
    cases = [(cols + 0.5, rows + 0.5, buf.position[rows, cols], buf.normal[rows, cols], 1.5, 2.0),
             (u, v, fine.position, fine.normal, 1.0 / fine.factor, 1.25)]
    rng = np.random.default_rng(13)  # planes at every angle: parallel (n.d = 0) and behind (s <= 0) included
    m = 5000
    nrm = rng.normal(size=(m, 3)).astype(np.float32)
    nrm[:50] = np.float32(cam.right)  # parallel to the rays through the screen's vertical centre line
    cases.append((np.full(m, buf.width / 2.0), rng.uniform(0, buf.height, m),
                  cam.position + rng.normal(size=(m, 3)) * 20.0, nrm, 1.5, 2.0))
    clamped = 0
    for uu, vv, p, n, reach, factor in cases:
        got = tangent_reach(cam, buf, uu, vv, p, n, reach, factor)
        ref = plain_tangent_reach(cam, buf.width, buf.height, uu, vv, p, n, reach, factor)
        assert got.shape == ref.shape == (4 * len(uu), 3)
        assert np.array_equal(got, ref)
        dist = np.repeat(np.linalg.norm(p - cam.position, axis=1), 4)
        clamped += int(np.sum(np.isclose(np.linalg.norm(got - cam.position, axis=1), dist)))
    assert clamped > 0  # the fallback branch (the hit's own distance) was exercised


def test_fine_edges_are_the_grid_state_test(demo):
    c = CoarseCache()
    for light in ({"type": "directional", "direction": sun(-120.0)}, {"type": "directional", "direction": sun(95.0, 8.0)},
                  {"type": "spot", "position": [0.0, 12.0, 0.0], "direction": [0.0, -1.0, 0.0], "cone_deg": 25.0}):
        _, buf = cached_coarse_pass(demo, demo_rig(light, 96), "a", c)
        fine = buf.fine
        rec = fine.receiver[0]
        assert 0 < rec.sum() < len(rec)
        nb = fine.neighbours()
        for neighbours in (None, nb):
            got = fine.edges(rec, neighbours=neighbours)
            ref = plain_edges(fine, rec)
            assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
        assert ref[0].any() and (ref[1] > 0).any()
        assert set(np.unique(nb)) >= {-2, -1, 0}  # untraced, missed and hit neighbours all occur


def test_cached_receivers_equal_the_plain_ones_over_sun_moves(demo, monkeypatch):
    made = []
    real = coarse_cache.receiver_prep
    monkeypatch.setattr(coarse_cache, "receiver_prep", lambda *a: made.append(1) or real(*a))
    for coarse in (180, 96):
        c = CoarseCache()
        lights = [{"type": "directional", "direction": sun(az, el)} for az, el in
                  ((-120, 50), (-103, 50), (30, 50), (95, 20), (170, 5), (0, 88))]
        lights.append({"type": "spot", "position": [0.0, 12.0, 0.0], "direction": [0.0, -1.0, 0.0], "cone_deg": 25.0})
        for light in lights:
            rig = demo_rig(light, coarse)
            res, buf = cached_coarse_pass(demo, rig, "a", c)
            got = light_problems(res, buf, demo.loaded.geometry.bounds())
            res2, buf2 = coarse_pass(demo, rig)
            ref = light_problems(res2, buf2, demo.loaded.geometry.bounds())
            cp = c.passes()[0]
            assert (cp.receiver_prep is None) == (light is lights[0])  # a camera seen once: the plain path
            for g, r in zip(got, ref, strict=True):
                assert len(r.receivers) > len(r.samples) > 0
                for k in ("receivers", "receiver_slack", "sample_rows"):
                    assert np.array_equal(getattr(g, k), getattr(r, k)), (coarse, light, k)
            if light["type"] == "spot":  # a cone ends where no directional light's receivers can: computed then
                prep = c.passes()[0].receiver_prep
                edge, _ = buf.fine.edges(buf.fine.receiver[0])
                assert (edge & (prep.fine_row < 0)).sum() > 0 and (edge & (prep.fine_row >= 0)).sum() > 0
        assert (c.misses, c.hits) == (1, len(lights) - 1) and c.receiver_misses == len(lights)
    assert len(made) == 2  # the camera-only part once per camera pass, at its second receiver mask


def test_cached_solve_equals_the_plain_solve(demo, monkeypatch):
    monkeypatch.setattr(coarse_cache, "COARSE", CoarseCache())
    for az in (-120.0, 17.0, 150.0):
        rig = demo_rig({"type": "directional", "direction": sun(az, 40.0)})
        cached = solve(demo, rig, SolveRequest("optimized", cache_tenant="a"))  # no time budget: the search runs to its end
        plain = solve(demo, rig, SolveRequest("optimized"))
        assert without_times(cached) == without_times(plain)
        assert cached["solver"]["converged"]
