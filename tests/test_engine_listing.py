"""docs/engine-integration.md's shader listings and light-pass state blocks, extracted verbatim, rendered in real
OpenGL (Mesa llvmpipe through EGL, in a subprocess: renderers.gl_listing) in the opengl, d3d and vulkan
(glClipControl) and reversed-Z conventions, GLSL as printed and HLSL through glslang and SPIRV-Cross, the casters
offset by the document's slope-scaled bias (its OpenGL calls executed, its Direct3D 11 and Vulkan fields set as
their OpenGL equivalents); their shadow against exact ray-traced visibility at the same pixels must be within
1.25x of what `evaluate --depth` predicts for the same solution."""
from __future__ import annotations

import pytest

from shadowopt.api.schemas import validate_rig
from shadowopt.renderers import gl_listing as G
from shadowopt.service.bench import engine as E

SCREEN = (480, 270)
MAP = 1024
MODES = ("solution", "linear")  # the solutions' maps are all hardware here: linear forced tests its pieces
LANGUAGES = E.LANGUAGES if E.hlsl_tools() is None else ("glsl",)


def _scene(name):
    pairs, skipped = E.scene_rigs([name], SCREEN)
    if not pairs:
        pytest.skip(f"{name}: {skipped.get(name, 'absent')}")
    return pairs[0]


def _measure(name, cascades, **kw):
    n, path, rig = _scene(name)
    try:
        return E.measure(validate_rig, n, path, rig, cascades, MAP, SCREEN, kw.pop("languages", LANGUAGES),
                         kw.pop("modes", MODES), **kw)
    except RuntimeError as e:
        if str(e).startswith("no OpenGL"):
            pytest.skip(str(e).splitlines()[0])
        raise


def test_the_document_has_every_listing_piece_once():
    got = {lang: sorted(p) for lang, p in E.listings().items()}
    assert got == {"glsl": ["light-pass-hardware", "light-pass-linear", "light-pass-vertex", "shadow-lookup",
                            "shadow-lookup-local"],
                   "hlsl": ["light-pass-linear", "light-pass-vertex", "shadow-lookup", "shadow-lookup-local"],
                   "c": ["light-pass-state-d3d11", "light-pass-state-gl", "light-pass-state-vulkan"]}
    assert "allow_log_warp" in E.DOC.read_text()  # the one sentence saying the log warp is not covered


@pytest.mark.parametrize("reversed_z", [False, True])
def test_the_three_state_blocks_set_one_light_pass_state(reversed_z):
    """OpenGL's calls, Direct3D 11's and Vulkan's rasterizer fields, read as the harness reads them: depth
    clamping on, no culling, the slope-scaled offset k with clamp m (both negated with reversed-Z: towards
    the far plane, 0), no constant offset; OpenGL's depth test LESS (reversed-Z: GREATER)."""
    src = E.listings()["c"]
    k, m = 1.5, 0.002
    sign = -1.0 if reversed_z else 1.0
    want = {("glEnable", (G.GL_DEPTH_CLAMP,)), ("glDisable", (G.GL_CULL_FACE,)),
            ("glEnable", (G.GL_POLYGON_OFFSET_FILL,)), ("glPolygonOffsetClamp", (sign * k, 0.0, sign * m))}
    for api in ("gl", "d3d11", "vulkan"):
        calls = {(name, tuple(args)) for name, args in G.light_pass_state(api, src[f"light-pass-state-{api}"], k, m,
                                                                            reversed_z)}
        if api == "gl":
            assert ("glDepthFunc", (G.GL_GREATER if reversed_z else G.GL_LESS,)) in calls
            calls = {c for c in calls if c[0] != "glDepthFunc"}
        assert calls == want, api
    with pytest.raises(ValueError, match="DepthBias"):  # a constant D3D bias is not what the document asks
        G.light_pass_state("d3d11", src["light-pass-state-d3d11"].replace("DepthBias = 0", "DepthBias = 16"),
                           k, m, reversed_z)


_RESULTS: dict = {}


def _listing_result(scene, cascades):
    """One solution, ground truth and OpenGL run per (scene, cascades), shared by both languages' tests."""
    if (scene, cascades) not in _RESULTS:
        _RESULTS[(scene, cascades)] = _measure(scene, cascades)
    return _RESULTS[(scene, cascades)]


# Two representatives (one and four cascades); McUsd and the corpus scenes (street_canyon, terrain ...) at both
# counts, with the same listings and conventions, are `shadowopt bench engine`'s table (BENCHMARKS.md, engine).
LISTING_CASES = [("mcusd", 1), ("street_canyon", 4)]


