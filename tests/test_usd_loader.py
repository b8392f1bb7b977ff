"""The USD loader on real stages: the working group's assets and small stages written here."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from shadowopt.renderers.scene_data import SceneError
from shadowopt.renderers.triangulation import ear_clip, triangulate
from shadowopt.renderers.usd_loader import load_scene


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


# ---------------------------------------------------------------- more geometry truths
def _polygon_area_2d(xy):
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _point_in_polygon(p, poly):
    inside = False
    for i in range(len(poly)):
        a, b = poly[i - 1], poly[i]
        if (a[1] > p[1]) != (b[1] > p[1]):
            x = a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            if x > p[0]:
                inside = not inside
    return inside


def test_concave_faces_in_a_usd_file_keep_their_area_and_stay_inside(tmp_path):
    # An L (6 corners), a comb (12 corners, three teeth) and a convex octagon, tilted out of any
    # coordinate plane so the best-fit-plane projection is exercised.
    L = [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]
    comb = [(0, 0), (5, 0), (5, 3), (4, 3), (4, 1), (3, 1), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)]
    octagon = [(np.cos(a), np.sin(a)) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    polys = [np.array(p, float) for p in (L, comb, octagon)]
    rot = np.array(Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(1, 2, 3).GetNormalized(), 37.0)))  # rows
    pts, counts, idx = [], [], []
    for k, p in enumerate(polys):
        off = len(pts)
        for x, y in p:
            pts.append(tuple(np.array([x + 10 * k, y, 0.0]) @ rot))
        counts.append(len(p))
        idx += list(range(off, off + len(p)))
    s = new_stage(tmp_path / "poly.usda")
    m = UsdGeom.Mesh.Define(s, "/Polys")
    m.CreatePointsAttr([Gf.Vec3f(*map(float, q)) for q in pts])
    m.CreateFaceVertexCountsAttr(counts)
    m.CreateFaceVertexIndicesAttr(idx)
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "poly.usda").geometry
    assert g.triangle_count == sum(len(p) - 2 for p in polys)
    flat = g.vertices @ rot.T  # back into the polygons' plane (rot is orthonormal)
    assert np.allclose(flat[:, 2], 0, atol=1e-5)
    for k, p in enumerate(polys):
        sel = [t for t in g.faces if abs(flat[t, 0].mean() - 10 * k) < 5]
        sel = np.array(sel)
        assert tri_area(flat, sel).sum() == pytest.approx(_polygon_area_2d(p), rel=1e-5)
        for t in sel:  # every triangle lies inside its polygon (its centroid does, and no overlap: areas add up)
            c = flat[t, :2].mean(0) - [10 * k, 0]
            assert _point_in_polygon(c, p)
        # consistent winding: every triangle faces the same way as the polygon
        n = np.cross(flat[sel[:, 1]] - flat[sel[:, 0]], flat[sel[:, 2]] - flat[sel[:, 0]])[:, 2]
        assert np.all(n > 0)


def test_ear_clipping_handles_a_big_concave_polygon_and_a_self_intersecting_one():
    # a 200-corner star: concave at every other corner
    a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    r = np.where(np.arange(200) % 2 == 0, 1.0, 0.4)
    star = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(200)], 1)
    t = triangulate(star, np.array([200]), np.arange(200))
    assert len(t) == 198 and tri_area(star, t).sum() == pytest.approx(_polygon_area_2d(star[:, :2]))
    pentagram = np.array([[np.cos(x), np.sin(x), 0] for x in np.arange(5) * 4 * np.pi / 5], float)
    assert len(triangulate(pentagram, np.array([5]), np.arange(5))) == 3  # finite answer, no crash


def _signed_volume(v, f):
    return np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0


def test_implicit_prims_are_closed_outward_facing_and_the_right_size(tmp_path):
    s = new_stage(tmp_path / "solids.usda")
    UsdGeom.Cube.Define(s, "/Cube").CreateSizeAttr(3.0)
    UsdGeom.Sphere.Define(s, "/Sphere").CreateRadiusAttr(2.0)
    c = UsdGeom.Cylinder.Define(s, "/Cyl")
    c.CreateRadiusAttr(1.0), c.CreateHeightAttr(4.0), c.CreateAxisAttr("Y")
    k = UsdGeom.Cone.Define(s, "/Cone")
    k.CreateRadiusAttr(1.0), k.CreateHeightAttr(3.0)
    cap = UsdGeom.Capsule.Define(s, "/Capsule")
    cap.CreateRadiusAttr(0.5), cap.CreateHeightAttr(2.0), cap.CreateAxisAttr("X")
    pl = UsdGeom.Plane.Define(s, "/Plane")
    pl.CreateWidthAttr(4.0), pl.CreateLengthAttr(6.0), pl.CreateAxisAttr("Y")
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "solids.usda").geometry

    def part(name):
        f = g.faces[g.face_prim == g.prim_paths.index(name)]
        return g.vertices, f

    # Volumes by the divergence theorem: positive means every triangle faces outward.
    # Tessellated round solids are inscribed, so they come out slightly small (32 segments: < 3%).
    truths = {"/Cube": 27.0, "/Sphere": 4 / 3 * np.pi * 8, "/Cyl": np.pi * 4, "/Cone": np.pi / 3 * 3,
              "/Capsule": np.pi * 0.25 * 2 + 4 / 3 * np.pi * 0.125}
    for name, vol in truths.items():
        got = _signed_volume(*part(name))
        assert 0.97 * vol <= got <= vol * (1 + 1e-9), (name, got, vol)
    v, f = part("/Cyl")
    used = v[np.unique(f)]
    assert np.allclose([used[:, 1].min(), used[:, 1].max()], [-2, 2])  # axis Y
    v, f = part("/Capsule")
    used = v[np.unique(f)]
    assert np.allclose([used[:, 0].min(), used[:, 0].max()], [-1.5, 1.5])  # axis X, height + 2 radii
    v, f = part("/Plane")
    used = v[np.unique(f)]
    assert np.allclose(used[:, 1], 0) and tri_area(v, f).sum() == pytest.approx(24.0)


def test_point_instancer_masks_invisible_ids_and_applies_the_prototype_transform_once(tmp_path):
    s = new_stage(tmp_path / "pim.usda")
    inst = UsdGeom.PointInstancer.Define(s, "/Inst")
    UsdGeom.Xform.Define(s, "/Inst/Protos")
    proto = UsdGeom.Xform.Define(s, "/Inst/Protos/Lifted")
    UsdGeom.XformCommonAPI(proto).SetTranslate(Gf.Vec3d(0, 100, 0))
    UsdGeom.Cube.Define(s, "/Inst/Protos/Lifted/Box").CreateSizeAttr(2.0)
    inst.CreatePrototypesRel().SetTargets([proto.GetPath()])
    inst.CreateProtoIndicesAttr([0, 0, 0])
    inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(5, 0, 0), Gf.Vec3f(0, 0, 7)])
    inst.CreateInvisibleIdsAttr([1])
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "pim.usda").geometry
    assert g.triangle_count == 24  # the middle instance is hidden
    centres = sorted(tuple(np.round(g.vertices[np.unique(g.faces[g.face_prim == k])].mean(0), 6))
                     for k in range(len(g.prim_paths)))
    assert centres == [(0, 100, 0), (0, 100, 7)]
    assert all(p.startswith("/Inst[") for p in g.prim_paths)


def test_time_sampled_points_without_a_default_are_read_at_their_first_sample(tmp_path):
    s = new_stage(tmp_path / "anim_pts.usda")
    m = UsdGeom.Mesh.Define(s, "/Tri")
    a = m.CreatePointsAttr()
    a.Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(0, 1, 0)], 10)
    a.Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(3, 0, 0), Gf.Vec3f(0, 3, 0)], 20)
    m.CreateFaceVertexCountsAttr([3])
    m.CreateFaceVertexIndicesAttr([0, 1, 2])
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "anim_pts.usda")
    assert sc.time_code is None and sc.geometry.bounds()[1][0] == pytest.approx(1.0)
    assert any("first sample" in w and "/Tri" in w for w in sc.warnings)
    assert load_scene(tmp_path / "anim_pts.usda", time_code=15).geometry.bounds()[1][0] == pytest.approx(2.0)


def test_bad_face_counts_and_short_faces(tmp_path):
    s = new_stage(tmp_path / "counts.usda")
    for name, counts, idx in [("Sum", [3, 3], [0, 1, 2]), ("Short", [2, 3], [0, 1, 0, 1, 2])]:
        m = UsdGeom.Mesh.Define(s, f"/{name}")
        m.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
        m.CreateFaceVertexCountsAttr(counts)
        m.CreateFaceVertexIndicesAttr(idx)
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "counts.usda")
    assert sc.geometry.prim_paths == ["/Short"] and sc.geometry.triangle_count == 1
    text = " | ".join(sc.warnings)
    assert "/Sum: skipped, faceVertexCounts sum to 6" in text and "/Short: 1 faces with fewer than 3" in text


def test_every_bad_mesh_means_an_empty_stage_error(tmp_path):
    s = new_stage(tmp_path / "allbad.usda")
    m = UsdGeom.Mesh.Define(s, "/Broken")
    m.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    m.CreateFaceVertexCountsAttr([3])
    m.CreateFaceVertexIndicesAttr([0, 1, 9])
    s.GetRootLayer().Save()
    with pytest.raises(SceneError) as e:
        load_scene(tmp_path / "allbad.usda")
    assert e.value.code == "empty_stage" and "allbad.usda" in e.value.message and "/Broken" in e.value.message


def test_lights_follow_their_transforms_in_a_z_up_stage(tmp_path):
    s = new_stage(tmp_path / "zl.usda", "Z", 0.01)
    UsdGeom.Cube.Define(s, "/Ground")
    sun = UsdLux.DistantLight.Define(s, "/Sun")
    UsdGeom.XformCommonAPI(sun).SetRotate(Gf.Vec3f(0, 0, 0))  # stage -Z: straight down in a Z-up stage
    disk = UsdLux.DiskLight.Define(s, "/Disk")
    UsdGeom.XformCommonAPI(disk).SetTranslate(Gf.Vec3d(100, 200, 300))
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "zl.usda")
    lights = {l.usd_path: l for l in sc.lights}
    assert np.allclose(lights["/Sun"].direction, [0, -1, 0])  # world +Y up: the sun shines down
    d = lights["/Disk"]
    assert d.type == "spot" and d.cone_deg == 90.0 and "hemisphere" in d.note
    assert np.allclose(d.position, [1, 3, -2])  # (x, y, z) cm -> (x, z, -y) m


# ---------------------------------------------------------------- the working group's assets
@pytest.fixture(scope="module")
def chess(usd_assets):
    import time

    t0 = time.perf_counter()
    sc = load_scene(usd_assets / "full_assets/OpenChessSet/chess_set.usda")
    return sc, time.perf_counter() - t0


def test_chess_set_loads_whole_and_its_load_time_is_part_of_the_call(chess):
    """How fast it loads is a benchmark's figure; load_s is measured inside the call."""
    sc, wall = chess
    assert sc.geometry.triangle_count > 500_000
    assert 0 < sc.load_s <= wall
    assert sc.geometry.faces.dtype == np.int32 and sc.geometry.vertices.dtype == np.float64
    assert sc.geometry.faces.max() < len(sc.geometry.vertices)
    assert len(sc.geometry.prim_paths) == 49  # 32 pieces (the pawns with 2 meshes) + the board
    lo, hi = sc.geometry.bounds()
    assert np.all(hi - lo < 1.0) and hi[1] - lo[1] > 0.05  # a table-top object in metres, standing up


