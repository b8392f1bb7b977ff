"""The stage's traversal: every renderable triangle merged into one mesh in the world frame, plus
cameras and lights (renderers.usd_loader opens the stage).

- Budget: `max_triangles` is charged prim by prim during the traversal, before anything is
  tessellated, triangulated or copied: meshes by faceVertexCounts (a face of n corners is n - 2
  triangles), implicit prims by their fixed tessellation counts, point instancers as visible
  instances x prototype triangles; SceneError("too_many_triangles") as soon as the count exceeds it.
- Traversal includes instance proxies (instanceable prims) and expands PointInstancers (masked ids
  skipped); invisible prims are skipped with their subtrees; gprims are drawn when their computed
  purpose is default or render.
"""
from __future__ import annotations

import os

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux

from ..solvers.frames import stage_to_world as _stage_to_world
from ..solvers.frames import transform_points
from .implicit_prims import implicit_mesh, implicit_triangle_count
from .scene_data import LoadedScene, SceneError, SceneGeometry
from .stage_units import stage_frame
from .usd_cameras_lights import read_camera, read_light
from .usd_meshes import face_triangles, mesh_triangles
from .usd_values import as_array, attr_value, np_matrix


class Budget:
    """The running triangle count of one load; `charge` raises as soon as it exceeds the limit."""

    def __init__(self, limit: int | None, max_prims: int | None = None):
        self.limit = limit
        self.count = 0
        self.max_prims = max_prims
        self.prims = 0

    def prim(self, prim) -> None:
        """Count one more composed prim visited (instancer prototypes' prims included)."""
        self.prims += 1
        if self.max_prims is not None and self.prims > self.max_prims:
            raise SceneError("too_many_prims", f"the scene has more than {self.max_prims} prims (limit "
                             f"{self.max_prims}); the limit was passed at {prim.GetPath()}")

    def charge(self, n: int, what: str) -> None:
        self.count += int(n)
        if self.limit is not None and self.count > self.limit:
            raise SceneError("too_many_triangles", f"the scene has more than {self.limit} triangles "
                             f"(limit {self.limit}); counted before tessellating, the limit was passed at {what}")


