"""USD stage -> LoadedScene: every renderable triangle merged into one mesh in the world frame,
plus cameras and lights with their USD paths.

- Composition (sublayers, references, payloads) as USD does it. With `asset_root` or `sandbox`, every
  asset path (composition arcs and value clips) is first checked by renderers.asset_resolver and the
  layers naming refused ones are replaced by anonymous copies without them, so USD never opens them.
- Traversal includes instance proxies (instanceable prims) and expands PointInstancers (masked ids
  skipped); invisible prims are skipped with their subtrees; gprims are drawn when their computed
  purpose is default or render.
- Meshes are triangulated as authored (subdivision meshes as their cage): triangles and quads
  vectorised, larger faces fanned when a vectorised check finds them convex, ear-clipped otherwise.
- Implicit prims (Cube, Sphere, Cylinder, Cone, Capsule, Plane, and the *_1 variants) are tessellated.
- Units: the stage's upAxis and metersPerUnit (USD's fallbacks: Y and 0.01) -> solvers.frames world.
- At the default time code, attributes with time samples but no default are read at their first sample.
- usd-core's diagnostics (missing files, MaterialX it cannot read) become scene warnings.
Malformed input raises SceneError with a machine-readable code (not_found, not_usd, corrupt,
unsafe_archive, empty_stage, bad_option, too_large, internal); nothing else escapes.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import posixpath
import re
import tempfile
import threading
import time
import zipfile

import numpy as np

from ..solvers.frames import stage_to_world as _stage_to_world
from ..solvers.frames import transform_directions, transform_points
from .asset_resolver import check_asset_path, is_unsafe_entry_name, usdz_entries
from .scene_data import LoadedScene, SceneError, SceneGeometry, UsdCamera, UsdLight

SEGMENTS = 32  # tessellation of implicit round prims (around), half of it along
MAX_WARNINGS = 50
_USD_EXT = (".usd", ".usda", ".usdc", ".usdz")


# ---------------------------------------------------------------- diagnostics
_FD2_LOCK = threading.RLock()  # fd 2 is process-wide: one redirect at a time (loads are serialised)


@contextlib.contextmanager
def captured_stderr(sink: list[str]):
    """Collect what C++ code writes on file descriptor 2 (usd-core's diagnostics) into `sink`.

    usd-core's Python bindings offer no diagnostic delegate, so fd 2 is redirected to a temporary
    file for the duration. Anything other threads write to stderr meanwhile lands there too."""
    with _FD2_LOCK:
        with _redirect_fd2(sink):
            yield


@contextlib.contextmanager
def _redirect_fd2(sink: list[str]):
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
    name them (re-anchoring the rest), so USD never opens them. Value clips (which USD opens for
    attribute values, outside composition) are checked the same way. Returns the root layer to open."""
    from pxr import Sdf, Tf

    archive = root if root.lower().endswith(".usdz") else None
    first_entry = usdz_entries(archive)[0] if archive else None
    memo: dict[str, str] = {}

    def refuse(dep, layer_id, reason):
        warnings.append(f"refused asset @{dep}@ named in {_short(layer_id)}: {reason}; it was not read")

    def visit(layer_id: str, depth: int = 0) -> str:
        if layer_id in memo or depth > 64:
            return memo.get(layer_id, layer_id)
        memo[layer_id] = layer_id
        if depth == 0:
            layer = _open_fresh(layer_id)  # the root: failing to read it is the caller's error
        else:
            try:
                layer = _open_fresh(layer_id)
            except Tf.ErrorException as e:  # an unreadable dependency: USD will warn when composing
                warnings.append(f"{_short(layer_id)} could not be read: {_usd_error_text(str(e))[:200]}")
                layer = None
        if layer is None:
            return layer_id
        anchor = f"{archive}[{first_entry}]" if archive and layer_id == archive else layer_id
        new_paths: dict[str, str] = {}
        for dep in layer.GetCompositionAssetDependencies():
            ok, reason = check_asset_path(dep, anchor, mode, asset_root, archive)
            if not ok:
                refuse(dep, layer_id, reason)
                new_paths[dep] = ""
                continue
            resolved = layer.ComputeAbsolutePath(dep)
            sub = visit(resolved, depth + 1)
            if sub != resolved:
                new_paths[dep] = sub
        bad_clips, clip_prims = _refused_clip_sets(layer, anchor, mode, asset_root, archive, refuse, layer_id)
        if not new_paths and not bad_clips:
            return layer_id
        copy = Sdf.Layer.CreateAnonymous(os.path.basename(layer_id) + ".sandboxed.usda")
        copy.TransferContent(layer)
        for dep in copy.GetCompositionAssetDependencies():
            copy.UpdateCompositionAssetDependency(dep, new_paths.get(dep, layer.ComputeAbsolutePath(dep)))
        for prim_path in clip_prims:  # drop refused clip sets; anchor the others to the original layer
            spec = copy.GetObjectAtPath(prim_path)
            clips = {}
            for name, clip in dict(spec.GetInfo("clips")).items():
                if (prim_path, name) in bad_clips:
                    continue
                clip = dict(clip)
                if clip.get("assetPaths"):
                    clip["assetPaths"] = Sdf.AssetPathArray(
                        [Sdf.AssetPath(layer.ComputeAbsolutePath(getattr(a, "path", str(a)))) for a in clip["assetPaths"]])
                if clip.get("manifestAssetPath"):
                    m = clip["manifestAssetPath"]
                    clip["manifestAssetPath"] = Sdf.AssetPath(layer.ComputeAbsolutePath(getattr(m, "path", str(m))))
                if clip.get("templateAssetPath"):
                    clip["templateAssetPath"] = layer.ComputeAbsolutePath(str(clip["templateAssetPath"]))
                clips[name] = clip
            if clips:
                spec.SetInfo("clips", clips)
            else:
                spec.ClearInfo("clips")
        keep.append(copy)
        memo[layer_id] = copy.identifier
        return copy.identifier

    return visit(root)


def _open_fresh(identifier: str):
    """Sdf.Layer.FindOrOpen, but a layer already in USD's registry (held by some other live stage)
    is reloaded first when its file changed on disk, so what is checked and composed is the file as
    it is now. Layers with unsaved in-memory edits are left alone."""
    from pxr import Sdf

    layer = Sdf.Layer.Find(identifier)
    if layer is not None and not layer.anonymous and not layer.dirty:
        layer.Reload()  # a no-op unless the file's modification time changed
        return layer
    return Sdf.Layer.FindOrOpen(identifier)


def _refused_clip_sets(layer, anchor, mode, asset_root, archive, refuse, layer_id):
    """(prim path, clip set name) of value-clip sets in `layer` naming an asset that may not be read,
    and the paths of every prim spec that has clips."""
    found, prims = set(), []

    def on_spec(path):
        if not path.IsPrimPath() and not path.IsPrimVariantSelectionPath():
            return
        spec = layer.GetObjectAtPath(path)
        if spec is None or not spec.HasInfo("clips"):
            return
        prims.append(path)
        for name, clip in dict(spec.GetInfo("clips")).items():
            clip = dict(clip) if clip else {}
            paths = [getattr(a, "path", str(a)) for a in (clip.get("assetPaths") or [])]
            if clip.get("manifestAssetPath"):
                paths.append(getattr(clip["manifestAssetPath"], "path", str(clip["manifestAssetPath"])))
            verdicts = [check_asset_path(a, anchor, mode, asset_root, archive) for a in paths]
            tmpl = clip.get("templateAssetPath")
            if tmpl:
                verdicts.append((False, f"clip template {tmpl!r} can name any file matching a pattern")
                                if mode == "sandbox" else
                                check_asset_path(posixpath.dirname(str(tmpl)) + "/x.usd", anchor, mode, asset_root, archive))
            bad = [(a, why) for a, (ok, why) in zip(paths + ([tmpl] if tmpl else []), verdicts) if not ok]
            if bad:
                for a, why in bad:
                    refuse(a, layer_id, f"value clip set {name!r} of {path}: {why}")
                found.add((path, name))

    layer.Traverse(layer.pseudoRoot.path, on_spec)
    return found, prims


def _short(identifier: str) -> str:
    return os.path.basename(identifier) if "[" not in identifier else identifier.rsplit("/", 1)[-1]


# ---------------------------------------------------------------- triangulation
def _newell_normal(pts: np.ndarray) -> np.ndarray:
    nxt = np.roll(pts, -1, axis=0)
    return np.array([np.sum((pts[:, 1] - nxt[:, 1]) * (pts[:, 2] + nxt[:, 2])),
                     np.sum((pts[:, 2] - nxt[:, 2]) * (pts[:, 0] + nxt[:, 0])),
                     np.sum((pts[:, 0] - nxt[:, 0]) * (pts[:, 1] + nxt[:, 1]))])


def _project_ccw(pts: np.ndarray) -> np.ndarray | None:
    """(n, 3) polygon -> (n, 2) in its best-fit plane, counter-clockwise; None when degenerate."""
    normal = _newell_normal(pts)
    nn = np.linalg.norm(normal)
    if not np.isfinite(nn) or nn < 1e-300:
        return None
    normal = normal / nn
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)  # (u, v, normal) right-handed: the polygon winds counter-clockwise in (u, v)
    c = pts - pts.mean(axis=0)
    return np.stack([c @ u, c @ v], axis=1)