def test_mcusd_camera_and_sun_against_their_authored_transforms(usd_assets):
    sc = load_scene(usd_assets / "full_assets/McUsd/McUsd.usda")
    assert sc.geometry.triangle_count == 880  # the file's header: 440 faces (880 triangles)
    cam = sc.cameras[0]
    assert cam.usd_path == "/McUsd/Camera"
    assert np.allclose(cam.position, [5.35, 5.35, 5.35])  # translate 535 cm
    assert np.dot(cam.forward, -cam.position / np.linalg.norm(cam.position)) > 0.999  # aimed at the origin

    def rx(d):
        c, s_ = np.cos(np.radians(d)), np.sin(np.radians(d))
        return np.array([[1, 0, 0], [0, c, -s_], [0, s_, c]])

    def ry(d):
        c, s_ = np.cos(np.radians(d)), np.sin(np.radians(d))
        return np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])

    sun = {l.usd_path: l for l in sc.lights}["/McUsd/Lights/Sun"]
    assert sun.type == "directional"
    assert np.allclose(sun.direction, ry(325) @ rx(235) @ [0, 0, -1])  # rotateZXY = (235, 325, 0)
    dome = {l.usd_path: l for l in sc.lights}["/McUsd/Lights/DomeLight"]
    assert dome.type == "ignored" and dome.note