def extract(stage, path, time_code, warnings, budget: Budget | None = None, name=None,
             layer_name=None) -> LoadedScene:
    budget = budget or Budget(None)
    name = name or os.path.basename(path)
    tc = Usd.TimeCode.Default() if time_code is None else Usd.TimeCode(time_code)
    up, mpu = stage_frame(stage, warnings, layer_name)
    s2w = _stage_to_world(up, mpu)
    dp = stage.GetRootLayer().defaultPrim
    if dp and not stage.GetPrimAtPath("/" + dp if not dp.startswith("/") else dp):
        warnings.append(f"defaultPrim {dp!r} does not exist in the stage")
    xcache = UsdGeom.XformCache(tc) if not tc.IsDefault() else _DefaultTimeXforms(warnings)
    verts, faces, prims, prim_paths = [], [], [], []
    nverts = 0
    cameras, lights = [], []

    def add(local_pts, tris, world_m, prim_path):
        nonlocal nverts
        if tris is None or len(tris) == 0:
            return
        m = s2w @ world_m
        world_pts = transform_points(m, local_pts)
        if not np.all(np.isfinite(world_pts)):
            warnings.append(f"{prim_path}: skipped, its transform makes the points non-finite")
            return
        verts.append(world_pts)
        t = np.asarray(tris, dtype=np.int64) + nverts
        if np.linalg.det(m[:3, :3]) < 0:
            t = t[:, ::-1]  # a mirroring transform flips winding; keep it consistent
        faces.append(t)
        prims.append(np.full(len(tris), len(prim_paths), np.int32))
        prim_paths.append(prim_path)
        nverts += len(local_pts)

    def geometry_of(prim, charged: bool = False):
        """The prim's (points, triangles), charged to the budget first unless `charged` (instancer
        prototypes: their instances were charged)."""
        if not prim.IsA(UsdGeom.Gprim) or not renderable_purpose(prim):
            return None
        if prim.IsA(UsdGeom.Mesh):
            return mesh_triangles(prim, tc, warnings, None if charged else budget.charge)
        else:
            if not charged:
                budget.charge(implicit_triangle_count(prim.GetTypeName()), str(prim.GetPath()))
            r = implicit_mesh(prim, tc, warnings)
            if r is None and not prim.IsA(UsdGeom.Curves) and not prim.IsA(UsdGeom.Points):
                warnings.append(f"{prim.GetPath()}: {prim.GetTypeName()} is not supported, skipped")
            return r
        return None

    def triangles_of(prim) -> int:
        """What geometry_of(prim) would make, without tessellating (meshes: faceVertexCounts only)."""
        if not prim.IsA(UsdGeom.Gprim) or not renderable_purpose(prim):
            return 0
        if prim.IsA(UsdGeom.Mesh):
            return face_triangles(attr_value(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr(), tc))
        return implicit_triangle_count(prim.GetTypeName())

    def skip_subtree(prim) -> bool:
        """Invisible prims hide their whole subtree (visibility is inherited)."""
        img = UsdGeom.Imageable(prim)
        if not img:
            return False
        return img.GetVisibilityAttr().Get(tc) == UsdGeom.Tokens.invisible

    def renderable_purpose(prim) -> bool:
        """Computed purpose (a prim without its own opinion inherits its ancestors'): default and
        render are drawn, proxy and guide are not, nor is a token USD does not know."""
        purpose = UsdGeom.Imageable(prim).ComputePurpose()
        if purpose in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render):
            return True
        if purpose not in (UsdGeom.Tokens.proxy, UsdGeom.Tokens.guide):
            warnings.append(f"{prim.GetPath()}: unknown purpose {purpose!r}, not drawn")
        return False

    it = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in it:
        budget.prim(prim)
        if skip_subtree(prim):
            it.PruneChildren()
            continue
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            if renderable_purpose(prim):
                _expand_instancer(prim, tc, xcache, add, geometry_of, triangles_of, skip_subtree, warnings,
                                  budget)
            continue
        if prim.IsA(UsdGeom.Camera):
            cameras.append(read_camera(prim, tc, xcache, s2w, mpu, warnings))
            continue
        if prim.HasAPI(UsdLux.LightAPI) or "Light" in prim.GetTypeName():
            lt = read_light(prim, tc, xcache, s2w)
            if lt is not None:
                lights.append(lt)
                continue
        g = geometry_of(prim)
        if g is not None:
            add(g[0], g[1], np_matrix(xcache.GetLocalToWorldTransform(prim)), str(prim.GetPath()))

    if not verts:
        raise SceneError("empty_stage", f"{name}: the stage has no renderable triangles"
                         + (f" ({len(warnings)} warnings: {warnings[0]})" if warnings else ""))
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    if not np.all(np.isfinite(V)):
        raise SceneError("bad_mesh", f"{name}: transformed points are not finite (a degenerate transform?)")
    geometry = SceneGeometry(V, F.astype(np.int32), np.concatenate(prims), prim_paths)
    return LoadedScene(path, "", geometry, cameras, lights, up, mpu, s2w,
                       None if time_code is None else float(time_code), [])


class _DefaultTimeXforms:
    """UsdGeom.XformCache at the default time, except that a prim whose transform ops have time
    samples but no default value is read at its first sample (as points are), not as identity."""

    def __init__(self, warnings: list[str]):
        self._cache = UsdGeom.XformCache()
        self._memo: dict = {}
        self._warnings = warnings
        self._identity = Gf.Matrix4d(1.0)

    def _local(self, prim):
        xf = UsdGeom.Xformable(prim)
        if not xf:
            return self._identity, False
        t = Usd.TimeCode.Default()
        if xf.TransformMightBeTimeVarying():
            late = [op for op in xf.GetOrderedXformOps()
                    if op.GetAttr().Get(t) is None and op.GetNumTimeSamples() > 0]
            if late:
                first = min(op.GetTimeSamples()[0] for op in late)
                t = Usd.TimeCode(first)
                self._warnings.append(f"{prim.GetPath()}: transform has only time samples: read at its first "
                                      f"sample t={first:g}")
        return xf.GetLocalTransformation(t), xf.GetResetXformStack()

    def GetLocalToWorldTransform(self, prim):  # noqa: N802 - the XformCache name
        key = prim.GetPath()
        m = self._memo.get(key)
        if m is None:
            parent = prim.GetParent()
            local, reset = self._local(prim)
            if reset or not parent or parent.IsPseudoRoot():
                m = local
            else:
                m = local * self.GetLocalToWorldTransform(parent)  # row vectors: local first
            self._memo[key] = m
        return m


