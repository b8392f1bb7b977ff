"""Engine presets (output.engine): known world points, written in each engine's own frame and units, land on
the texture coordinates and depths the engine's documented conventions give; every preset's solution reads
back exactly; a preset with a contradicting explicit field is refused naming both.

The expected values are written from the engines' documentation, not from solvers.conventions:
- where a world point is in the engine (its axes and unit),
- how the engine reads the 16 numbers (memory order, column or row vectors),
- which texture row is t = 0 and which depth the map stores at the light's near and far planes.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shadowopt.solvers.conventions import ENGINES, export_matrices

from testkit import gl_depth

REPO = Path(__file__).resolve().parents[1]

# Where shadowopt's world point (x, y, z) (right-handed, +Y up, metres) is in each engine.
TO_ENGINE = {
    "opengl": lambda x, y, z: (x, y, z),
    "d3d": lambda x, y, z: (x, y, z),
    "vulkan": lambda x, y, z: (x, y, z),
    # Unity: left-handed, +Y up, metres; Unity's USD package converts a right-handed stage by z -> -z
    # (UnityTypeConverter.ChangeBasis: diag(1, 1, -1))
    "unity": lambda x, y, z: (x, y, -z),
    # Unreal: left-handed, +Z up, centimetres; its USD importer maps a Y-up stage by swapping Y and Z and
    # scaling metres to centimetres (UsdToUnreal::ConvertVector)
    "unreal": lambda x, y, z: (100 * x, 100 * z, 100 * y),
    "godot": lambda x, y, z: (x, y, z),  # right-handed, +Y up, metres
    "three": lambda x, y, z: (x, y, z),  # right-handed, +Y up, metres
    "bevy": lambda x, y, z: (x, y, z),  # right-handed, +Y up, metres
    "filament": lambda x, y, z: (x, y, z),  # right-handed, +Y up, metres
    # Babylon.js: left-handed, +Y up, metres; its glTF loader places a right-handed asset under a root node turned
    # 180 degrees about Y and scaled (1, 1, -1): x -> -x
    "babylon": lambda x, y, z: (-x, y, z),
}
UNIT = {e: (100.0 if e == "unreal" else 1.0) for e in ENGINES}  # engine units per metre

# (texture t, stored depth) from the canonical t_gl (0 at the map's bottom, NDC y = -1) and the linear-
# or window-depth D (0 at the light's near plane, 1 at its far plane), as each engine documents them.
TEXTURE = {
    "opengl": lambda t, d: (t, d),  # glDepthRange(0, 1): (z_ndc + 1)/2; textures start bottom-left
    "d3d": lambda t, d: (1 - t, d),  # NDC z in [0, 1]; texture origin top-left (v = 0.5 - 0.5 y)
    "vulkan": lambda t, d: (1 - t, d),  # NDC y down, z in [0, 1]; origin top-left
    # URP ShadowUtils.GetShadowTransform: the projection's z row negated when usesReversedZBuffer
    # (Direct3D 11/12, Vulkan, Metal), then scale and bias 0.5: v = 0.5 y + 0.5, depth 1 near, 0 far
    "unity": lambda t, d: (t, 1 - d),
    # Unreal: reversed Z (near 1, far 0), D3D texture origin top-left
    "unreal": lambda t, d: (1 - t, 1 - d),
    # Godot 4.3+: reverse Z, Vulkan clip (y flipped by the depth correction), uv = ndc * 0.5 + 0.5
    "godot": lambda t, d: (1 - t, 1 - d),
    # three.js: shadow.matrix = scale-and-bias 0.5 · projection · view, WebGL depth [-1, 1] -> [0, 1]
    "three": lambda t, d: (t, d),
    # Bevy: reverse Z (near 1, far 0), shadows.wgsl uv = ndc.xy * (0.5, -0.5) + 0.5
    "bevy": lambda t, d: (1 - t, 1 - d),
    # Filament ShadowMap::getTextureCoordsMapping: v = 0.5 y + 0.5, depth mapped to [1, 0]
    "filament": lambda t, d: (t, 1 - d),
    # Babylon.js WebGL2: uv = 0.5 clip.xy / w + 0.5 (shadowsFragmentFunctions.js), depth (z + 1) / 2 (directional
    # depthValues (1, 2): directionalLight.pure.js getDepthMinZ / getDepthMaxZ)
    "babylon": lambda t, d: (t, d),
}
# Which engines take the OpenGL-convention projection in their API and convert it to their GPU clip
# themselves (Unity: Camera.projectionMatrix / CommandBuffer.SetViewProjectionMatrices and
# GL.GetGPUProjectionMatrix; Filament: Camera::setCustomProjection), so projection · view of a point gives
# OpenGL's NDC; every other preset's projection is the GPU's clip matrix of the map it samples.
OPENGL_PROJECTION = {"unity", "filament"}
# The light view space each engine's view matrices map to: OpenGL's eye space looks down -Z (three.js,
# Godot, Bevy, Filament, Unity's worldToCameraMatrix); Unreal's view space is left-handed, looking down +Z.
LOOKS_DOWN_PLUS_Z = {"unreal", "babylon"}  # Babylon: Matrix.LookAtLHToRef


def decode(flat, engine: str):
    """The 16 numbers as the engine reads them, applied to a point: every preset here documents a
    column-major array of a matrix acting on column vectors (GLSL mat4, HLSL column_major packing, glam,
    three.js Matrix4.elements, Unity Matrix4x4, Godot Projection columns, filament mat4f), except Unreal,
    whose FMatrix M[row][col] (memory row-major) multiplies row vectors: v' = v * M."""
    a = np.asarray(flat, dtype=np.float64)
    if engine == "unreal":
        fm = a.reshape(4, 4)  # FMatrix.M[r][c] = flat[4 r + c]
        return lambda p: np.append(p, 1.0) @ fm
    m = a.reshape(4, 4).T  # column-major: flat[i + 4 j] = M[i][j]
    return lambda p: m @ np.append(p, 1.0)