@pytest.mark.gl
@pytest.mark.parametrize("language", E.LANGUAGES)
@pytest.mark.parametrize("scene, cascades", LISTING_CASES)
def test_pasted_listing_matches_evaluate_depth(scene, cascades, language):
    if language not in LANGUAGES:
        pytest.skip(f"the HLSL listings were not rendered: {E.hlsl_tools()}")
    r = _listing_result(scene, cascades)
    assert r["receivers"] > 10_000
    bad = []
    jobs = {k: v for k, v in r["listing"].items() if k.startswith(language + "_")}
    assert len(jobs) == len(E.CONVENTIONS) * len(MODES)
    for name, v in jobs.items():
        mode = name.rsplit("_", 1)[1]
        ev = r["evaluate"][mode]
        # Silhouette pixels where the rasterizer sees another surface than the ray tracer are left out: few.
        assert v["compared"] >= 0.99 * v["receivers"], (name, v)
        if v["wrong"] > 1.25 * ev:
            bad.append(f"{name}: listing {v['wrong']} wrong pixels vs evaluate --depth {mode} {ev}")
    assert not bad, f"{scene}, {cascades} cascade(s), {r['receivers']} receivers: " + "; ".join(bad)
    assert r["cascades"] == cascades and r["screen"] == list(SCREEN)
    for block in r["depth"]:  # the caster-side slope-scaled bias is the fitted one (0 allowed), the receiver-side slope off
        for mode in ("hardware", "linear"):
            b = block[mode]
            assert b["slope_scaled"] >= 0 and b["slope_clamp"] > 0 and b["slope"] == 0, (mode, b)
    # the rule's caster-side term stays in the other mode's block, so every listing runs a polygon offset
    assert any(block[m]["slope_scaled"] > 0 for block in r["depth"] for m in ("hardware", "linear"))
    # What the document says a solution echoes: the light and camera it was solved for (world frame).
    for conv, echo in r["resolved"].items():
        assert echo["lights"][0]["direction"] == pytest.approx(r["light"]["direction"], abs=1e-9), conv
        for key in ("position", "forward", "fov_y_deg"):
            assert echo["camera"][key] == pytest.approx(r["camera"][key], abs=1e-9), (conv, key)


@pytest.mark.gl
def test_a_wrong_listing_fails_the_check():
    """The check can fail: the lookup without reversed-Z's flipped comparison, or without its bias, is far
    outside 1.25x of evaluate."""
    src = E.listings()
    lookup = src["glsl"]["shadow-lookup"]
    flip = "bool shadowed = uParams.y > 0.5 ? d + bias < stored : d - bias > stored;"
    assert flip in lookup
    unflipped = "bool shadowed = d - bias > stored;"
    broken = dict(src, glsl=dict(src["glsl"], **{"shadow-lookup": lookup.replace(flip, unflipped)}))
    hlsl_flip = "bool shadowed = gParams.y > 0.5 ? d + bias < stored : d - bias > stored;"
    assert hlsl_flip in src["hlsl"]["shadow-lookup"]
    broken["hlsl"] = dict(src["hlsl"], **{"shadow-lookup": src["hlsl"]["shadow-lookup"].replace(
        hlsl_flip, unflipped)})
    r = _measure("street_canyon", 1, languages=LANGUAGES, modes=("solution",), sources=broken,
                 conventions=("reversed_z",))
    ev = r["evaluate"]["solution"]
    for lang in LANGUAGES:
        got = r["listing"][f"{lang}_reversed_z_solution"]["wrong"]
        assert got > 10 * max(ev, 1), (lang, got, ev)
    no_bias = _without(src, "glsl:shadow-lookup", "float bias = uDepth[k].x + uDepth[k].y * tanPsi;",
                       "float bias = 0.0;")
    r = _measure("terrain", 1, languages=("glsl",), modes=("solution",), sources=no_bias, conventions=("opengl",))
    ev, got = r["evaluate"]["solution"], r["listing"]["glsl_opengl_solution"]["wrong"]
    assert got > 1.25 * ev, (got, ev)


def _without(src: dict, piece: str, line: str, instead: str = "") -> dict:
    lang, piece = piece.split(":")
    return E.replaced(src, lang, piece, line, instead)