def ear_clip(pts: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangulate one simple polygon (n, 3) given in order, concave or not; returns local index triples.

    Ears are cut in the polygon's best-fit plane (Newell normal). A corner is an ear when it is convex
    and no other remaining reflex corner lies in its triangle. Self-intersecting leftovers are fanned.
    """
    n = len(pts)
    if n < 3:
        return []
    if n == 3:
        return [(0, 1, 2)]
    p2 = _project_ccw(np.asarray(pts, dtype=np.float64))
    if p2 is None:
        return [(0, i, i + 1) for i in range(1, n - 1)]  # degenerate: any fan has zero area
    scale = float(np.abs(p2).max()) or 1.0
    eps = 1e-12 * scale * scale
    idx = list(range(n))
    tris: list[tuple[int, int, int]] = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    k = 0
    stall = 0
    while len(idx) > 3 and stall <= len(idx):
        m = len(idx)
        k %= m
        i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
        a, b, c = p2[i0], p2[i1], p2[i2]
        is_ear = cross(a, b, c) > eps
        if is_ear:
            others = np.array([j for j in idx if j not in (i0, i1, i2)], dtype=np.int64)
            q = p2[others]
            # only points not coincident with the ear's corners can block it
            same = (np.all(np.isclose(q, a), axis=1) | np.all(np.isclose(q, b), axis=1)
                    | np.all(np.isclose(q, c), axis=1))
            q = q[~same]
            if len(q):
                d1 = (b[0] - a[0]) * (q[:, 1] - a[1]) - (b[1] - a[1]) * (q[:, 0] - a[0])
                d2 = (c[0] - b[0]) * (q[:, 1] - b[1]) - (c[1] - b[1]) * (q[:, 0] - b[0])
                d3 = (a[0] - c[0]) * (q[:, 1] - c[1]) - (a[1] - c[1]) * (q[:, 0] - c[0])
                is_ear = not np.any((d1 >= -eps) & (d2 >= -eps) & (d3 >= -eps))
        if is_ear:
            tris.append((i0, i1, i2))
            idx.pop(k)
            stall = 0
        else:
            k += 1
            stall += 1
    if len(idx) > 3:
        # No ear left (a self-intersecting or numerically flat remainder): fan it.
        tris += [(idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1)]
    elif len(idx) == 3:
        tris.append((idx[0], idx[1], idx[2]))
    return tris


def _convex_mask(P: np.ndarray) -> np.ndarray:
    """(F, n, 3) polygons -> (F,) True where the polygon is convex (a fan triangulates it exactly).

    Convex: every corner turns the same way about the face normal and the turns add up to one full
    turn (a pentagram turns the same way at every corner but twice around)."""
    nxt = np.roll(P, -1, axis=1)
    normal = np.stack([np.sum((P[..., 1] - nxt[..., 1]) * (P[..., 2] + nxt[..., 2]), axis=1),
                       np.sum((P[..., 2] - nxt[..., 2]) * (P[..., 0] + nxt[..., 0]), axis=1),
                       np.sum((P[..., 0] - nxt[..., 0]) * (P[..., 1] + nxt[..., 1]), axis=1)], axis=1)
    nlen = np.linalg.norm(normal, axis=1)
    normal = normal / np.where(nlen > 0, nlen, 1.0)[:, None]
    e = nxt - P  # edge i: corner i -> i+1
    e_prev = np.roll(e, 1, axis=1)
    sin = np.einsum("fnk,fk->fn", np.cross(e_prev, e), normal)
    cos = np.einsum("fnk,fnk->fn", e_prev, e)
    scale = np.linalg.norm(e_prev, axis=2) * np.linalg.norm(e, axis=2)
    left = sin >= -1e-9 * scale
    turn = np.arctan2(sin, cos).sum(axis=1)
    return (nlen > 0) & np.all(left, axis=1) & (np.abs(turn - 2 * np.pi) < 1e-3)


def triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygon soup -> (T, 3) vertex indices, in face order within each face size.

    Triangles and quads are vectorised; larger faces are grouped by size, checked for convexity in
    one vectorised pass and fanned, and only the concave ones are ear-clipped one by one."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
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
    for nv in np.unique(counts[counts > 4]):
        s = starts[counts == nv]
        poly = indices[s[:, None] + np.arange(nv)[None, :]]  # (F, nv)
        convex = _convex_mask(points[poly])
        if convex.any():
            pc = poly[convex]
            j = np.arange(1, nv - 1)
            fan = np.stack([np.repeat(pc[:, :1], nv - 2, axis=1), pc[:, j], pc[:, j + 1]], axis=2)
            out.append(fan.reshape(-1, 3))
        for pl in poly[~convex]:
            t = ear_clip(points[pl])
            if t:
                out.append(pl[np.array(t, dtype=np.int64)])
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


def implicit_mesh(prim, time_code, warnings: list[str] | None = None):
    """Tessellate a UsdGeom implicit prim in its local frame. Returns (points, triangles) or None."""
    from pxr import UsdGeom

    t = prim.GetTypeName()

    def get(name, default):
        a = prim.GetAttribute(name)
        v = _get(a, time_code, warnings) if a else None
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
    if t in ("Cylinder", "Cone", "Capsule", "Cylinder_1", "Capsule_1"):
        capsule = t.startswith("Capsule")
        r = float(get("radius", 1.0 if not capsule else 0.5))
        if t.endswith("_1"):  # the newer schemas: one radius per end
            rt, rb = float(get("radiusTop", r)), float(get("radiusBottom", r))
        else:
            rt = rb = r
        h = float(get("height", 2.0 if not capsule else 1.0))
        axis = str(get("axis", "Z"))
        if t.startswith("Cylinder"):
            prof = [(0.0, -h / 2), (rb, -h / 2), (rt, h / 2), (0.0, h / 2)]
        elif t == "Cone":
            prof = [(0.0, -h / 2), (r, -h / 2), (0.0, h / 2)]
        else:
            q = max(half // 2, 2)
            bottom = [(rb * math.sin(a), -h / 2 - rb * math.cos(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            top = [(rt * math.cos(a), h / 2 + rt * math.sin(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            bottom[0], top[-1] = (0.0, -h / 2 - rb), (0.0, h / 2 + rt)
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


def _get(attr, time_code, warnings: list[str] | None = None):
    """attr's value at time_code. At the default time, an attribute with time samples but no default
    value gives its first sample (USD would give nothing), so animated points are not lost."""
    v = attr.Get(time_code)
    if v is None and time_code.IsDefault() and attr.GetNumTimeSamples() > 0:
        samples = attr.GetTimeSamples()
        v = attr.Get(samples[0])
        if warnings is not None:
            warnings.append(f"{attr.GetPath()}: only time samples, no default value: read at its first sample "
                            f"t={samples[0]:g}")
    return v


def _as_array(value, cols: int | None, dtype):
    """A USD array value -> NumPy of shape (N, cols) / (N,), or None when it has another shape or type."""
    if value is None or isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        return None
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        return None
    if cols is None:
        return arr if arr.ndim == 1 else None
    if arr.ndim == 2 and arr.shape[1] == cols:
        return arr
    if arr.size == 0:
        return arr.reshape(0, cols)
    return None


def _mesh_triangles(prim, time_code, warnings):
    from pxr import UsdGeom

    path = str(prim.GetPath())
    mesh = UsdGeom.Mesh(prim)
    raw_pts = _get(mesh.GetPointsAttr(), time_code, warnings)
    raw_counts = _get(mesh.GetFaceVertexCountsAttr(), time_code, warnings)
    raw_idx = _get(mesh.GetFaceVertexIndicesAttr(), time_code, warnings)
    if raw_pts is None or raw_counts is None or raw_idx is None:
        missing = [n for n, v in (("points", raw_pts), ("faceVertexCounts", raw_counts),
                                  ("faceVertexIndices", raw_idx)) if v is None]
        warnings.append(f"{path}: skipped, no {', '.join(missing)}")
        return None
    pts = _as_array(raw_pts, 3, np.float64)
    counts = _as_array(raw_counts, None, np.int64)
    idx = _as_array(raw_idx, None, np.int64)
    if pts is None:
        warnings.append(f"{path}: skipped, its points are not an array of 3-vectors "
                        f"(got a {type(raw_pts).__name__})")
        return None
    if counts is None or idx is None:
        warnings.append(f"{path}: skipped, faceVertexCounts/faceVertexIndices are not integer arrays")
        return None
    if len(pts) == 0 or len(counts) == 0:
        warnings.append(f"{path}: skipped, the mesh is empty")
        return None
    if not np.all(np.isfinite(pts)):
        warnings.append(f"{path}: skipped, its points contain NaN or infinite values")
        return None
    if np.any(counts < 0) or counts.sum() != len(idx):
        warnings.append(f"{path}: skipped, faceVertexCounts sum to {int(counts.sum())} but there are "
                        f"{len(idx)} faceVertexIndices")
        return None
    if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
        warnings.append(f"{path}: skipped, faceVertexIndices range over [{int(idx.min())}, {int(idx.max())}] "
                        f"but there are {len(pts)} points")
        return None
    small = counts < 3
    if small.any():
        warnings.append(f"{path}: {int(small.sum())} faces with fewer than 3 vertices dropped")
        keep = np.repeat(~small, counts)
        idx, counts = idx[keep], counts[~small]
        if len(counts) == 0:
            return None
    tris = triangulate(pts, counts, idx)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tris = tris[:, ::-1]  # keep every triangle counter-clockwise about its outward normal
    return pts, tris


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
                names = usdz_entries(path)
                bad = [n for n in names if is_unsafe_entry_name(n)]
                if names and names[0] in bad:
                    raise SceneError("unsafe_archive", f"{path}: the archive's root layer has an unsafe entry name "
                                     f"{names[0]!r} (absolute or climbing out with '..'); refused")
                if bad:
                    warnings.append(f"usdz entries with unsafe names refused and not read: {', '.join(bad[:5])}")
            root = os.path.abspath(path)
            if sandbox or asset_root is not None:
                root = _rewrite_dependencies(root, mode, asset_root, warnings, keep)
            layer = _open_fresh(root)
            if layer is None:
                raise SceneError("corrupt", f"{path}: USD could not read the file (truncated or damaged)")
            stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
            if stage is None:
                raise SceneError("corrupt", f"{path}: USD could not open the stage")
            if not (sandbox or asset_root is not None):
                # Unrestricted mode: layers other stages still hold may be older than their files.
                for used in stage.GetUsedLayers():
                    if not used.anonymous and not used.dirty:
                        used.Reload()
            scene = _extract(stage, path, time_code, warnings)
    except SceneError:
        raise
    except Tf.ErrorException as e:
        msg = _usd_error_text(str(e))
        raise SceneError("corrupt", f"{path}: USD could not read the file: {msg[:300]}") from e
    except (RuntimeError, ValueError, OSError, zipfile.BadZipFile) as e:
        raise SceneError("corrupt", f"{path}: {type(e).__name__}: {str(e)[:300]}") from e
    except MemoryError as e:
        raise SceneError("too_large", f"{path}: the scene does not fit in memory") from e
    except Exception as e:  # never let anything else escape: the caller handles SceneError only
        raise SceneError("internal", f"{path}: the loader failed ({type(e).__name__}: {str(e)[:300]})") from e
    all_warnings = _dedupe(warnings + diag)
    scene.warnings = all_warnings[:MAX_WARNINGS]
    if len(all_warnings) > MAX_WARNINGS:
        scene.warnings.append(f"... and {len(all_warnings) - MAX_WARNINGS} more warnings")
    try:
        scene.scene_hash = _scene_hash(stage, path)
    except OSError as e:
        raise SceneError("not_found", f"{path}: a layer could not be read for hashing ({e})") from e
    scene.load_s = time.perf_counter() - t_start
    del keep
    return scene


def _dedupe(items: list[str]) -> list[str]:
    seen, out = set(), []
    for w in items:
        if w not in seen:
            seen.add(w)
            out.append(w)
    return out


def _usd_error_text(text: str) -> str:
    """The useful part of a Tf error: drop the C++ location and namespaces."""
    text = text.strip().strip("'")
    m = re.search(r" : '(.*)'?$", text, re.S)
    if m:
        text = m.group(1)
    text = re.sub(r"pxrInternal_v\w+::", "", text).strip().strip("'")
    return text or "unreadable"


def _scene_hash(stage, path) -> str:
    """sha256 of the root file's bytes, then of every file-backed layer the stage composed, sorted by
    identifier (each as its name inside the scene folder and its own digest). Anonymous layers (the
    session layer, sandboxed copies) are derived from those files and left out, so the hash does not
    depend on memory addresses."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read())
    base = os.path.dirname(os.path.abspath(path))
    for layer in sorted(stage.GetUsedLayers(), key=lambda l: l.identifier):
        if layer.anonymous:
            continue
        ident = layer.identifier
        real = layer.realPath
        rel = os.path.relpath(real, base) if real and os.path.isabs(real) else ident.rsplit("/", 1)[-1]
        h.update(b"\0" + rel.encode("utf-8", "replace") + b"\0")
        if real and os.path.isfile(real):
            with open(real, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
        else:  # a layer inside a .usdz (its bytes are in the root file) or one USD made in memory
            h.update(hashlib.sha256(layer.ExportToString().encode()).digest())
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
    # USD does not rescale layers authored in other units: say so when a composed layer differs.
    for other in stage.GetUsedLayers():
        if other == layer or other.anonymous:
            continue
        try:
            info = other.pseudoRoot.GetInfo("metersPerUnit") if other.pseudoRoot.HasInfo("metersPerUnit") else None
        except Exception:  # noqa: BLE001 - metadata we cannot read is not worth failing for
            info = None
        if info is not None and not math.isclose(float(info), mpu, rel_tol=1e-9):
            warnings.append(f"layer {_short(other.identifier)} is authored with metersPerUnit {float(info):g} but "
                            f"the stage uses {mpu:g}; USD does not rescale it, so it is read in the stage's units")
    return up, mpu


def _extract(stage, path, time_code, warnings) -> LoadedScene:
    from pxr import Usd, UsdGeom, UsdLux

    tc = Usd.TimeCode.Default() if time_code is None else Usd.TimeCode(time_code)
    up, mpu = _stage_frame(stage, warnings)
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

    def geometry_of(prim):
        if not prim.IsA(UsdGeom.Gprim) or not renderable_purpose(prim):
            return None
        if prim.IsA(UsdGeom.Mesh):
            return _mesh_triangles(prim, tc, warnings)
        else:
            r = implicit_mesh(prim, tc, warnings)
            if r is None and not prim.IsA(UsdGeom.Curves) and not prim.IsA(UsdGeom.Points):
                warnings.append(f"{prim.GetPath()}: {prim.GetTypeName()} is not supported, skipped")
            return r
        return None

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
        if skip_subtree(prim):
            it.PruneChildren()
            continue
        if prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            if renderable_purpose(prim):
                _expand_instancer(prim, tc, xcache, add, geometry_of, skip_subtree, warnings)
            continue
        if prim.IsA(UsdGeom.Camera):
            cameras.append(_camera(prim, tc, xcache, s2w, mpu, warnings))
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


class _DefaultTimeXforms:
    """UsdGeom.XformCache at the default time, except that a prim whose transform ops have time
    samples but no default value is read at its first sample (as points are), not as identity."""

    def __init__(self, warnings: list[str]):
        from pxr import Gf, UsdGeom

        self._cache = UsdGeom.XformCache()
        self._memo: dict = {}
        self._warnings = warnings
        self._identity = Gf.Matrix4d(1.0)

    def _local(self, prim):
        from pxr import Usd, UsdGeom

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


def _expand_instancer(prim, tc, xcache, add, geometry_of, skip_subtree, warnings):
    """Every visible instance of a PointInstancer: prototype geometry placed by the instance
    transforms (which include each prototype root's own transform); invisibleIds/inactiveIds masked."""
    from pxr import Usd, UsdGeom

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
    xforms = inst.ComputeInstanceTransformsAtTime(t, t, UsdGeom.PointInstancer.IncludeProtoXform,
                                                  UsdGeom.PointInstancer.IgnoreMask)
    indices = _as_array(inst.GetProtoIndicesAttr().Get(t), None, np.int64)
    if xforms is None or indices is None or len(xforms) != len(indices):
        if indices is not None and len(indices):
            warnings.append(f"{ipath}: instance transforms could not be computed (mismatched array sizes?); skipped")
        return
    mask = inst.ComputeMaskAtTime(t)
    visible = np.ones(len(indices), bool) if not mask else np.asarray(mask, bool)
    if len(visible) != len(indices):
        visible = np.ones(len(indices), bool)
    inst_world = _np_matrix(xcache.GetLocalToWorldTransform(prim))
    stage = prim.GetStage()
    proto_geo = []
    for target in protos:
        root = stage.GetPrimAtPath(target)
        parts = []
        if root and not skip_subtree(root):
            # relative to the prototype root: its own transform comes with the instance transforms
            root_inv = np.linalg.inv(_np_matrix(xcache.GetLocalToWorldTransform(root)))
            rng = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
            for p in rng:
                if skip_subtree(p):
                    rng.PruneChildren()
                    continue
                g = geometry_of(p)
                if g is not None:
                    rel = root_inv @ _np_matrix(xcache.GetLocalToWorldTransform(p))
                    parts.append((g, rel, str(p.GetPath())))
        elif not root:
            warnings.append(f"{ipath}: prototype {target} does not exist")
        proto_geo.append(parts)
    bad = 0
    for k, (pi, xf) in enumerate(zip(indices, xforms)):
        if not visible[k]:
            continue
        if pi < 0 or pi >= len(proto_geo):
            bad += 1
            continue
        m = inst_world @ _np_matrix(xf)
        for (pts, tris), rel, ppath in proto_geo[pi]:
            sub = ppath[len(ipath):] if ppath.startswith(ipath) else ppath
            add(pts, tris, m @ rel, f"{ipath}[{k}]{sub}")
    if bad:
        warnings.append(f"{ipath}: {bad} instances name prototypes that do not exist; skipped")


def _camera(prim, tc, xcache, s2w, mpu, warnings) -> UsdCamera:
    """Position and axes from the camera's transform (it looks along local -Z, up is local +Y);
    clipping range from stage units to meters; fov from the vertical aperture and focal length."""
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    focal = float(_get(cam.GetFocalLengthAttr(), tc) or 50.0)
    hap = float(_get(cam.GetHorizontalApertureAttr(), tc) or 20.955)
    vap = float(_get(cam.GetVerticalApertureAttr(), tc) or 15.2908)
    clip = _get(cam.GetClippingRangeAttr(), tc) or (1.0, 1e6)
    m = s2w @ _np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    fwd = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    up = transform_directions(m, np.array([0.0, 1.0, 0.0]))
    if focal <= 0 or vap <= 0:
        warnings.append(f"{prim.GetPath()}: focalLength {focal:g} / verticalAperture {vap:g} are not positive; "
                        "USD's fallbacks 50 / 15.2908 used")
        focal, vap = 50.0, 15.2908
    fov = math.degrees(2.0 * math.atan(vap / (2.0 * focal)))
    return UsdCamera(str(prim.GetPath()), pos, fwd, up, fov, float(clip[0]) * mpu, float(clip[1]) * mpu,
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