# A light above the origin looking straight down (-Y): light-view x = world x, y = -world z, the light
# 10 m up; its ortho box [-5, 5] x [-4, 4], depths 1..21 m; its frustum for the perspective case.
LIGHT_VIEW = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, -10], [0, 0, 0, 1]])
L, R, B, T, N, F = -5.0, 5.0, -4.0, 4.0, 1.0, 21.0


def gl_ortho(l, r, b, t, n, f):  # glOrtho reference page
    return np.array([[2 / (r - l), 0, 0, -(r + l) / (r - l)], [0, 2 / (t - b), 0, -(t + b) / (t - b)],
                     [0, 0, -2 / (f - n), -(f + n) / (f - n)], [0, 0, 0, 1.0]])


def gl_frustum(l, r, b, t, n, f):  # glFrustum reference page
    return np.array([[2 * n / (r - l), 0, (r + l) / (r - l), 0], [0, 2 * n / (t - b), (t + b) / (t - b), 0],
                     [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)], [0, 0, -1.0, 0]])


POINTS = np.array([[0.0, 0.0, 0.0], [2.0, -3.0, 1.5], [-4.0, 5.0, -3.0], [4.5, 8.5, 3.9], [-1.0, -10.5, 0.2]])


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("kind", ["ortho", "frustum"])
def test_engine_frame_points_land_on_documented_texels_and_depths(engine, kind):
    P = gl_ortho(L, R, B, T, N, F) if kind == "ortho" else gl_frustum(L / 10, R / 10, B / 10, T / 10, N, F)
    l, r, b, t = (L, R, B, T) if kind == "ortho" else (L / 10, R / 10, B / 10, T / 10)
    out = export_matrices(LIGHT_VIEW, P, engine=engine)
    view, proj, tex = (decode(out[k], engine) for k in ("view_matrix", "projection_matrix", "texture_matrix"))
    fm_proj = np.asarray(out["projection_matrix"], float)
    for p in POINTS:
        x, y, z = p
        if kind == "ortho":
            s, t_gl, D = (x - l) / (r - l), (-z - b) / (t - b), ((10 - y) - N) / (F - N)
        else:
            d = 10 - y
            s, t_gl, D = (x * N / d - l) / (r - l), (-z * N / d - b) / (t - b), (1 / N - 1 / d) / (1 / N - 1 / F)
        pe = np.array(TO_ENGINE[engine](x, y, z), dtype=np.float64)
        want_t, want_depth = TEXTURE[engine](t_gl, D)
        h = tex(pe)
        assert h[:3] / h[3] == pytest.approx([s, want_t, want_depth], abs=1e-9), (engine, p)
        # the light view: the light 10 m up looks down; its depth axis per the engine's view space
        v = view(pe)
        depth_axis = v[2] if engine in LOOKS_DOWN_PLUS_Z else -v[2]
        assert depth_axis == pytest.approx((10 - y) * UNIT[engine], rel=1e-12, abs=1e-9)
        # projection · view: what the light pass rasterizes
        if engine == "unreal":
            c = v @ fm_proj.reshape(4, 4)
        else:
            c = np.asarray(fm_proj).reshape(4, 4).T @ v
        ndc = c[:3] / c[3]
        if engine in OPENGL_PROJECTION:  # OpenGL NDC; the engine reverses depth itself
            assert ndc == pytest.approx([2 * s - 1, 2 * t_gl - 1, 2 * D - 1], abs=1e-9)
        elif engine in ("opengl", "three", "babylon"):  # window z = (z_ndc + 1)/2
            assert ndc == pytest.approx([2 * s - 1, 2 * t_gl - 1, 2 * want_depth - 1], abs=1e-9)
        else:  # NDC z in [0, 1] is the stored depth; Vulkan-style clip (Vulkan, Godot) has y down
            y_ndc = -(2 * t_gl - 1) if engine in ("vulkan", "godot") else 2 * t_gl - 1
            assert ndc == pytest.approx([2 * s - 1, y_ndc, want_depth], abs=1e-9)