@pytest.mark.gl
def test_the_caster_offset_is_needed():
    """With a quarter of the solution's receiver constant (in evaluate's maps and the listing's alike) the
    casters' slope-scaled offset carries the bias on sloped surfaces: the listing with it agrees with evaluate
    in every convention (so with reversed-Z's negated offset too); without it (the offset call or field
    dropped from each state block, the slope term from the linear light passes) the listing has acne that
    evaluate does not predict."""
    quarter = {"constant": lambda b: 0.25 * b["constant"]}
    r = _measure("street_canyon", 1, depth_override=quarter)
    for name, v in r["listing"].items():
        ev = r["evaluate"][name.rsplit("_", 1)[1]]
        assert v["wrong"] <= 1.25 * ev, f"{name}: listing {v['wrong']} wrong pixels vs evaluate {ev}"
    src = E.without_caster_offset(E.listings())
    r = _measure("street_canyon", 1, depth_override=quarter, sources=src, conventions=("opengl", "vulkan"))
    for name, v in r["listing"].items():
        ev = r["evaluate"][name.rsplit("_", 1)[1]]
        assert v["wrong"] > 3 * max(ev, 10), f"{name}: without the offset {v['wrong']} wrong pixels, evaluate {ev}"


@pytest.mark.gl
def test_blend_only_where_the_next_cascade_holds_the_point_and_the_normal_offset():
    """Blend bands widened to each cascade's whole split (in evaluate's maps and the listing's), so that past
    a band's midpoint many receivers lie outside cascade k + 1, and a normal offset (0.3 m; the solutions
    return 0) in every block: the listing agrees with evaluate; a lookup that blends with k + 1 everywhere in
    the band does not."""
    def whole_split(cascades):
        for c in cascades[:-1]:
            c["blend_band"] = [c["split"][0], c["split"][1]]

    kw = dict(depth_override={"normal_offset": 0.3}, cascade_override=whole_split)
    r = _measure("street_canyon", 4, conventions=("opengl", "reversed_z"), **kw)
    for name, v in r["listing"].items():
        ev = r["evaluate"][name.rsplit("_", 1)[1]]
        assert v["wrong"] <= 1.25 * ev, f"{name}: listing {v['wrong']} wrong pixels vs evaluate {ev}"
    src = _without(E.listings(), "glsl:shadow-lookup", "if (inside) v = mix(v, next, w);", "v = mix(v, next, w);")
    r = _measure("street_canyon", 4, conventions=("opengl",), languages=("glsl",), modes=("solution",),
                 sources=src, **kw)
    ev, got = r["evaluate"]["solution"], r["listing"]["glsl_opengl_solution"]["wrong"]
    assert got > 10 * max(ev, 10), (got, ev)