def _expand_instancer(prim, tc, xcache, add, geometry_of, triangles_of, skip_subtree, warnings, budget):
    """Every visible instance of a PointInstancer: prototype geometry placed by the instance
    transforms (which include each prototype root's own transform); invisibleIds/inactiveIds masked.

    The budget is charged visible instances x prototype triangles (counted without tessellating)
    before any instance transform is computed or any prototype tessellated."""
    inst = UsdGeom.PointInstancer(prim)
    ipath = str(prim.GetPath())
    protos = inst.GetPrototypesRel().GetTargets()
    t = tc
    if tc.IsDefault():
        # The instancer's arrays may be time-sampled only: read them where they have values.
        attr = inst.GetPositionsAttr()
        if attr.Get(tc) is None and attr.GetNumTimeSamples() > 0:
            t = Usd.TimeCode(attr.GetTimeSamples()[0])
            warnings.append(f"{ipath}: instance positions have only time samples: read at t={t.GetValue():g}")
    indices = as_array(inst.GetProtoIndicesAttr().Get(t), None, np.int64)
    if indices is None or not len(indices):
        return
    mask = inst.ComputeMaskAtTime(t)
    visible = np.ones(len(indices), bool) if not mask else np.asarray(mask, bool)
    if len(visible) != len(indices):
        visible = np.ones(len(indices), bool)
    stage = prim.GetStage()
    roots = [stage.GetPrimAtPath(target) for target in protos]
    proto_tris = np.zeros(len(roots), np.int64)
    for k, root in enumerate(roots):
        if root and not skip_subtree(root):
            rng = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
            for p in rng:
                budget.prim(p)
                if skip_subtree(p):
                    rng.PruneChildren()
                    continue
                proto_tris[k] += triangles_of(p)
    named = visible & (indices >= 0) & (indices < len(roots))
    per_proto = np.bincount(indices[named], minlength=len(roots)) if named.any() else np.zeros(len(roots), np.int64)
    total = int(np.dot(per_proto.astype(np.int64), proto_tris))
    budget.charge(total, f"{ipath} ({int(named.sum())} instances of prototypes with "
                  f"{', '.join(str(int(x)) for x in proto_tris[:4])}{'...' if len(proto_tris) > 4 else ''} triangles)")
    bad = int((visible & ~named).sum())
    if bad:
        warnings.append(f"{ipath}: {bad} instances name prototypes that do not exist; skipped")
    for target, root in zip(protos, roots):
        if not root:
            warnings.append(f"{ipath}: prototype {target} does not exist")
    if total == 0:
        return
    xforms = inst.ComputeInstanceTransformsAtTime(t, t, UsdGeom.PointInstancer.IncludeProtoXform,
                                                  UsdGeom.PointInstancer.IgnoreMask)
    if xforms is None or len(xforms) != len(indices):
        warnings.append(f"{ipath}: instance transforms could not be computed (mismatched array sizes?); skipped")
        return
    inst_world = np_matrix(xcache.GetLocalToWorldTransform(prim))
    proto_geo = []
    for k, root in enumerate(roots):
        parts = []
        if root and per_proto[k] and proto_tris[k] and not skip_subtree(root):
            # relative to the prototype root: its own transform comes with the instance transforms
            root_inv = np.linalg.inv(np_matrix(xcache.GetLocalToWorldTransform(root)))
            rng = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
            for p in rng:
                if skip_subtree(p):
                    rng.PruneChildren()
                    continue
                g = geometry_of(p, charged=True)
                if g is not None:
                    rel = root_inv @ np_matrix(xcache.GetLocalToWorldTransform(p))
                    parts.append((g, rel, str(p.GetPath())))
        proto_geo.append(parts)
    for k in np.flatnonzero(named):
        pi = indices[k]
        if not proto_geo[pi]:
            continue
        m = inst_world @ np_matrix(xforms[int(k)])
        for (pts, tris), rel, ppath in proto_geo[pi]:
            sub = ppath[len(ipath):] if ppath.startswith(ipath) else ppath
            add(pts, tris, m @ rel, f"{ipath}[{k}]{sub}")