@pytest.mark.parametrize("engine", ENGINES)
def test_view_matrix_is_the_engine_kind_of_view(engine):
    """A rigid light view in the engine's units (Unreal's in centimetres), read as the engine reads the 16
    numbers (decode): distances between engine-frame points are kept, and the handedness of the map
    between the engine's world and the light view is a proper rotation for Unreal (a left-handed view of a
    left-handed world) and the right-handed engines, a mirror for Unity (worldToCameraMatrix maps its
    left-handed world to OpenGL's right-handed camera space, as Unity documents)."""
    out = export_matrices(LIGHT_VIEW, gl_ortho(L, R, B, T, N, F), engine=engine)
    view = decode(out["view_matrix"], engine)
    o = view(np.zeros(3))[:3]
    J = np.array([view(e)[:3] - o for e in np.eye(3)]).T  # columns: images of the engine's unit axes
    assert np.allclose(J @ J.T, np.eye(3), atol=1e-12)  # rigid in the engine's own units
    assert np.linalg.det(J) == pytest.approx(-1.0 if engine == "unity" else 1.0, abs=1e-12)
    # the light 10 m up (engine units) sits at the view origin
    up = np.array(TO_ENGINE[engine](0.0, 10.0, 0.0), float)
    assert view(up)[:3] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)


@pytest.fixture(scope="module")
def demo():
    from shadowopt.service.pipeline import scene_entry

    return scene_entry(REPO / "configs" / "demo_scene.usda")


def _rig(output: dict, cascades: int = 2, lights: list | None = None) -> dict:
    from shadowopt.api.schemas import validate_rig

    rig = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    # bias "rule": the same depth block for every preset (a fitted bias follows the engine's terms and depth
    # format, tests/test_bias_fit.py), so that the read-back compares the matrices and lengths alone
    rig["shadow"] = {"resolution": [512, 512], "cascades": cascades, "bias": "rule"}
    rig["coarse_long_side"] = 96
    rig["output"] = output
    if lights is not None:
        rig["lights"] = lights
    return validate_rig(rig)


@pytest.fixture(scope="module")
def world_solution(demo):
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    return solve(demo, _rig({}), SolveRequest("focused"))


@pytest.mark.parametrize("engine", ENGINES)
def test_every_preset_reads_back_exactly_and_states_its_convention(demo, world_solution, engine):
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    sol = json.loads(json.dumps(solve(demo, _rig({"engine": engine}), SolveRequest("focused"))))  # through JSON, as served
    conv = sol["convention"]
    assert conv["engine"] == engine and conv["frame"] == "engine"
    assert (conv["handedness"], conv["up_axis"]) == {"unity": ("left", "+Y"), "unreal": ("left", "+Z"), "babylon": ("left", "+Y")}.get(
        engine, ("right", "+Y"))
    assert conv["length_unit"] == ("centimetres" if engine == "unreal" else "metres")
    assert conv["reversed_z"] == (TEXTURE[engine](0.0, 0.0)[1] == 1.0)
    assert conv["texture_origin"] == ("bottom-left" if TEXTURE[engine](0.0, 0.0)[0] == 0.0 else "top-left")
    ref = maps_from_solution(world_solution)[0]
    got = maps_from_solution(sol)[0]
    assert len(got) == len(ref) == 2
    pts = np.array([[0.3, 0.2, -1.5], [-2.0, 0.0, 1.0], [1.0, 0.5, -4.0]])
    for a, b, c, c0 in zip(ref, got, sol["lights"][0]["cascades"], world_solution["lights"][0]["cascades"]):
        # the read-back map is the one the world solution exported (its OpenGL column-major matrices)
        v0 = np.asarray(c0["view_matrix"], float).reshape(4, 4).T
        p0 = np.asarray(c0["projection_matrix"], float).reshape(4, 4).T
        assert np.allclose(b.view, v0, atol=1e-12) and np.allclose(b.projection, p0, atol=1e-12)
        # and the engine's texture matrix, on the same points in the engine's frame, lands where the
        # read-back map does (its canonical t, its window depth), by the engine's documented rules
        tex = decode(c["texture_matrix"], engine)
        for X in pts:
            s_, t_, z_ndc, _ = (float(v[0]) for v in b.map_coords(X[None]))
            h = tex(np.array(TO_ENGINE[engine](*X), float))
            want_t, want_d = TEXTURE[engine](t_, (z_ndc + 1) / 2)
            assert h[:3] / h[3] == pytest.approx([s_, want_t, want_d], abs=1e-9), (engine, X)
        assert (a.split, a.light_depth, a.blend_band, a.n_prime, a.eta) == (b.split, b.light_depth, b.blend_band,
                                                                           b.n_prime, b.eta)
        assert a.depth == b.depth and a.depth_bias == b.depth_bias
        # the solution's own lengths are in the engine's unit
        k = UNIT[engine]
        assert c["split"] == pytest.approx([v * k for v in c0["split"]], rel=1e-12)
        assert c["light_depth"] == pytest.approx([v * k for v in c0["light_depth"]], rel=1e-12)
        if c0["blend_band"] is not None:
            assert c["blend_band"] == pytest.approx([v * k for v in c0["blend_band"]], rel=1e-12)
        unitless = ("constant", "slope", "slope_scaled", "slope_clamp")
        for mode, keys in (("hardware", (*unitless, "normal_offset")),
                           ("linear", (*unitless, "normal_offset", "near", "far"))):
            for key in keys:
                scale = k if key in ("normal_offset", "near", "far") else 1.0
                want = c0["depth"][mode][key]  # slope_clamp null: no clamp
                assert c["depth"][mode][key] == (None if want is None else pytest.approx(want * scale, rel=1e-12))