def test_animated_cube_asset_moves_with_time(usd_assets):
    p = usd_assets / "test_assets/_common/animated_cube_translation.usda"
    centre = {t: load_scene(p, time_code=t).geometry.bounds() for t in (0, 50, 100)}
    # translate goes (0,0,0) -> (100,0,0) cm over frames 0..100; the cube is 1 cm wide
    for t, (lo, hi) in centre.items():
        assert np.allclose((lo + hi) / 2, [t / 100.0, 0, 0]) and np.allclose(hi - lo, 0.01)
    assert load_scene(p).time_code is None


def test_purpose_active_and_invalid_default_prim_assets(usd_assets):
    comp = usd_assets / "test_assets/foundation/stage_composition"
    pur = load_scene(comp / "purpose.usda")
    assert pur.geometry.prim_paths == ["/World/CubeIsRender"]
    assert any("CubeIsOther" in w for w in pur.warnings)
    assert load_scene(comp / "active.usda").geometry.prim_paths == ["/World/CubeActive"]
    bad = load_scene(usd_assets / "test_assets/foundation/stage_configuration/invalid_defaultPrim/invalid_defaultPrim.usda")
    assert bad.geometry.triangle_count > 0 and any("defaultPrim" in w for w in bad.warnings)


def test_meters_per_unit_assets(usd_assets):
    d = usd_assets / "test_assets/foundation/stage_configuration/metersPerUnit"
    one, ten = load_scene(d / "metersPerUnit_1.usda"), load_scene(d / "metersPerUnit_10.usda")
    assert (one.meters_per_unit, ten.meters_per_unit) == (1.0, 10.0)
    ext = lambda sc: np.subtract(*sc.geometry.bounds()[::-1])  # noqa: E731
    # the same layout authored in units ten times larger is ten times larger in metres
    assert np.allclose(ext(ten), 10 * ext(one))
    mix = load_scene(d / "metersPerUnit_mix.usda")
    assert mix.meters_per_unit == 100.0
    assert any("metersPerUnit_10.usda" in w and "does not rescale" in w for w in mix.warnings)


