"""The USD loader's triangles against properties a user can check on any closed mesh, and visibility
inheritance (USD's documented rules).

- Winding: the loader keeps every triangle counter-clockwise about its outward normal. For a closed mesh
  that means the signed volume sum(a . (b x c)) / 6 over its triangles is the mesh's (positive) volume
  (the divergence theorem) and each triangle's normal points away from the mesh's centre (a convex mesh).
  USD: `orientation = "leftHanded"` means faces are wound clockwise seen from outside (UsdGeomMesh /
  UsdGeomGprim docs: the left-hand rule gives the outward normal), and a transform with a negative
  determinant mirrors the winding; both must come out outward.
- Visibility: `invisible` on a prim hides its whole subtree; a child with no visibility opinion of its own
  inherits it (UsdGeomImageable: visibility is "inherited" by default, ComputeVisibility).
"""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, Vt

from shadowopt.renderers.usd_loader import load_scene

# A unit cube's corners and its six faces wound counter-clockwise seen from outside (right-handed).
CORNERS = [(x, y, z) for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)]
FACES_CCW = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def new_stage(path):
    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(s, "Y")
    UsdGeom.SetStageMetersPerUnit(s, 1.0)
    return s


def cube_mesh(stage, path, left_handed: bool, scale=(2.0, 3.0, 4.0), translate=(5.0, 1.0, -2.0)):
    """A closed unit-cube mesh scaled by `scale` and moved to `translate` by its own transform (a negative
    scale entry mirrors it); its quads wound for `left_handed` (reversed, with orientation leftHanded)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    faces = [tuple(reversed(f)) for f in FACES_CCW] if left_handed else FACES_CCW
    mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*c) for c in CORNERS]))
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    if left_handed:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    api = UsdGeom.XformCommonAPI(mesh)
    api.SetTranslate(Gf.Vec3d(*translate))
    api.SetScale(Gf.Vec3f(*scale))
    return mesh


def outwardness(vertices, faces):
    """(signed volume, smallest normal . (centroid - centre) over the triangles, normalised)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    vol = float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c)))) / 6.0
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    centre = vertices[np.unique(faces)].mean(0)
    out = (a + b + c) / 3.0 - centre
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return vol, float(np.min(np.einsum("ij,ij->i", n, out)))


@pytest.mark.parametrize("left_handed", [False, True], ids=["rightHanded", "leftHanded"])
@pytest.mark.parametrize("mirrored", [False, True], ids=["plain", "mirrored"])
def test_closed_mesh_triangles_face_outward_for_either_orientation(tmp_path, left_handed, mirrored):
    s = new_stage(tmp_path / "c.usda")
    scale = (-2.0, 3.0, 4.0) if mirrored else (2.0, 3.0, 4.0)
    cube_mesh(s, "/Box", left_handed, scale=scale)
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "c.usda").geometry
    assert g.triangle_count == 12
    vol, worst = outwardness(g.vertices, g.faces)
    assert vol == pytest.approx(2.0 * 3.0 * 4.0, rel=1e-6), (left_handed, mirrored, vol)
    assert worst > 0.1, (left_handed, mirrored, worst)  # every triangle's normal points out of the box


def test_an_invisible_parent_hides_children_without_their_own_opinion(tmp_path):
    s = new_stage(tmp_path / "v.usda")
    UsdGeom.Cube.Define(s, "/Shown/Cube")
    UsdGeom.Xform.Define(s, "/Hidden").CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    UsdGeom.Cube.Define(s, "/Hidden/Child")  # no visibility opinion: inherits invisible
    UsdGeom.Xform.Define(s, "/Hidden/Deeper")
    UsdGeom.Cube.Define(s, "/Hidden/Deeper/Grandchild").CreateVisibilityAttr(UsdGeom.Tokens.inherited)
    UsdGeom.Cube.Define(s, "/Hidden/Sibling")  # another gprim of the same subtree
    s.GetRootLayer().Save()
    stage = Usd.Stage.Open(str(tmp_path / "v.usda"))
    for p in ("/Hidden/Child", "/Hidden/Deeper/Grandchild", "/Hidden/Sibling"):  # USD's own answer
        assert UsdGeom.Imageable(stage.GetPrimAtPath(p)).ComputeVisibility() == UsdGeom.Tokens.invisible
    g = load_scene(tmp_path / "v.usda").geometry
    assert g.prim_paths == ["/Shown/Cube"] and g.triangle_count == 12


def test_instanced_and_parent_mirrored_meshes_face_outward(tmp_path):
    """Prototypes (either orientation) placed by a PointInstancer with mirroring scales, and a leftHanded
    mesh under a mirroring parent Xform: each instance is a closed box whose triangles face outward."""
    s = new_stage(tmp_path / "i.usda")
    inst = UsdGeom.PointInstancer.Define(s, "/Inst")
    for lh in (False, True):
        cube_mesh(s, f"/Inst/Protos/B{int(lh)}", lh, scale=(1.0, 1.0, 1.0), translate=(0.0, 0.0, 0.0))
    inst.CreatePrototypesRel().SetTargets(["/Inst/Protos/B0", "/Inst/Protos/B1"])
    inst.CreateProtoIndicesAttr([0, 1, 0, 1])
    inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(5, 0, 0), Gf.Vec3f(0, 0, 7), Gf.Vec3f(9, 0, 9)])
    scales = [(1, 1, 1), (1, 1, 1), (-2, 1, 1), (-1, 3, 1)]
    inst.CreateScalesAttr([Gf.Vec3f(*v) for v in scales])
    UsdGeom.XformCommonAPI(UsdGeom.Xform.Define(s, "/Mirror")).SetScale(Gf.Vec3f(1, -1, 1))
    cube_mesh(s, "/Mirror/L", True, scale=(1.0, 2.0, 3.0), translate=(20.0, 0.0, 0.0))
    s.GetRootLayer().Save()
    g = load_scene(tmp_path / "i.usda").geometry
    volumes = {p: abs(float(np.prod(v))) for p, v in zip([f"/Inst[{k}]" for k in range(4)], scales)}
    volumes["/Mirror/L"] = 6.0
    assert len(g.prim_paths) == 5
    for k, path in enumerate(g.prim_paths):
        vol, worst = outwardness(g.vertices, g.faces[g.face_prim == k])
        expected = next(v for p, v in volumes.items() if path.startswith(p))
        assert vol == pytest.approx(expected, rel=1e-6) and worst > 0.1, (path, vol, worst)