@pytest.mark.parametrize("engine", ENGINES)
def test_a_scene_point_through_a_real_solution(demo, engine):
    """A point on a texel's light ray of the demo's first cascade (a quarter of the way from its near plane,
    an orthographic map: D = 0.25), given in the engine's frame, through the returned texture matrix."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    sol = solve(demo, _rig({"engine": engine}, cascades=1), SolveRequest("focused"))
    smap = maps_from_solution(sol)[0][0]
    assert smap.warp_kind == "none" and abs(smap.projection[3, 2]) == 0.0  # orthographic
    s, t = 0.3125, 0.6875
    near, far = smap.texel_rays(np.array([s]), np.array([t]))
    p = 0.75 * near[0] + 0.25 * far[0]
    pe = np.array(TO_ENGINE[engine](*p), dtype=np.float64)
    h = decode(sol["lights"][0]["cascades"][0]["texture_matrix"], engine)(pe)
    want_t, want_depth = TEXTURE[engine](t, 0.25)
    assert h[:3] / h[3] == pytest.approx([s, want_t, want_depth], abs=1e-7)
    # the linear light-space depth from the engine's own view matrix and the returned near/far (both in
    # the engine's unit) is the world map's: (distance along the view axis - near) / (far - near)
    c = sol["lights"][0]["cascades"][0]
    lin = c["depth"]["linear"]
    v = decode(c["view_matrix"], engine)(pe)
    dist = v[2] if engine in LOOKS_DOWN_PLUS_Z else -v[2]
    lin0 = smap.depth["linear"]  # the same map in world metres (read back from internal)
    dist0 = -(smap.view @ np.append(p, 1.0))[2]
    assert (dist - lin["near"]) / (lin["far"] - lin["near"]) == pytest.approx(
        (dist0 - lin0["near"]) / (lin0["far"] - lin0["near"]), abs=1e-9)


@pytest.mark.parametrize("output, fields", [
    ({"engine": "unity", "convention": "d3d"}, ("output.engine", "output.convention")),
    ({"engine": "bevy", "reversed_z": False}, ("output.engine", "output.reversed_z")),
    ({"engine": "unreal", "layout": "row_major"}, ("output.engine", "output.layout")),
    ({"engine": "unreal", "frame": "stage"}, ("output.engine", "output.frame")),
    ({"engine": "three", "frame": "stage"}, ("output.engine", "output.frame")),
])
def test_a_contradicting_field_is_refused_naming_both(output, fields):
    from pydantic import ValidationError

    from shadowopt.api.schemas import OutputSpec, format_validation_error

    with pytest.raises(ValidationError) as e:
        OutputSpec.model_validate(output)
    msg = format_validation_error(e.value)
    assert all(f in msg for f in fields), msg
    field = fields[1].removeprefix("output.")
    assert f"remove output.{field} (the preset sets it)" in msg and "output: output." not in msg, msg


@pytest.mark.parametrize("engine", ENGINES)
def test_agreeing_fields_and_frame_world_are_accepted_and_filled(engine):
    """Fields equal to the preset's and frame "world" (the default, which a dumped rig carries) are accepted
    with every preset; the preset fills convention, layout and reversed_z."""
    from shadowopt.api.schemas import OutputSpec
    from shadowopt.solvers.conventions import ENGINE_PRESETS

    p = ENGINE_PRESETS[engine]
    o = OutputSpec.model_validate({"engine": engine, "convention": p["convention"], "reversed_z": p["reversed_z"],
                                   "layout": p["layout"], "frame": "world"})
    assert (o.convention, o.reversed_z, o.layout) == (p["convention"], p["reversed_z"], p["layout"])
    o = OutputSpec.model_validate({"engine": engine})
    assert (o.convention, o.reversed_z, o.layout) == (p["convention"], p["reversed_z"], p["layout"])


@pytest.mark.parametrize("engine", ENGINES)
def test_a_preset_rig_validates_twice_unchanged(engine):
    """validate_rig(validate_rig(rig)) == validate_rig(rig): the validated rig (frame "world" and the
    preset's own convention, layout and reversed_z filled in) is itself a valid rig, as the batch queue
    and the benchmarks re-validate dumped rigs."""
    once = _rig({"engine": engine})
    assert _rig_validate(once) == once
    assert once["output"]["engine"] == engine and once["output"]["frame"] == "world"


def _rig_validate(rig: dict) -> dict:
    from shadowopt.api.schemas import validate_rig

    return validate_rig(json.loads(json.dumps(rig)))


@pytest.mark.parametrize("engine", ["unity", "unreal", "bevy"])
def test_a_bare_client_rig_with_a_preset_is_accepted_by_the_server(engine, monkeypatch):
    """The Python client installed without the server's stack cannot fill the preset's fields (its
    OutputSpec keeps the defaults: reversed_z False, convention opengl); rig_json sends only the output
    fields that were set, so the server accepts the rig and fills the preset."""
    import sys

    from shadowopt.api.client import rig_json
    from shadowopt.api.schemas import Rig

    raw = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    raw["output"] = {"engine": engine}
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "shadowopt.solvers.conventions", None)  # import fails: the bare client
        bare = Rig.model_validate(raw)
        assert bare.output.reversed_z is False  # not filled without the stack
        sent = rig_json(bare)
    assert sent["output"] == {"engine": engine}
    assert _rig_validate(sent)["output"] == _rig(raw["output"])["output"]
    assert rig_json(Rig.model_validate(raw))["output"]["engine"] == engine  # with the stack: filled, agreeing
    _rig_validate(rig_json(Rig.model_validate(raw)))


@pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")
def test_the_rest_api_answers_422_naming_the_fields(tmp_path):
    from starlette.testclient import TestClient

    from shadowopt.api.server import create_app
    from shadowopt.api.settings import Settings

    rig = json.loads((REPO / "configs" / "demo_rig.json").read_text())
    rig["output"] = {"engine": "unity", "reversed_z": False}
    client = TestClient(create_app(Settings(data_dir=str(tmp_path / "data"))), base_url="http://localhost")
    r = client.post("/v1/optimize", json={"scene_id": "0" * 16, "rig": rig})
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert "output.engine" in err["message"] and "output.reversed_z" in err["message"]
    assert err["field"].startswith("rig.output")


def test_the_engines_page_table_says_what_each_preset_sets():
    """docs/engines.md's summary table against the preset table: handedness, up axis, unit, clip depth,
    reversed depth, texture origin, what projection_matrix holds and the layout, per engine."""
    from shadowopt.solvers.conventions import ENGINE_PRESETS, convention_info

    rows = {}
    for line in (REPO / "docs" / "engines.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[0].strip("`") in ENGINES:
            rows[cells[0].strip("`")] = cells
    assert set(rows) == set(ENGINES)
    clip_of = {"opengl": "[−1, 1]", "d3d": "[0, 1]", "vulkan": "[0, 1], NDC y down"}
    for engine, (_, frame, clip, rev, origin, proj, layout) in rows.items():
        info = convention_info({"engine": engine})
        p = ENGINE_PRESETS[engine]
        unit = {"metres": "m", "centimetres": "cm"}[info["length_unit"]]
        assert frame == f"{info['handedness']}, {info['up_axis']}, {unit}", engine
        if p["projection"] == "opengl":  # the API takes OpenGL's clip; the GPU's range is the reversed one
            assert clip.startswith("OpenGL in the API, ") and ("[0, 1] on the GPU" in clip or
                                                               "[1, 0] on the GPU" in clip), engine
        else:
            assert clip == clip_of[p["convention"]], engine
        assert rev.split()[0] == ("yes" if info["reversed_z"] else "no"), engine
        assert origin == info["texture_origin"], engine
        assert proj.split()[0] == {"clip": "clip", "opengl": "OpenGL"}[p["projection"]], engine
        assert layout.startswith({"column_major": "column-major", "row_major": "row-major"}[p["layout"]]), engine


def test_three_webgpu_renderer_form_is_the_d3d_convention():
    """docs/engines.md, three.js: with WebGPURenderer, three.js builds shadow.matrix as a 0.5 scale and
    bias in x, y with z passed through, times projection (WebGPUCoordinateSystem: clip z in [0, 1]) times
    view (LightShadow.updateMatrices), and ShadowNode samples it at (x, 1 - y): with the d3d convention's
    projection that is the d3d texture matrix (top-left origin, window depth)."""
    from shadowopt.solvers.conventions import export_matrices

    for P in (gl_ortho(L, R, B, T, N, F), gl_frustum(L / 10, R / 10, B / 10, T / 10, N, F)):
        out = export_matrices(LIGHT_VIEW, P, "d3d")
        V = decode(out["view_matrix"], "d3d")
        proj = np.asarray(out["projection_matrix"], float).reshape(4, 4).T
        s_webgpu = np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 1.0, 0], [0, 0, 0, 1]])
        tex = decode(out["texture_matrix"], "d3d")
        for p in POINTS:
            h = s_webgpu @ proj @ V(p)
            x, y, z = h[:3] / h[3]
            g = tex(p)
            assert [x, 1 - y, z] == pytest.approx(list(g[:3] / g[3]), abs=1e-12)


def test_filament_render_target_uv_flip_gives_the_top_left_rows():
    """docs/engines.md, Filament: on Metal, Vulkan and WebGPU Filament folds v -> 1 - v into its shadow
    texture matrix (ShadowMap::getTextureCoordsMapping's Mf when textureSpaceFlipped, the same as
    uvToRenderTargetUV in the shader); applied to the preset's texture matrix it gives the rows of a
    top-left-origin API (the d3d texture matrix's v), the depth staying 1 - D."""
    from shadowopt.solvers.conventions import export_matrices

    P = gl_frustum(L / 10, R / 10, B / 10, T / 10, N, F)
    fil = decode(export_matrices(LIGHT_VIEW, P, engine="filament")["texture_matrix"], "filament")
    top_left = decode(export_matrices(LIGHT_VIEW, P, "d3d")["texture_matrix"], "d3d")
    mf = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 1.0], [0, 0, 1.0, 0], [0, 0, 0, 1]])
    for p in POINTS:
        a, b = mf @ fil(p), top_left(p)
        assert a[:2] / a[3] == pytest.approx(b[:2] / b[3], abs=1e-12)
        assert a[2] / a[3] == pytest.approx(1 - b[2] / b[3], abs=1e-12)