def test_mesh_schema_assets(usd_assets):
    m = usd_assets / "test_assets/schemaTests/usdGeom/meshes"
    five = load_scene(m / "5_face/5_face.usda")
    assert five.geometry.triangle_count == 5 * 2 + 3  # five quads and one pentagon
    for scheme in ("subdiv_catmullClark", "subdiv_loop_triangles", "subdiv_bilinear"):
        assert load_scene(m / scheme / f"{scheme}.usda").geometry.triangle_count == 12  # the cage, not refined
    pts = load_scene(m / "points_types/pointsTypes.usda")
    # arrays of 3-vectors (point/float/color/normal, float or double) are read; scalars and 1-D arrays are not
    assert len(pts.geometry.prim_paths) == 8
    assert any("/World/intArray" in w for w in pts.warnings)
    with pytest.raises(SceneError) as e:
        load_scene(m / "empty_mesh/empty.usda")
    assert e.value.code == "empty_stage"


def test_intent_vfx_scene_composes_a_thousand_instances(usd_assets):
    sc = load_scene(usd_assets / "intent-vfx/scenes/simpleAssetScene.usd")
    assert len(sc.geometry.prim_paths) == 1000
    assert sc.geometry.triangle_count == 1000 * load_scene(
        usd_assets / "intent-vfx/assets/simpleAsset/simpleAsset.usd").geometry.triangle_count


