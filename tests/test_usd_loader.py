"""The USD loader on real stages: the working group's assets and small stages written here."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from shadowopt.renderers.scene_data import SceneError
from shadowopt.renderers.usd_loader import ear_clip, load_scene, triangulate


def tri_area(p, t):
    return 0.5 * np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1)


def new_stage(path, up="Y", mpu=1.0):
    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(s, up)
    UsdGeom.SetStageMetersPerUnit(s, mpu)
    return s


def test_concave_polygon_triangulates_to_its_own_area():
    # An L shape (area 3) and a star-like concave hexagon: ear clipping must not leave the polygon.
    L = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], float)
    t = np.array(ear_clip(L))
    assert len(t) == 4 and tri_area(L, t).sum() == pytest.approx(3.0)
    arrow = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [2, 1, 0], [0, 3, 0]], float)  # reflex corner at (2,1)
    t = np.array(ear_clip(arrow))
    area = 0.5 * abs(sum(arrow[i, 0] * arrow[i - 1, 1] - arrow[i - 1, 0] * arrow[i, 1] for i in range(5)))
    assert tri_area(arrow, t).sum() == pytest.approx(area)
    # A concave quad (dart) through the vectorised path: the split must use the reflex diagonal.
    dart = np.array([[0, 0, 0], [2, 1, 0], [4, 0, 0], [2, 3, 0]], float)
    t = triangulate(dart, np.array([4]), np.arange(4))
    assert tri_area(dart, t).sum() == pytest.approx(4.0)


def test_z_up_centimetre_stage_is_converted_to_y_up_metres(tmp_path):
    s = new_stage(tmp_path / "z.usda", "Z", 0.01)
    c = UsdGeom.Cube.Define(s, "/Box")
    c.CreateSizeAttr(100.0)
    UsdGeom.XformCommonAPI(c).SetTranslate(Gf.Vec3d(0, 0, 50))  # resting on the stage's ground z = 0
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "z.usda")
    lo, hi = sc.geometry.bounds()
    assert np.allclose(lo, [-0.5, 0.0, -0.5]) and np.allclose(hi, [0.5, 1.0, 0.5])
    assert sc.up_axis == "Z" and sc.meters_per_unit == 0.01


def test_implicit_prims_are_tessellated_at_their_size(tmp_path):
    s = new_stage(tmp_path / "p.usda")
    UsdGeom.Sphere.Define(s, "/S").CreateRadiusAttr(2.0)
    cyl = UsdGeom.Cylinder.Define(s, "/C")
    cyl.CreateRadiusAttr(0.5)
    cyl.CreateHeightAttr(3.0)
    cyl.CreateAxisAttr("X")
    UsdGeom.XformCommonAPI(cyl).SetTranslate(Gf.Vec3d(10, 0, 0))
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "p.usda")
    g = sc.geometry
    sphere = g.vertices[np.unique(g.faces[g.face_prim == g.prim_paths.index("/S")])]
    assert np.allclose(np.linalg.norm(sphere, axis=1), 2.0)
    cv = g.vertices[np.unique(g.faces[g.face_prim == g.prim_paths.index("/C")])]
    assert np.allclose([cv[:, 0].min(), cv[:, 0].max()], [8.5, 11.5])
    assert np.linalg.norm(cv[:, 1:], axis=1).max() == pytest.approx(0.5)


def test_purpose_visibility_and_time_samples(tmp_path):
    s = new_stage(tmp_path / "v.usda")
    for name, kw in [("Render", {}), ("Guide", {"purpose": "guide"}), ("Proxy", {"purpose": "proxy"}),
                     ("Hidden", {"visibility": "invisible"})]:
        c = UsdGeom.Cube.Define(s, f"/{name}")
        if "purpose" in kw:
            c.CreatePurposeAttr(kw["purpose"])
        if "visibility" in kw:
            c.CreateVisibilityAttr(kw["visibility"])
    m = UsdGeom.Cube.Define(s, "/Moving")
    op = m.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0)
    op.Set(Gf.Vec3d(100, 0, 0), 100)
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "v.usda", time_code=50)
    assert sorted(sc.geometry.prim_paths) == ["/Moving", "/Render"]
    g = sc.geometry
    mv = g.vertices[np.unique(g.faces[g.face_prim == g.prim_paths.index("/Moving")])]
    assert mv[:, 0].mean() == pytest.approx(50.0)
    assert sc.time_code == 50.0


def test_point_instancer_places_each_instance(tmp_path):
    s = new_stage(tmp_path / "pi.usda")
    inst = UsdGeom.PointInstancer.Define(s, "/Inst")
    proto = UsdGeom.Cube.Define(s, "/Inst/Protos/Box")
    proto.CreateSizeAttr(1.0)
    inst.CreatePrototypesRel().SetTargets([proto.GetPath()])
    inst.CreateProtoIndicesAttr([0, 0, 0])
    inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(5, 0, 0), Gf.Vec3f(0, 0, 7)])
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "pi.usda").geometry
    assert g.triangle_count == 36
    centres = sorted(tuple(np.round(g.vertices[np.unique(g.faces[g.face_prim == k])].mean(0), 6)) for k in range(3))
    assert centres == [(0, 0, 0), (0, 0, 7), (5, 0, 0)]


def test_cameras_and_lights_are_found_with_their_paths(tmp_path):
    s = new_stage(tmp_path / "cl.usda")
    UsdGeom.Cube.Define(s, "/Ground")
    cam = UsdGeom.Camera.Define(s, "/Cam")
    cam.CreateFocalLengthAttr(20.0)
    cam.CreateVerticalApertureAttr(20.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.5, 500))
    UsdGeom.XformCommonAPI(cam).SetTranslate(Gf.Vec3d(1, 2, 3))
    UsdLux.DistantLight.Define(s, "/Sun")
    spot = UsdLux.SphereLight.Define(s, "/Spot")
    UsdLux.ShapingAPI.Apply(spot.GetPrim()).CreateShapingConeAngleAttr(30.0)
    UsdLux.SphereLight.Define(s, "/Bulb")
    UsdLux.RectLight.Define(s, "/Panel")
    UsdLux.DomeLight.Define(s, "/Sky")
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "cl.usda")
    c = sc.cameras[0]
    assert c.usd_path == "/Cam" and np.allclose(c.position, [1, 2, 3]) and np.allclose(c.forward, [0, 0, -1])
    assert c.fov_y_deg == pytest.approx(np.degrees(2 * np.arctan(0.5))) and (c.near, c.far) == (0.5, 500)
    kinds = {l.usd_path: (l.type, l.cone_deg) for l in sc.lights}
    assert kinds == {"/Sun": ("directional", None), "/Spot": ("spot", 30.0), "/Bulb": ("point", None),
                     "/Panel": ("spot", 90.0), "/Sky": ("ignored", None)}
    assert np.allclose([l.direction for l in sc.lights if l.usd_path == "/Sun"][0], [0, 0, -1])


def test_working_group_assets(usd_assets):
    chess = load_scene(usd_assets / "full_assets/OpenChessSet/chess_set.usda")
    assert chess.geometry.triangle_count > 500_000
    assert any("mtlx" in w for w in chess.warnings)  # MaterialX it cannot read: a warning, not stderr noise
    mc = load_scene(usd_assets / "full_assets/McUsd/McUsd.usda")
    assert [c.usd_path for c in mc.cameras] == ["/McUsd/Camera"]
    assert {l.usd_path: l.type for l in mc.lights}["/McUsd/Lights/Sun"] == "directional"
    prims = load_scene(usd_assets / "test_assets/schemaTests/usdGeom/primitives/all_primitives.usda")
    assert len(prims.geometry.prim_paths) >= 5


@pytest.mark.parametrize("rel", ["sublayer_same_folder.usda", "sublayer_child_folder.usda", "sublayer_parent_folder.usda"])
def test_composition_across_folders(usd_assets, rel):
    sc = load_scene(usd_assets / "test_assets/foundation/stage_composition/subLayer" / rel)
    assert sc.geometry.triangle_count > 0


@pytest.mark.parametrize("kind", ["references", "payload"])
def test_composition_references_and_payloads(usd_assets, kind):
    base = usd_assets / "test_assets/foundation/stage_composition" / kind
    pre = "reference" if kind == "references" else "payload"
    for name in ("same_folder", "child_folder", "parent_folder"):
        assert load_scene(base / f"{pre}_{name}.usda").geometry.triangle_count > 0
    bad = load_scene(base / f"{pre}_invalid.usda")  # a missing file is a warning, not an error
    assert any("does_not_exist" in w for w in bad.warnings)


def test_up_axis_assets(usd_assets):
    d = usd_assets / "test_assets/foundation/stage_configuration/upAxis"
    z = load_scene(d / "upAxis_Z.usda")
    y = load_scene(d / "upAxis_Y.usda")
    assert z.up_axis == "Z" and y.up_axis == "Y"
    bad = load_scene(d / "upAxis_X.usda")
    assert any("upAxis" in w for w in bad.warnings)


def _write(path, text):
    path.write_text(text)
    return path


def test_malformed_inputs_give_clear_errors(tmp_path, usd_assets):
    cases = {
        "missing": (tmp_path / "nope.usda", "not_found"),
        "png": (_write(tmp_path / "image.usda", "\x89PNG not usd"), "not_usd"),
        "empty_file": (_write(tmp_path / "empty.usda", ""), "not_usd"),
        "txt": (_write(tmp_path / "notes.txt", "hello"), "not_usd"),
        "empty_stage": (_write(tmp_path / "nothing.usda", "#usda 1.0\n"), "empty_stage"),
        "syntax": (_write(tmp_path / "broken.usda", '#usda 1.0\ndef Mesh "M" {\n  point3f[] points = [(0,0'), "corrupt"),
    }
    layer = Sdf.Layer.FindOrOpen(str(usd_assets / "full_assets/McUsd/McUsd.usda"))
    layer.Export(str(tmp_path / "good.usdc"))
    data = (tmp_path / "good.usdc").read_bytes()
    (tmp_path / "trunc.usdc").write_bytes(data[: len(data) // 2])
    cases["truncated"] = (tmp_path / "trunc.usdc", "corrupt")
    for name, (p, code) in cases.items():
        with pytest.raises(SceneError) as e:
            load_scene(p)
        assert e.value.code == code, (name, e.value.message)
        assert p.name in e.value.message
        if name == "syntax":
            assert "parse error" in e.value.message and "pxrInternal" not in e.value.message


def test_bad_meshes_are_skipped_with_a_warning_naming_them(tmp_path):
    s = new_stage(tmp_path / "bad.usda")
    s.GetRootLayer().defaultPrim = "Missing"
    for name, pts, idx in [("Good", [(0, 0, 0), (1, 0, 0), (0, 0, 1)], [0, 1, 2]),
                           ("OutOfRange", [(0, 0, 0), (1, 0, 0), (0, 0, 1)], [0, 1, 7]),
                           ("NaN", [(0, 0, 0), (float("nan"), 0, 0), (0, 0, 1)], [0, 1, 2])]:
        m = UsdGeom.Mesh.Define(s, f"/{name}")
        m.CreatePointsAttr(pts)
        m.CreateFaceVertexCountsAttr([3])
        m.CreateFaceVertexIndicesAttr(idx)
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "bad.usda")
    assert sc.geometry.prim_paths == ["/Good"]
    joined = " | ".join(sc.warnings)
    assert "/OutOfRange" in joined and "/NaN" in joined and "defaultPrim 'Missing'" in joined


def test_instanceable_prims_are_expanded(tmp_path):
    s = new_stage(tmp_path / "inst.usda")
    proto = UsdGeom.Xform.Define(s, "/Proto")
    UsdGeom.Cube.Define(s, "/Proto/Box").CreateSizeAttr(1.0)
    for k, x in enumerate((0.0, 10.0)):
        p = UsdGeom.Xform.Define(s, f"/I{k}")
        p.GetPrim().GetReferences().AddInternalReference("/Proto")
        p.GetPrim().SetInstanceable(True)
        UsdGeom.XformCommonAPI(p).SetTranslate(Gf.Vec3d(x, 0, 0))
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "inst.usda").geometry
    assert sorted(g.prim_paths) == ["/I0/Box", "/I1/Box", "/Proto/Box"]
    i1 = g.vertices[np.unique(g.faces[g.face_prim == g.prim_paths.index("/I1/Box")])]
    assert np.allclose(i1.mean(0), [10, 0, 0])