def test_unreal_light_forward_is_the_z_column_of_the_fmatrix():
    """docs/engines.md, Unreal: the light's forward in Unreal's coordinates (for WorldToLight's +X) is the
    z column (M[0][2], M[1][2], M[2][2]) of the FMatrix filled from view_matrix. LIGHT_VIEW looks down
    world -Y, which is Unreal's -Z (down)."""
    from shadowopt.solvers.conventions import export_matrices

    fm = np.asarray(export_matrices(LIGHT_VIEW, gl_ortho(L, R, B, T, N, F), engine="unreal")["view_matrix"],
                    float).reshape(4, 4)
    fwd = fm[:3, 2]
    assert fwd / np.linalg.norm(fwd) == pytest.approx([0.0, 0.0, -1.0], abs=1e-12)
    assert np.linalg.norm(fwd) == pytest.approx(1.0, abs=1e-12)  # rigid in centimetres


def test_point_light_faces_keep_world_axis_names_under_a_preset(demo):
    """docs/engines.md: a point light's faces are named by shadowopt's world axes whatever the preset;
    under Unreal (Z up) the "+y" face looks along Unreal's +Z, "+z" along Unreal's +Y (TO_ENGINE of the
    world axis), each face's view read as FMatrix row vectors looking down +Z."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    lights = [{"type": "point", "position": [0.5, 3.0, 0.5]}]
    world = solve(demo, _rig({}, lights=lights), SolveRequest("focused"))["lights"][0]["cascades"]
    sol = solve(demo, _rig({"engine": "unreal"}, lights=lights), SolveRequest("focused"))["lights"][0]["cascades"]
    faces = [c["face"] for c in world]  # the faces with receivers (the others are dropped), in the cube's order
    assert [c["face"] for c in sol] == faces and len(faces) >= 3
    assert faces == [f for f in ["+x", "-x", "+y", "-y", "+z", "-z"] if f in faces]
    for c in sol:
        axis = {"x": 0, "y": 1, "z": 2}[c["face"][1]]
        d = np.zeros(3)
        d[axis] = 1.0 if c["face"][0] == "+" else -1.0
        want = np.array(TO_ENGINE["unreal"](*d), float) / 100.0  # the world axis in Unreal's axes
        fm = np.asarray(c["view_matrix"], float).reshape(4, 4)
        fwd = fm[:3, 2] / np.linalg.norm(fm[:3, 2])
        assert fwd == pytest.approx(want, abs=1e-9), c["face"]


def test_log_warp_with_a_top_left_origin_applies_to_one_minus_v(demo):
    """docs/engines.md: a log-warped map (LogPSM, output.allow_log_warp) under a top-left preset (Bevy):
    t = 1 - v of the texture matrix, t' = c0 log(c1 t + c2) (warp.log), the texel at v = 1 - t', which is
    where the read-back map (its own log warp, bottom-left t) puts the point."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    sol = solve(demo, _rig({"engine": "bevy", "allow_log_warp": True}, cascades=1), SolveRequest("logpsm"))
    c = sol["lights"][0]["cascades"][0]
    assert c["warp"]["kind"] == "log"
    lw = c["warp"]["log"]
    smap = maps_from_solution(sol)[0][0]
    tex = decode(c["texture_matrix"], "bevy")
    s0, t0 = np.array([0.2, 0.5, 0.8]), np.array([0.3, 0.6, 0.9])
    near, far = smap.texel_rays(s0, t0)  # world points whose warped (s, t) are s0, t0
    for X, s_want, t_want in zip(0.5 * (near + far), s0, t0):
        h = tex(np.array(TO_ENGINE["bevy"](*X), float))
        s, v = h[0] / h[3], h[1] / h[3]
        t_warped = lw["c0"] * np.log(lw["c1"] * (1 - v) + lw["c2"])
        assert (s, 1 - t_warped) == pytest.approx((s_want, 1 - t_want), abs=1e-9)