def test_scene_hash_is_stable_and_follows_composed_layers(tmp_path):
    (tmp_path / "part.usda").write_text('#usda 1.0\n(\n metersPerUnit = 1\n)\ndef Cube "P" {\n double size = 1\n}\n')
    s = new_stage(tmp_path / "root.usda")
    s.DefinePrim("/R").GetReferences().AddReference("./part.usda", "/P")
    s.GetRootLayer().Save()
    first = load_scene(tmp_path / "root.usda")
    h1 = first.scene_hash
    assert load_scene(tmp_path / "root.usda").scene_hash == h1 and len(h1) == 64
    # editing a referenced file (not the root) changes the hash, and the geometry (no stale layer cache)
    (tmp_path / "part.usda").write_text('#usda 1.0\n(\n metersPerUnit = 1\n)\ndef Cube "P" {\n double size = 2\n}\n')
    second = load_scene(tmp_path / "root.usda")
    assert second.scene_hash != h1
    assert second.geometry.bounds()[1][0] == pytest.approx(1.0) and first.geometry.bounds()[1][0] == pytest.approx(0.5)


def test_more_malformed_inputs(tmp_path):
    (tmp_path / "folder.usda").mkdir()
    (tmp_path / "pic.usdc").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 100)
    (tmp_path / "text.usdz").write_text("just text")
    for name, code in [("folder.usda", "not_usd"), ("pic.usdc", "not_usd"), ("text.usdz", "not_usd")]:
        with pytest.raises(SceneError) as e:
            load_scene(tmp_path / name)
        assert e.value.code == code and name in e.value.message


def test_time_sampled_transforms_without_a_default_use_their_first_sample(tmp_path):
    s = new_stage(tmp_path / "anim_xf.usda")
    x = UsdGeom.Xform.Define(s, "/X")
    op = x.AddTranslateOp()
    op.Set(Gf.Vec3d(10, 0, 0), 1)
    op.Set(Gf.Vec3d(20, 0, 0), 2)
    UsdGeom.XformCommonAPI(UsdGeom.Xform.Define(s, "/X/Y")).SetTranslate(Gf.Vec3d(0, 5, 0))  # a default
    UsdGeom.Cube.Define(s, "/X/Y/C")
    s.GetRootLayer().Save()
    sc = load_scene(tmp_path / "anim_xf.usda")
    assert np.allclose(np.add(*sc.geometry.bounds()) / 2, [10, 5, 0])
    assert any("/X: transform has only time samples" in w for w in sc.warnings)
    assert np.allclose(np.add(*load_scene(tmp_path / "anim_xf.usda", time_code=2).geometry.bounds()) / 2, [20, 5, 0])


def test_a_missing_material_file_named_by_many_prims_is_one_warning_with_its_count(tmp_path):
    """issue 25: a scene whose pieces all reference one missing look file printed one usd-core warning per prim
    (teapotScene.usd: 548 lines, capped at 50 + "... and 499 more"); now one line per missing file, with the
    number of prims that name it. A second missing file keeps its own line."""
    n = 300
    prims = "".join(f'def Mesh "Piece{i}" (\n    references = @looks/missing_look.usda@</Look>\n)\n{{\n'
                    f'    int[] faceVertexCounts = [3]\n    int[] faceVertexIndices = [0, 1, 2]\n'
                    f'    point3f[] points = [({i}, 0, 0), ({i + 1}, 0, 0), ({i}, 0, 1)]\n}}\n' for i in range(n))
    other = 'def Xform "Lamp" (\n    references = @looks/other_missing.usda@</Look>\n)\n{\n}\n'
    (tmp_path / "many.usda").write_text('#usda 1.0\n(\n    upAxis = "Y"\n    metersPerUnit = 1\n)\n' + prims + other)
    sc = load_scene(tmp_path / "many.usda")
    assert sc.geometry.triangle_count == n
    about = [w for w in sc.warnings if "missing_look.usda" in w]
    assert len(about) == 1 and f"the {n} prims" in about[0], sc.warnings[:3]
    assert len([w for w in sc.warnings if "other_missing.usda" in w]) == 1
    assert len(sc.warnings) == 2, sc.warnings
