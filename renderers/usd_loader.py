"""USD stage -> LoadedScene: every renderable triangle merged into one mesh in the world frame,
plus cameras and lights with their USD paths.

- Composition (sublayers, references, payloads) as USD does it; asset paths are first checked by
  renderers.asset_resolver (local vs sandbox mode) and refused ones are dropped before USD opens them.
- Traversal includes instance proxies (instanceable prims) and expands PointInstancers; prims with
  purpose proxy/guide and invisible prims are skipped with their subtrees.
- Meshes are triangulated as authored (subdivision meshes as their cage); polygons with more than
  four corners by ear clipping in their best-fit plane, so concave faces come out right.
- Implicit prims (Cube, Sphere, Cylinder, Cone, Capsule, Plane) are tessellated.
- Units: the stage's upAxis and metersPerUnit (USD's fallbacks: Y and 0.01) -> solvers.frames world.
- usd-core's diagnostics (missing files, MaterialX it cannot read) become scene warnings.
Malformed input raises SceneError with a machine-readable code; nothing else escapes.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
import tempfile
import time
import zipfile

import numpy as np

from ..solvers.frames import stage_to_world as _stage_to_world
from ..solvers.frames import transform_directions, transform_points
from .asset_resolver import check_asset_path, unsafe_usdz_entries
from .scene_data import LoadedScene, SceneError, SceneGeometry, UsdCamera, UsdLight

SEGMENTS = 32  # tessellation of implicit round prims (around), half of it along
MAX_WARNINGS = 50
_USD_EXT = (".usd", ".usda", ".usdc", ".usdz")


# ---------------------------------------------------------------- diagnostics
@contextlib.contextmanager
def captured_stderr(sink: list[str]):
    """Collect what C++ code writes on file descriptor 2 (usd-core's diagnostics) into `sink`."""
    import sys

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
            sink.extend(_summarize_diagnostics(text))


def _summarize_diagnostics(text: str) -> list[str]:
    out = []
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        line = re.sub(r"^(Warning|Error|Coding Error|Runtime Error): in \S+ at line \d+ of \S+ -- ", r"\1: ", line)
        line = re.sub(r" \(instantiating stage on stage @[^@]*@ <0x[0-9a-f]+>\)", "", line)
        line = re.sub(r" <0x[0-9a-f]+>", "", line)
        if line not in out:
            out.append(line)
    return out


# ---------------------------------------------------------------- pre-checks
def _check_file(path: str) -> None:
    if not os.path.exists(path):
        raise SceneError("not_found", f"{path}: no such file")
    if os.path.isdir(path):
        raise SceneError("not_usd", f"{path}: is a folder, not a USD file")
    ext = os.path.splitext(path)[1].lower()
    if ext not in _USD_EXT:
        raise SceneError("not_usd", f"{path}: not a USD file (extension {ext or 'none'}; expected .usd, .usda, .usdc or .usdz)")
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as e:
        raise SceneError("not_found", f"{path}: cannot read ({e.strerror})") from e
    if not head:
        raise SceneError("not_usd", f"{path}: the file is empty")
    kind = "usda" if head.startswith(b"#usda") else "usdc" if head.startswith(b"PXR-USDC") else \
        "usdz" if head.startswith(b"PK\x03\x04") else None
    expected = {".usda": ("usda",), ".usdc": ("usdc",), ".usdz": ("usdz",), ".usd": ("usda", "usdc")}[ext]
    if kind not in expected:
        raise SceneError("not_usd", f"{path}: not a {ext} file (it does not start with a USD header)")
    if kind == "usdz" and not zipfile.is_zipfile(path):
        raise SceneError("corrupt", f"{path}: the usdz archive is damaged")


# ---------------------------------------------------------------- asset resolution
def _rewrite_dependencies(root: str, mode: str, asset_root: str | None, warnings: list[str], keep: list):
    """Walk the layer graph; refused asset paths are removed from anonymous copies of the layers that
    name them (re-anchoring the rest), so USD never opens them. Returns the root layer to open."""
    from pxr import Sdf

    archive = root if root.lower().endswith(".usdz") else None
    memo: dict[str, str] = {}

    def visit(layer_id: str, depth: int = 0) -> str:
        if layer_id in memo or depth > 64:
            return memo.get(layer_id, layer_id)
        memo[layer_id] = layer_id
        layer = Sdf.Layer.FindOrOpen(layer_id)
        if layer is None:
            return layer_id
        new_paths: dict[str, str] = {}
        for dep in layer.GetCompositionAssetDependencies():
            ok, reason = check_asset_path(dep, layer_id, mode, asset_root, archive)
            if not ok:
                warnings.append(f"refused asset @{dep}@ named in {_short(layer_id)}: {reason}; it was not read")
                new_paths[dep] = ""
                continue
            resolved = layer.ComputeAbsolutePath(dep)
            sub = visit(resolved, depth + 1)
            if sub != resolved:
                new_paths[dep] = sub
        if not new_paths:
            return layer_id
        copy = Sdf.Layer.CreateAnonymous(os.path.basename(layer_id) + ".sandboxed.usda")
        copy.TransferContent(layer)
        for dep in copy.GetCompositionAssetDependencies():
            copy.UpdateCompositionAssetDependency(dep, new_paths.get(dep, layer.ComputeAbsolutePath(dep)))
        keep.append(copy)
        memo[layer_id] = copy.identifier
        return copy.identifier

    return visit(root)


def _short(identifier: str) -> str:
    return os.path.basename(identifier) if "[" not in identifier else identifier.rsplit("/", 1)[-1]


# ---------------------------------------------------------------- triangulation
def _newell_normal(pts: np.ndarray) -> np.ndarray:
    nxt = np.roll(pts, -1, axis=0)
    return np.array([np.sum((pts[:, 1] - nxt[:, 1]) * (pts[:, 2] + nxt[:, 2])),
                     np.sum((pts[:, 2] - nxt[:, 2]) * (pts[:, 0] + nxt[:, 0])),
                     np.sum((pts[:, 0] - nxt[:, 0]) * (pts[:, 1] + nxt[:, 1]))])


def ear_clip(pts: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangulate one simple polygon (n, 3) given in order; returns local index triples."""
    n = len(pts)
    if n < 3:
        return []
    if n == 3:
        return [(0, 1, 2)]
    normal = _newell_normal(pts)
    if np.linalg.norm(normal) < 1e-30:
        return [(0, i, i + 1) for i in range(1, n - 1)]  # degenerate: any fan has zero area
    ax = int(np.argmax(np.abs(normal)))
    keep = [a for a in range(3) if a != ax]
    p2 = pts[:, keep].astype(np.float64)
    if normal[ax] < 0:
        p2 = p2[:, ::-1]  # make the projected polygon counter-clockwise
    idx = list(range(n))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < n * n:
        guard += 1
        m = len(idx)
        for k in range(m):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
            a, b, c = p2[i0], p2[i1], p2[i2]
            if cross(a, b, c) <= 0:
                continue  # reflex (or flat) corner: not an ear
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = p2[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                idx.pop(k)
                break
        else:
            break  # no ear found (self-intersecting polygon): fan the rest
    tris += [(idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1)]
    return tris


def triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygon soup -> (T, 3) vertex indices. Triangles and quads vectorised, larger faces ear-clipped."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    out = []
    tri = counts == 3
    if tri.any():
        s = starts[tri]
        out.append(np.stack([indices[s], indices[s + 1], indices[s + 2]], axis=1))
    quad = counts == 4
    if quad.any():
        s = starts[quad]
        a, b, c, d = (indices[s + k] for k in range(4))
        pa, pb, pc, pd = points[a], points[b], points[c], points[d]
        n = np.cross(pc - pa, pd - pb)  # the quad's normal (diagonal cross product)
        # Split along a-c unless b or d is a reflex corner, in which case a-c leaves the quad.
        ok_ac = (np.sum(np.cross(pb - pa, pc - pa) * n, axis=1) > 0) & (np.sum(np.cross(pc - pa, pd - pa) * n, axis=1) > 0)
        t1 = np.where(ok_ac[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
        t2 = np.where(ok_ac[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
        out += [t1, t2]
    for f in np.nonzero(counts > 4)[0]:
        poly = indices[starts[f]:starts[f] + counts[f]]
        out.append(np.array([[poly[i], poly[j], poly[k]] for i, j, k in ear_clip(points[poly])], dtype=np.int64).reshape(-1, 3))
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)


# ---------------------------------------------------------------- implicit prims
def _axis_matrix(axis: str) -> np.ndarray:
    """Rotation taking +Z to the given axis (a cyclic permutation of coordinates)."""
    if axis == "X":
        return np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)
    if axis == "Y":
        return np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float)
    return np.eye(3)


def _revolve(profile: list[tuple[float, float]], seg: int = SEGMENTS):
    """Surface of revolution about +Z of a (radius, z) profile; zero radius collapses to a point."""
    ang = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    verts, faces = [], []
    rings = []
    for r, z in profile:
        if r == 0:
            rings.append([len(verts)])
            verts.append((0.0, 0.0, z))
        else:
            rings.append(list(range(len(verts), len(verts) + seg)))
            verts += [(r * math.cos(a), r * math.sin(a), z) for a in ang]
    for ra, rb in zip(rings[:-1], rings[1:]):
        for i in range(seg):
            j = (i + 1) % seg
            a0, a1 = ra[i % len(ra)], ra[j % len(ra)]
            b0, b1 = rb[i % len(rb)], rb[j % len(rb)]
            if len(ra) > 1:
                faces.append((a0, a1, b1) if len(rb) == 1 else (a0, a1, b0))
            if len(rb) > 1:
                faces.append((a1, b1, b0) if len(ra) > 1 else (a0, b1, b0))
    return np.array(verts, float), np.array(faces, np.int64)


def implicit_mesh(prim, time_code):
    """Tessellate a UsdGeom implicit prim in its local frame. Returns (points, triangles) or None."""
    from pxr import UsdGeom

    t = prim.GetTypeName()

    def get(name, default):
        a = prim.GetAttribute(name)
        v = a.Get(time_code) if a else None
        return default if v is None else v

    half = SEGMENTS // 2
    if t == "Cube":
        s = float(get("size", 2.0)) / 2
        v = np.array([[x, y, z] for x in (-s, s) for y in (-s, s) for z in (-s, s)], float)
        f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        return v, f
    if t == "Sphere":
        r = float(get("radius", 1.0))
        prof = [(r * math.sin(th), -r * math.cos(th)) for th in np.linspace(0, np.pi, half + 1)]
        prof[0], prof[-1] = (0.0, -r), (0.0, r)
        return _revolve(prof)
    if t in ("Cylinder", "Cone", "Capsule"):
        r = float(get("radius", 1.0 if t != "Capsule" else 0.5))
        h = float(get("height", 2.0 if t != "Capsule" else 1.0))
        axis = str(get("axis", "Z"))
        if t == "Cylinder":
            prof = [(0.0, -h / 2), (r, -h / 2), (r, h / 2), (0.0, h / 2)]
        elif t == "Cone":
            prof = [(0.0, -h / 2), (r, -h / 2), (0.0, h / 2)]
        else:
            q = max(half // 2, 2)
            bottom = [(r * math.sin(a), -h / 2 - r * math.cos(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            top = [(r * math.cos(a), h / 2 + r * math.sin(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            bottom[0], top[-1] = (0.0, -h / 2 - r), (0.0, h / 2 + r)
            prof = bottom + top
        v, f = _revolve(prof)
        return v @ _axis_matrix(axis).T, f
    if t == "Plane":
        w, l = float(get("width", 2.0)) / 2, float(get("length", 2.0)) / 2
        axis = str(get("axis", "Z"))
        v = np.array([[-w, -l, 0], [w, -l, 0], [w, l, 0], [-w, l, 0]], float)
        return v @ _axis_matrix(axis).T, np.array([[0, 1, 2], [0, 2, 3]])
    return None


# ---------------------------------------------------------------- the loader
def _np_matrix(gf) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> NumPy 4x4 acting on column vectors."""
    return np.array(gf, dtype=np.float64).T


def _mesh_triangles(prim, time_code, warnings):
    from pxr import UsdGeom

    path = str(prim.GetPath())
    mesh = UsdGeom.Mesh(prim)
    pts = mesh.GetPointsAttr().Get(time_code)
    counts = mesh.GetFaceVertexCountsAttr().Get(time_code)
    idx = mesh.GetFaceVertexIndicesAttr().Get(time_code)
    if pts is None or counts is None or idx is None or len(pts) == 0 or len(counts) == 0:
        return None
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(counts, dtype=np.int64)
    idx = np.asarray(idx, dtype=np.int64)
    if not np.all(np.isfinite(pts)):
        warnings.append(f"{path}: skipped, its points contain NaN or infinite values")
        return None
    if counts.sum() != len(idx) or np.any(counts < 0):
        warnings.append(f"{path}: skipped, faceVertexCounts sum to {int(counts.sum())} but there are "
                        f"{len(idx)} faceVertexIndices")
        return None
    if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
        warnings.append(f"{path}: skipped, faceVertexIndices reach {int(idx.max())} (or below 0) but there are "
                        f"{len(pts)} points")
        return None
    small = counts < 3
    if small.any():
        warnings.append(f"{path}: {int(small.sum())} faces with fewer than 3 vertices dropped")
        keep = np.repeat(~small, counts)
        idx, counts = idx[keep], counts[~small]
        if len(counts) == 0:
            return None
    return pts, triangulate(pts, counts, idx)


def load_scene(path, *, time_code: float | None = None, asset_root: str | None = None,
               sandbox: bool = False) -> LoadedScene:
    """Open a USD file and return its triangles, cameras and lights in the world frame."""
    t_start = time.perf_counter()
    path = os.fspath(path)
    _check_file(path)
    warnings: list[str] = []
    diag: list[str] = []
    keep: list = []
    try:
        from pxr import Sdf, Tf, Usd, UsdGeom
    except ImportError as e:  # pragma: no cover - set-up problem
        raise SceneError("unavailable", f"usd-core is not installed: {e}") from e
    mode = "sandbox" if sandbox else "local"
    if asset_root is not None and not sandbox and not os.path.isdir(asset_root):
        raise SceneError("bad_option", f"asset root {asset_root!r} is not a folder")
    try:
        with captured_stderr(diag):
            if path.lower().endswith(".usdz") and sandbox:
                bad = unsafe_usdz_entries(path)
                if bad:
                    warnings.append(f"usdz entries with unsafe names refused and not read: {', '.join(bad[:5])}")
            root = os.path.abspath(path)
            if sandbox or asset_root is not None:
                root = _rewrite_dependencies(root, mode, asset_root, warnings, keep)
            layer = Sdf.Layer.FindOrOpen(root)
            if layer is None:
                raise SceneError("corrupt", f"{path}: USD could not read the file (truncated or damaged)")
            stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
            if stage is None:
                raise SceneError("corrupt", f"{path}: USD could not open the stage")
            scene = _extract(stage, path, time_code, warnings)
    except SceneError:
        raise
    except Tf.ErrorException as e:
        msg = _usd_error_text(str(e))
        raise SceneError("corrupt", f"{path}: USD could not read the file: {msg[:300]}") from e
    except (RuntimeError, ValueError, OSError, zipfile.BadZipFile) as e:
        raise SceneError("corrupt", f"{path}: {type(e).__name__}: {str(e)[:300]}") from e
    scene.warnings = (warnings + diag)[:MAX_WARNINGS]
    if len(warnings) + len(diag) > MAX_WARNINGS:
        scene.warnings.append(f"... and {len(warnings) + len(diag) - MAX_WARNINGS} more warnings")
    scene.scene_hash = _scene_hash(stage, path, keep)
    scene.load_s = time.perf_counter() - t_start
    del keep
    return scene


def _usd_error_text(text: str) -> str:
    """The useful part of a Tf error: drop the C++ location and namespaces."""
    text = text.strip().strip("'")
    m = re.search(r" : '(.*)'?$", text, re.S)
    if m:
        text = m.group(1)
    text = re.sub(r"pxrInternal_v\w+::", "", text).strip().strip("'")
    return text or "unreadable"


def _scene_hash(stage, path, keep) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read())
    for layer in sorted(stage.GetUsedLayers(), key=lambda l: l.identifier):
        if layer.anonymous:
            h.update(layer.ExportToString().encode())
        elif layer.realPath and os.path.isfile(layer.realPath):
            h.update(layer.identifier.rsplit("/", 1)[-1].encode())
            with open(layer.realPath, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
    return h.hexdigest()


def _stage_frame(stage, warnings):
    from pxr import UsdGeom

    layer = stage.GetRootLayer()
    up = "Y"
    if stage.HasAuthoredMetadata("upAxis"):
        up = str(stage.GetMetadata("upAxis"))
        if up not in ("Y", "Z"):
            warnings.append(f"upAxis {up!r} is not Y or Z: treated as Y")
            up = "Y"
    if stage.HasAuthoredMetadata("metersPerUnit"):
        mpu = float(stage.GetMetadata("metersPerUnit"))
        if not (math.isfinite(mpu) and mpu > 0):
            warnings.append(f"metersPerUnit {mpu!r} is not a positive number: USD's fallback 0.01 used")
            mpu = 0.01
    else:
        mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
        warnings.append(f"metersPerUnit not authored: USD's fallback {mpu} (centimetres) used")
    return up, mpu


def _extract(stage, path, time_code, warnings) -> LoadedScene:
    from pxr import Usd, UsdGeom, UsdLux

    tc = Usd.TimeCode.Default() if time_code is None else Usd.TimeCode(time_code)
    up, mpu = _stage_frame(stage, warnings)
    s2w = _stage_to_world(up, mpu)
    dp = stage.GetRootLayer().defaultPrim
    if dp and not stage.GetPrimAtPath("/" + dp if not dp.startswith("/") else dp):
        warnings.append(f"defaultPrim {dp!r} does not exist in the stage")
    xcache = UsdGeom.XformCache(tc)
    verts, faces, prims, prim_paths = [], [], [], []
    nverts = 0
    cameras, lights = [], []

    def add(local_pts, tris, world_m, prim_path):
        nonlocal nverts
        if tris is None or len(tris) == 0:
            return
        m = s2w @ world_m
        verts.append(transform_points(m, local_pts))
        t = np.asarray(tris, dtype=np.int64) + nverts
        if np.linalg.det(m[:3, :3]) < 0:
            t = t[:, ::-1]  # a mirroring transform flips winding; keep it consistent
        faces.append(t)
        prims.append(np.full(len(tris), len(prim_paths), np.int32))
        prim_paths.append(prim_path)
        nverts += len(local_pts)

    def geometry_of(prim):
        if prim.IsA(UsdGeom.Mesh):
            return _mesh_triangles(prim, tc, warnings)
        if prim.IsA(UsdGeom.Gprim):
            r = implicit_mesh(prim, tc)
            if r is None and not prim.IsA(UsdGeom.Curves) and not prim.IsA(UsdGeom.Points):
                warnings.append(f"{prim.GetPath()}: {prim.GetTypeName()} is not supported, skipped")
            return r
        return None

    def skip_subtree(prim) -> bool:
        img = UsdGeom.Imageable(prim)
        if not img:
            return False
        vis = img.GetVisibilityAttr().Get(tc)
        if vis == UsdGeom.Tokens.invisible:
            return True
        purpose = img.GetPurposeAttr().Get(tc)
        return purpose in (UsdGeom.Tokens.proxy, UsdGeom.Tokens.guide)

    it = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in it:
        if skip_subtree(prim):
            it.PruneChildren()
            continue
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            _expand_instancer(prim, tc, xcache, add, geometry_of, skip_subtree, warnings)
            continue
        if prim.IsA(UsdGeom.Camera):
            cameras.append(_camera(prim, tc, xcache, s2w, mpu))
            continue
        if prim.HasAPI(UsdLux.LightAPI) or "Light" in prim.GetTypeName():
            lt = _light(prim, tc, xcache, s2w)
            if lt is not None:
                lights.append(lt)
                continue
        g = geometry_of(prim)
        if g is not None:
            add(g[0], g[1], _np_matrix(xcache.GetLocalToWorldTransform(prim)), str(prim.GetPath()))

    if not verts:
        raise SceneError("empty_stage", f"{path}: the stage has no renderable triangles"
                         + (f" ({len(warnings)} warnings: {warnings[0]})" if warnings else ""))
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    if not np.all(np.isfinite(V)):
        raise SceneError("bad_mesh", f"{path}: transformed points are not finite (a degenerate transform?)")
    geometry = SceneGeometry(V, F.astype(np.int32), np.concatenate(prims), prim_paths)
    return LoadedScene(path, "", geometry, cameras, lights, up, mpu, s2w,
                       None if time_code is None else float(time_code), [])


def _expand_instancer(prim, tc, xcache, add, geometry_of, skip_subtree, warnings):
    from pxr import Usd, UsdGeom

    inst = UsdGeom.PointInstancer(prim)
    protos = inst.GetPrototypesRel().GetTargets()
    xforms = inst.ComputeInstanceTransformsAtTime(tc if not tc.IsDefault() else Usd.TimeCode.EarliestTime(), tc if not tc.IsDefault() else Usd.TimeCode.EarliestTime())
    indices = inst.GetProtoIndicesAttr().Get(tc)
    if xforms is None or indices is None:
        return
    indices = np.asarray(indices)
    inst_world = _np_matrix(xcache.GetLocalToWorldTransform(prim))
    stage = prim.GetStage()
    proto_geo = []
    for target in protos:
        root = stage.GetPrimAtPath(target)
        parts = []
        if root:
            parent_inv = np.linalg.inv(_np_matrix(xcache.GetLocalToWorldTransform(root.GetParent())))
            rng = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
            for p in rng:
                if skip_subtree(p):
                    rng.PruneChildren()
                    continue
                g = geometry_of(p)
                if g is not None:
                    rel = parent_inv @ _np_matrix(xcache.GetLocalToWorldTransform(p))
                    parts.append((g, rel, str(p.GetPath())))
        proto_geo.append(parts)
    for k, (pi, xf) in enumerate(zip(indices, xforms)):
        if pi < 0 or pi >= len(proto_geo):
            warnings.append(f"{prim.GetPath()}: instance {k} names prototype {pi}, which does not exist")
            continue
        m = inst_world @ _np_matrix(xf)
        for (pts, tris), rel, ppath in proto_geo[pi]:
            add(pts, tris, m @ rel, f"{prim.GetPath()}[{k}]{ppath[len(str(prim.GetPath())):]}")


def _camera(prim, tc, xcache, s2w, mpu) -> UsdCamera:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    focal = float(cam.GetFocalLengthAttr().Get(tc) or 50.0)
    hap = float(cam.GetHorizontalApertureAttr().Get(tc) or 20.955)
    vap = float(cam.GetVerticalApertureAttr().Get(tc) or 15.2908)
    clip = cam.GetClippingRangeAttr().Get(tc) or (1.0, 1e6)
    m = s2w @ _np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    fwd = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    up = transform_directions(m, np.array([0.0, 1.0, 0.0]))
    scale = float(abs(np.linalg.det(m[:3, :3])) ** (1.0 / 3.0))
    fov = math.degrees(2.0 * math.atan(vap / (2.0 * focal)))
    return UsdCamera(str(prim.GetPath()), pos, fwd, up, fov, float(clip[0]) * scale, float(clip[1]) * scale,
                     focal, hap, vap)


def _light(prim, tc, xcache, s2w) -> UsdLight | None:
    from pxr import UsdLux

    t = prim.GetTypeName()
    path = str(prim.GetPath())
    m = s2w @ _np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    axis = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    cone = None
    if prim.HasAPI(UsdLux.ShapingAPI):
        a = UsdLux.ShapingAPI(prim).GetShapingConeAngleAttr().Get(tc)
        cone = float(a) if a is not None else 90.0
    if t == "DistantLight":
        return UsdLight(path, t, "directional", direction=axis)
    if t == "SphereLight":
        if cone is not None and cone < 180.0:
            return UsdLight(path, t, "spot", position=pos, direction=axis, cone_deg=cone,
                            note="sphere light with a shaping cone")
        return UsdLight(path, t, "point", position=pos)
    if t in ("DiskLight", "RectLight"):
        c = cone if cone is not None and cone < 90.0 else 90.0
        return UsdLight(path, t, "spot", position=pos, direction=axis, cone_deg=c,
                        note=f"{t} emits into the hemisphere along its -Z: a spot of half-angle {c:g} deg")
    if t == "DomeLight" or t == "DomeLight_1":
        return UsdLight(path, t, "ignored", note="dome lights light from everywhere: no shadow map, ignored")
    if prim.HasAPI(UsdLux.LightAPI) or t.endswith("Light"):
        return UsdLight(path, t, "ignored", note=f"{t} is not modelled: ignored")
    return None