def test_warp_n_is_in_the_preset_unit(demo):
    """docs/engines.md: warp.n is a length and is returned in the preset's unit (Unreal: centimetres) for a
    perspective-warped map (LiSPSM); the depth block's lengths likewise, read back in metres exactly."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    world = solve(demo, _rig({}, cascades=1), SolveRequest("lispsm"))["lights"][0]["cascades"][0]
    sol = solve(demo, _rig({"engine": "unreal"}, cascades=1), SolveRequest("lispsm"))
    c = sol["lights"][0]["cascades"][0]
    assert c["warp"]["kind"] == world["warp"]["kind"] == "perspective"
    assert c["warp"]["n"] == pytest.approx(100.0 * world["warp"]["n"], rel=1e-12)
    assert c["warp"]["eta"] == pytest.approx(world["warp"]["eta"], rel=1e-12)  # no unit
    assert maps_from_solution(sol)[0][0].n_prime == pytest.approx(world["warp"]["n"], rel=1e-12)


@pytest.mark.gl
@pytest.mark.parametrize("engine", ["unreal", "godot"])
def test_engine_frame_geometry_rasterized_by_opengl_matches_the_ray_cast_map(demo, tmp_path, engine):
    """The demo's geometry moved into the engine's frame and units by hand (TO_ENGINE), drawn with the
    preset's projection · view in real OpenGL with that preset's clip rules (z in [0, 1], reversed: depth
    test GREATER, cleared to 0; Godot's Vulkan clip has y down): the stored depth is 1 - D of the ray-cast
    map's first hits on every texel. Unreal: left-handed, Z up, centimetres, a +Z-looking view and FMatrix
    row vectors; Godot: right-handed, Vulkan clip."""
    from shadowopt.renderers.shadow_map_rays import render_map
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    rig = _rig({"engine": engine}, cascades=1)
    sol = solve(demo, rig, SolveRequest("focused"))
    c = sol["lights"][0]["cascades"][0]
    a_v, a_p = (np.asarray(c[k], float).reshape(4, 4) for k in ("view_matrix", "projection_matrix"))
    clip = (a_v @ a_p).T if engine == "unreal" else a_p.T @ a_v.T  # as column vectors: (v M)^T = M^T v^T
    smap = maps_from_solution(sol)[0][0]
    res = (192, 192)
    smap.resolution = res
    rs = demo.rays
    to_e = np.array([TO_ENGINE[engine](*e) for e in np.eye(3)]).T  # columns: the world axes in the engine
    verts_e = (demo.loaded.geometry.vertices - rs.origin) @ to_e.T  # re-centred in float64 first, as an engine would
    shift = np.eye(4)
    shift[:3, 3] = to_e @ rs.origin
    depth = gl_depth(tmp_path, verts_e, demo.loaded.geometry.faces, clip @ shift, res, "zero_to_one", True)
    if engine == "godot":
        depth = depth[::-1]  # Vulkan-style NDC y down: framebuffer row 0 is the map's top
    covered = depth > 0.0
    D = 1.0 - depth  # reversed: 1 at the light's near plane
    d_ray = render_map(rs, resolve_rig(rig, demo.loaded).lights[0], smap)
    h, w = res
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    s, t = (ii + 0.5) / w, (jj + 0.5) / h
    near, far = smap.texel_rays(s.ravel(), t.ravel())  # orthographic: distance along the ray = D x length
    d_gl = (D.ravel() * np.linalg.norm(far - near, axis=1)).reshape(h, w)
    both = covered & np.isfinite(d_ray)
    assert both.mean() > 0.5 and np.mean(covered != np.isfinite(d_ray)) < 0.01
    err = np.abs(d_gl - d_ray)[both]
    span = smap.light_depth[1] - smap.light_depth[0]
    assert np.median(err) < 1e-4 * span and np.mean(err < 1e-3 * span) > 0.97, (np.median(err), span)


@pytest.mark.server
@pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")
def test_rest_camera_path_batch_and_client_rig_with_a_preset(tmp_path):
    """On a real uvicorn server (tests/serverkit.py): a camera-path batch with an engine preset (the server
    dumps each expanded configuration's rig and validates it again) runs, every result line in the
    preset's convention and unit; the Python client's `Rig` model with a preset round-trips through
    optimize."""
    import time

    import httpx
    from serverkit import TINY_RIG, TOKENS, auth, running, upload

    from shadowopt.api.client import Client
    from shadowopt.api.schemas import Rig

    with running(tmp_path / "data") as srv, httpx.Client(base_url=srv.base, headers=auth("alice"), timeout=120) as api:
        scene = upload(srv.base, "alice").json()
        rig = {**TINY_RIG, "output": {"engine": "unreal"}}
        body = {"scene_id": scene["scene_id"], "rig": rig, "method": "focused",
                "camera_path": {"keyframes": [{"position": [0, 3, 9], "target": [0, 0, 0]},
                                              {"position": [4, 3, 8], "target": [0, 0, 0]}], "samples": 2}}
        r = api.post("/v1/batches", json=body)
        assert r.status_code == 202, r.text
        bid = r.json()["batch_id"]
        deadline = time.monotonic() + 120
        while (st := api.get(f"/v1/batches/{bid}").json())["state"] in ("queued", "running"):
            assert time.monotonic() < deadline, st
            time.sleep(0.1)
        assert st["state"] == "done" and st["done"] == 2, st
        rows = [json.loads(x) for x in api.get(f"/v1/batches/{bid}/results").text.splitlines()]
        assert len(rows) == 2
        for row in rows:
            assert (row["convention"]["engine"], row["convention"]["length_unit"]) == ("unreal", "centimetres")
        with Client(srv.base, token=TOKENS["alice"]) as client:
            sol = client.optimize(scene["scene_id"], Rig.model_validate({**TINY_RIG, "output": {"engine": "unity"}}),
                                  method="focused")
        conv = sol["convention"]
        assert (conv["engine"], conv["handedness"], conv["reversed_z"]) == ("unity", "left", True)


@pytest.mark.parametrize("engine", ["unity", "filament"])
def test_the_engine_side_conversion_of_the_opengl_projection_matches_the_texture_matrix(engine):
    """docs/engines.md, Unity and Filament: the API takes the OpenGL-convention projection and the engine
    converts it for its reversed-Z GPU: Filament's vertex shaders do z' = -0.5 z + 0.5 w ("GL convention
    to inverted DX convention"), Unity's reversed-Z platforms the same (URP's GetShadowTransform negates
    the z row, then the 0.5 scale and bias). Unity also flips y when rendering into a texture on a top-left
    (UNITY_UV_STARTS_AT_TOP) platform, so row v = 0.5 - 0.5 y' of the stored map is at v = 0.5 + 0.5 y.
    The depth the GPU stores and that row are what the returned texture matrix reads."""
    from shadowopt.solvers.conventions import export_matrices

    P = gl_frustum(L / 10, R / 10, B / 10, T / 10, N, F)
    out = export_matrices(LIGHT_VIEW, P, engine=engine)
    view, tex = decode(out["view_matrix"], engine), decode(out["texture_matrix"], engine)
    proj = np.asarray(out["projection_matrix"], float).reshape(4, 4).T
    to_gpu = np.array([[1.0, 0, 0, 0], [0, -1.0 if engine == "unity" else 1.0, 0, 0], [0, 0, -0.5, 0.5],
                       [0, 0, 0, 1]])
    for x, y, z in POINTS:
        pe = np.array(TO_ENGINE[engine](x, y, z), float)
        c = to_gpu @ proj @ view(pe)
        ndc = c[:3] / c[3]
        row_v = 0.5 - 0.5 * ndc[1] if engine == "unity" else 0.5 + 0.5 * ndc[1]  # the row the map holds
        h = tex(pe)
        assert [0.5 + 0.5 * ndc[0], row_v, ndc[2]] == pytest.approx(list(h[:3] / h[3]), abs=1e-12)