@pytest.mark.gl
def test_the_light_pass_stores_what_evaluate_emulates():
    """Per texel, the depth Mesa's light pass stores with the document's state block (the OpenGL polygon offset
    for hardware, the shader's dFdx/dFdy term for linear) against evaluate's emulation of the light pass
    (shadow_map_rays.engine_stored_map: the caster's plane on the neighbouring texel rays): the offsets agree, as
    returned and with a clamp m small enough to cap most texels."""
    import numpy as np

    from shadowopt.renderers.depth_tests import engine_depth
    from shadowopt.renderers.ground_truth import screen_camera
    from shadowopt.renderers.shadow_map_rays import engine_stored_map, render_map
    from shadowopt.service.pipeline import scene_entry
    from shadowopt.service.rigs import resolve_rig

    n, path, rig = _scene("street_canyon")
    rig = {**rig, "shadow": {**(rig.get("shadow") or {}), "bias": "rule"}}  # the rule's clamp: small enough to bind
    entry = scene_entry(path)
    solved = E.solve_for_listing(validate_rig, entry, rig, 1, 512, conventions=("opengl",))
    rs, smap = entry.rays, solved["maps"][0]
    resolved = resolve_rig(solved["rig"], entry.loaded)
    light, camera = resolved.lights[0], screen_camera(resolved.camera, (64, 36))
    # (slope_scaled factor, slope_clamp factor) per variant: as returned, no offset, clamp 1/50 of the returned
    variants = {"on": (1.0, 1.0), "off": (0.0, 1.0), "clamped": (1.0, 0.02)}
    jobs = []
    for mode in ("hardware", "linear"):
        for v, (fk, fm) in variants.items():
            job = E.listing_jobs(solved, rs.origin, -np.asarray(light.direction), ("opengl",), ("glsl",), mode)[0]
            maps = [dict(m, depth=dict(m["depth"], slope_scaled=m["depth"]["slope_scaled"] * fk,
                                       slope_clamp=m["depth"]["slope_clamp"] * fm)) for m in job["maps"]]
            jobs.append(dict(job, name=f"{mode}_{v}", keep_maps=True, maps=maps))
    verts = np.array(rs.vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.array(rs.faces, dtype=np.uint32).reshape(-1, 3)
    try:
        gl = E.run_listing(verts, faces, E.camera_matrices(camera, rs, verts.astype(np.float64)), jobs, E.listings())
    except RuntimeError as e:
        if str(e).startswith("no OpenGL"):
            pytest.skip(str(e).splitlines()[0])
        raise
    d_occ, prim = render_map(rs, light, smap, prims=True)
    for mode in ("hardware", "linear"):
        eng = engine_depth(smap, mode)
        ev = {v: engine_stored_map(rs, smap, d_occ, prim, dict(eng, slope_scaled=eng["slope_scaled"] * fk,
                                                                 slope_clamp=eng["slope_clamp"] * fm))
              for v, (fk, fm) in variants.items()}
        g = {v: gl[f"stored_{mode}_{v}"][0].astype(float) for v in variants}
        # Texels whose caster is the same triangle in both (away from silhouettes: GL's and the ray's stored
        # depth agree without the offset to float32 precision) and where the offset is not lost to clamping.
        same = (prim >= 0) & (np.abs(g["off"] - ev["off"]) <= 1e-6) & (ev["on"] > ev["off"])
        assert same.mean() > 0.5, (mode, same.mean())
        for v in ("on", "clamped"):
            off_gl, off_ev = (g[v] - g["off"])[same], (ev[v] - ev["off"])[same]
            rel = np.abs(off_gl - off_ev) / off_ev
            assert np.median(rel) < 0.01 and np.mean(rel < 0.05) > 0.95, (mode, v, np.median(rel))
        m = eng["slope_clamp"] * variants["clamped"][1]
        capped = (g["clamped"] - g["off"])[same]
        assert np.mean(np.abs(capped - m) < 0.01 * m) > 0.5, (mode, "the clamp caps most texels")


_LOCAL: dict = {}


def _solve_local(entry, rig: dict, conventions, point_light_maps: str) -> dict:
    """solve_for_listing's result with shadow.point_light_maps set (solve_for_listing sets `shadow` itself)."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    shadow = {"resolution": [MAP, MAP], "cascades": 1, "point_light_maps": point_light_maps}
    sols = {}
    for conv in dict.fromkeys(["opengl", *conventions]):
        api, rz = E.CONVENTIONS[conv]
        sols[conv] = solve(entry, validate_rig(dict(rig, shadow=shadow, output={
            "convention": api, "layout": "column_major", "reversed_z": rz})), SolveRequest("optimized"))
    return {"solutions": sols, "maps": maps_from_solution(sols["opengl"])[0],
            "rig": validate_rig(dict(rig, shadow=shadow))}


def _local_light(tmp_path_factory, name: str, sources=None, conventions=tuple(E.CONVENTIONS), modes=MODES,
                 languages=LANGUAGES, depth_override=None, point_light_maps=None):
    """A spot or point light of tests/lights_scene.py (the demo scene with both) through the document's
    shadow-lookup-local piece in OpenGL: {"evaluate": {mode: misclassified}, "listing": {job: wrong pixels},
    "maps": [resolution, ...], "faces": [...], "receivers"}. The lookup gets the light's position with w = 1
    (re-centred as the matrices are) and, for a point light's faces, uParams.z = 1."""
    import numpy as np
    from lights_scene import write_lights_scene

    from shadowopt.renderers.ground_truth import evaluate_buffers, screen_camera
    from shadowopt.service.pipeline import scene_entry
    from shadowopt.service.rigs import resolve_rig

    if "path" not in _LOCAL:
        _LOCAL["path"] = write_lights_scene(tmp_path_factory.mktemp("lights"))
    entry = scene_entry(_LOCAL["path"])
    rig = {"camera": {"usd_path": "/World/Camera", "resolution": list(SCREEN)}, "lights": [{"usd_path": name}]}
    solved = (E.solve_for_listing(validate_rig, entry, rig, 1, MAP, depth_override=depth_override,
                                  conventions=conventions) if point_light_maps is None
              else _solve_local(entry, rig, conventions, point_light_maps))
    light = resolve_rig(solved["rig"], entry.loaded).lights[0]
    rs = entry.rays
    camera = screen_camera(resolve_rig(solved["rig"], entry.loaded).camera, SCREEN)
    evals, gt = {}, None
    for depth in modes:
        g = evaluate_buffers(rs, camera, light, solved["maps"], None, depth=depth)
        evals[depth], gt = g.result["misclassified_pixels"], gt or g
    faces = [m.face for m in solved["maps"]]
    to_light = [*(np.asarray(light.position, float) - rs.origin), 1.0]
    jobs = [dict(j, lookup="local", faces=faces[0] is not None)
            for mode in modes for j in E.listing_jobs(solved, rs.origin, to_light, conventions, languages, mode)]
    verts = np.array(rs.vertices, dtype=np.float32).reshape(-1, 3)
    tris = np.array(rs.faces, dtype=np.uint32).reshape(-1, 3)
    try:
        gl = E.run_listing(verts, tris, E.camera_matrices(camera, rs, verts.astype(np.float64)), jobs,
                           E.listings() if sources is None else sources)
    except RuntimeError as e:
        if str(e).startswith("no OpenGL"):
            pytest.skip(str(e).splitlines()[0])
        raise
    return {"evaluate": evals, "listing": {j["name"]: E.listing_wrong_pixels(gt, gl, rs, j["name"]) for j in jobs},
            "maps": [list(m.resolution) for m in solved["maps"]], "faces": faces,
            "receivers": int(gt.receivers.sum()), "shadowed": int(gt.exact_shadowed.sum()),
            "type": solved["solutions"]["opengl"]["lights"][0]["type"]}


@pytest.mark.gl
@pytest.mark.parametrize("light", ["/World/Spot", "/World/Bulb", "/World/Bulb:cube"])
def test_local_light_listing_matches_evaluate_depth(tmp_path_factory, light):
    """A spot light's map and a point light's faces (auto chooses face partitioning here: faces of different sizes
    in one array, each at its own resolution; ":cube" forces the cube's faces), drawn with shadow-lookup-local in
    every convention and language: their
    wrong pixels against ray-traced shadows are evaluate --depth's to 2% (+ 20 px; measured: equal), tighter than
    the directional listings' 1.25x, so that the broken lookups below fail it clearly."""
    light, _, maps = light.partition(":")
    r = _local_light(tmp_path_factory, light, point_light_maps=maps or None)
    print(f"{light} {maps or 'auto'}: maps {r['maps']} faces {r['faces']}, {r['receivers']} receivers ({r['shadowed']} shadowed), "
          f"evaluate {r['evaluate']}, listing {({k: v['wrong'] for k, v in r['listing'].items()})}")
    assert r["type"] == ("spot" if light.endswith("Spot") else "point")
    assert r["receivers"] > 10_000 and r["shadowed"] > 0.005 * r["receivers"]
    if r["type"] == "point":  # auto: face partitioning here, faces of different sizes; cube: one size
        sizes = {tuple(m) for m in r["maps"]}
        assert all(r["faces"]) and (len(sizes) == 1 if maps else len(sizes) >= 2), r["maps"]
    bad = []
    for name, v in r["listing"].items():
        ev = r["evaluate"][name.rsplit("_", 1)[1]]
        assert v["compared"] >= 0.99 * v["receivers"], (name, v)
        if abs(v["wrong"] - ev) > 0.02 * ev + 20:
            bad.append(f"{name}: listing {v['wrong']} wrong pixels vs evaluate {ev}")
    assert not bad, "; ".join(bad)


@pytest.mark.gl
def test_a_point_lights_face_rule_is_needed(tmp_path_factory):
    """The check can fail for the local lookup: a point light's faces served by face 0 alone (the loop without
    its inside test), or each map as a cascade (uParams.z ignored), are 10% (+ 200 px) past evaluate, outside
    the 2% the test above allows (measured: face 0 alone 4,041 wrong pixels against evaluate's 40); a spot with a normal
    offset (0.05 m in every block; the solutions return 0) still agrees, in reversed-Z too."""
    src = E.listings()
    first = E.replaced(src, "glsl", "shadow-lookup-local", "if (inside) return v;", "return v;")
    as_cascades = E.replaced(src, "glsl", "shadow-lookup-local", "if (uParams.z < 0.5)", "if (true)")
    for broken in (first, as_cascades):
        r = _local_light(tmp_path_factory, "/World/Bulb", sources=broken, conventions=("opengl",),
                         modes=("solution",), languages=("glsl",))
        ev, got = r["evaluate"]["solution"], r["listing"]["glsl_opengl_solution"]["wrong"]
        print(f"broken local lookup: {got} wrong pixels, evaluate {ev}")
        assert got > 1.1 * ev + 200, (got, ev)
    r = _local_light(tmp_path_factory, "/World/Spot", conventions=("opengl", "reversed_z"), modes=("solution",),
                     languages=("glsl",), depth_override={"normal_offset": 0.05})
    for name, v in r["listing"].items():
        ev = r["evaluate"]["solution"]
        print(f"spot, normal offset 0.05 m, {name}: {v['wrong']} wrong pixels, evaluate {ev}")
        assert abs(v["wrong"] - ev) <= 0.02 * ev + 20, (name, v, ev)
