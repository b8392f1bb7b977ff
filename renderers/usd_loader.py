"""USD stage -> LoadedScene: every renderable triangle merged into one mesh in the world frame,
plus cameras and lights with their USD paths.

- Composition (sublayers, references, payloads) as USD does it, in the unrestricted local mode.
- Restricted modes (`sandbox`, or `asset_root` given) fail closed: renderers.usd_sandbox walks and checks the
  layer graph before USD may open any layer, under the limits SANDBOX_MAX_*.
- Messages and warnings name files as the scene knows them (the file's base name, a usdz entry, a
  path relative to the scene's folder), never by a server path: every message leaving load_scene goes
  once through renderers.redaction.PathRedactor (the scene's folder and the asset root dropped, the
  Python installation, the repository, the working, temporary and home folders and any absolute path
  ending in a file name cut to base names).
Malformed input raises SceneError with a machine-readable code (not_found, not_usd, corrupt,
unsafe_archive, empty_stage, bad_option, too_large, too_many_triangles, too_many_prims, sandbox_limit, sandbox_unchecked
(the last checks before and after USD opens the stage found a layer the walk did not check), internal);
nothing else escapes.

The parts, each in its module of renderers/:
  usd_sandbox         the restricted modes' layer walk and limits, before Usd.Stage.Open
  usd_diagnostics     usd-core's stderr diagnostics as warnings; Tf errors' texts
  usd_traversal       the stage's traversal: gprims, point instancers, cameras, lights; the triangle/prim budget
  usd_meshes          Mesh prims -> triangles, triangulated by triangulation
  triangulation       polygon soups -> triangles (vectorised; earcut for concave faces)
  implicit_prims      Cube, Sphere, Cylinder, Cone, Capsule, Plane tessellated
  usd_values          attribute values (first time sample at the default time), arrays and matrices as NumPy
  stage_units         the stage's upAxis and metersPerUnit
  usd_cameras_lights  UsdCamera and UsdLight from their prims
  usd_animation       read_animation: cameras and lights at time codes, what moves (no geometry)
"""
from __future__ import annotations

import hashlib
import os
import time
import zipfile

from pxr import Tf, Usd

from .asset_resolver import USD_LAYER_EXTENSIONS, is_unsafe_entry_name, split_package_path, usdz_entries
from .redaction import PathRedactor
from .scene_data import LoadedScene, SceneError
from .usd_diagnostics import captured_stderr, dedupe, tf_text, usd_error_text
from .usd_sandbox import SANDBOX_MAX_PRIMS, LayerWalk, count_composed_prims, open_fresh
from .usd_traversal import Budget, extract

MAX_WARNINGS = 50


def _check_file(path: str) -> None:
    name = os.path.basename(path) or path
    if not os.path.exists(path):
        raise SceneError("not_found", f"{name}: no such file")
    if os.path.isdir(path):
        raise SceneError("not_usd", f"{name}: is a folder, not a USD file")
    ext = os.path.splitext(path)[1].lower()
    if ext not in USD_LAYER_EXTENSIONS:
        raise SceneError("not_usd", f"{name}: not a USD file (extension {ext or 'none'}; expected .usd, .usda, .usdc or .usdz)")
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as e:
        raise SceneError("not_found", f"{name}: cannot read ({e.strerror})") from e
    if not head:
        raise SceneError("not_usd", f"{name}: the file is empty")
    kind = "usda" if head.startswith(b"#usda") else "usdc" if head.startswith(b"PXR-USDC") else \
        "usdz" if head.startswith(b"PK\x03\x04") else None
    expected = {".usda": ("usda",), ".usdc": ("usdc",), ".usdz": ("usdz",), ".usd": ("usda", "usdc")}[ext]
    if kind not in expected:
        raise SceneError("not_usd", f"{name}: not a {ext} file (it does not start with a USD header)")
    if kind == "usdz" and not zipfile.is_zipfile(path):
        raise SceneError("corrupt", f"{name}: the usdz archive is damaged")
    if kind == "usdz":
        try:
            entries = usdz_entries(path)
        except (OSError, zipfile.BadZipFile, ValueError) as e:
            raise SceneError("corrupt", f"{name}: the usdz archive is damaged ({type(e).__name__})") from e
        if not entries:
            raise SceneError("empty_stage", f"{name}: the usdz archive has no entries")


def _scene_name(identifier: str, scene_dir: str) -> str:
    """How a message names a layer: relative to the scene's folder when inside it (a usdz entry as
    'archive.usdz[entry]'), else by its base name; anonymous layers by their tag."""
    if identifier.startswith("anon:"):
        return identifier.rsplit(":", 1)[-1]
    pkg, inner = split_package_path(identifier)
    rel = os.path.relpath(pkg, scene_dir) if os.path.isabs(pkg) else pkg
    name = rel if not rel.startswith("..") else os.path.basename(pkg)
    return f"{name}[{inner}]" if inner is not None else name


def load_scene(path, *, time_code: float | None = None, asset_root: str | None = None,
               sandbox: bool = False, max_triangles: int | None = None, max_prims: int | None = None) -> LoadedScene:
    """Open a USD file and return its triangles, cameras and lights in the world frame.

    Restricted (sandbox, or asset_root given): the layer graph is checked before USD opens anything
    and the limits SANDBOX_MAX_* apply. max_triangles: refuse (too_many_triangles) as soon as the
    running count passes it, before the prim that passes it is tessellated. max_prims: refuse
    (too_many_prims) as soon as the traversal has visited more composed prims (restricted modes:
    SANDBOX_MAX_PRIMS when not given; unrestricted: no limit unless given)."""
    t_start = time.perf_counter()
    path = os.fspath(path)
    scrub = PathRedactor([os.path.dirname(os.path.abspath(path)), asset_root]).text
    try:
        scene = load_stage(path, time_code, asset_root, sandbox, max_triangles, max_prims)
    except SceneError as e:
        raise SceneError(e.code, scrub(e.message)) from e.__cause__
    scene.warnings = [scrub(w) for w in scene.warnings]
    scene.load_s = time.perf_counter() - t_start
    return scene


def load_stage(path, time_code, asset_root, sandbox, max_triangles, max_prims=None, read=None) -> LoadedScene:
    """The stage opened with the mode's checks, then extract; or `read(stage, warnings)`'s value instead
    (read_animation: the same opening, checks and error handling, no geometry)."""
    name = os.path.basename(path) or path
    _check_file(path)
    warnings: list[str] = []
    diag: list[str] = []
    walk = None
    mode = "sandbox" if sandbox else "local"
    restricted = sandbox or asset_root is not None
    if asset_root is not None and not sandbox and not os.path.isdir(asset_root):
        raise SceneError("bad_option", f"asset root {os.path.basename(os.path.normpath(asset_root))!r} is not a folder")
    if max_triangles is not None and (isinstance(max_triangles, bool) or not isinstance(max_triangles, int)
                                      or max_triangles < 0):
        raise SceneError("bad_option", f"max_triangles must be a non-negative integer, got {max_triangles!r}")
    if max_prims is not None and (isinstance(max_prims, bool) or not isinstance(max_prims, int) or max_prims < 0):
        raise SceneError("bad_option", f"max_prims must be a non-negative integer, got {max_prims!r}")
    if max_prims is None and restricted:
        max_prims = SANDBOX_MAX_PRIMS
    scene_dir = os.path.dirname(os.path.abspath(path))

    def layer_name(identifier: str) -> str:
        return _scene_name(identifier, scene_dir)

    try:
        with captured_stderr(diag):
            if path.lower().endswith(".usdz") and sandbox:
                names = usdz_entries(path)
                bad = [n for n in names if is_unsafe_entry_name(n)]
                if names and names[0] in bad:
                    raise SceneError("unsafe_archive", f"{name}: the archive's root layer has an unsafe entry name "
                                     f"{names[0]!r} (absolute or climbing out with '..'); refused")
                if bad:
                    warnings.append(f"usdz entries with unsafe names refused and not read: {', '.join(bad[:5])}")
            root = os.path.abspath(path)
            if restricted:
                walk = LayerWalk(root, mode, asset_root, warnings, layer_name)
                if walk.root is None:
                    raise SceneError("corrupt", f"{name}: USD could not read the file (truncated or damaged)")
                walk.verify_graph()
                root = walk.root
            layer = (walk.copies.get(root) or walk.originals.get(root)) if walk else open_fresh(root)
            if layer is None:
                raise SceneError("corrupt", f"{name}: USD could not read the file (truncated or damaged)")
            if walk is not None and max_prims is not None:
                count_composed_prims(layer, max_prims)  # references multiply specs: bound before composing
            stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
            if stage is None:
                raise SceneError("corrupt", f"{name}: USD could not open the stage")
            if walk is not None:
                walk.verify_stage(stage)
            else:
                # Unrestricted mode: layers other stages still hold may be older than their files.
                for used in stage.GetUsedLayers():
                    if not used.anonymous and not used.dirty:
                        used.Reload()

            def shown(layer_):
                if walk is not None:
                    return walk.display(layer_) if (not layer_.anonymous or layer_.identifier in walk.copies) else None
                return None if layer_.anonymous else layer_name(layer_.identifier)

            if read is not None:
                return read(stage, warnings)
            scene = extract(stage, path, time_code, warnings, Budget(max_triangles, max_prims), name, shown)
    except SceneError:
        raise
    except Tf.ErrorException as e:
        msg = usd_error_text(tf_text(e))
        raise SceneError("corrupt", f"{name}: USD could not read the file: {msg[:300]}") from e
    except RecursionError as e:
        raise SceneError("too_large", f"{name}: the scene nests too deeply to be read") from e
    except (RuntimeError, ValueError, OSError, zipfile.BadZipFile) as e:
        raise SceneError("corrupt", f"{name}: {type(e).__name__}: {str(e)[:300]}") from e
    except MemoryError as e:
        raise SceneError("too_large", f"{name}: the scene does not fit in memory") from e
    except Exception as e:  # never let anything else escape: the caller handles SceneError only
        raise SceneError("internal", f"{name}: the loader failed ({type(e).__name__}: {str(e)[:300]})") from e
    all_warnings = dedupe(warnings + diag)
    scene.warnings = all_warnings[:MAX_WARNINGS]
    if len(all_warnings) > MAX_WARNINGS:
        scene.warnings.append(f"... and {len(all_warnings) - MAX_WARNINGS} more warnings")
    try:
        scene.scene_hash = _scene_hash(stage, path, walk.file_layers() if walk is not None else None)
    except OSError as e:
        raise SceneError("not_found", f"{name}: a layer could not be read for hashing ({e.strerror})") from e
    del walk
    return scene


def _hash_file(h, path):
    """`h` updated with the file's bytes, read 1 MiB at a time (the same digest as one read of the whole)."""
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h


def _scene_hash(stage, path, layers=None) -> str:
    """sha256 of the root file's bytes, then of every file-backed layer the stage composed, sorted by
    identifier (each as its name inside the scene folder and its own digest). Anonymous layers (the
    session layer, sandboxed copies) are derived from those files and left out, so the hash does not
    depend on memory addresses; in the restricted modes `layers` are the checked originals."""
    h = hashlib.sha256()
    _hash_file(h, path)  # in chunks: a package may be hundreds of MB
    base = os.path.dirname(os.path.abspath(path))
    for layer in sorted(stage.GetUsedLayers() if layers is None else layers, key=lambda l: l.identifier):
        if layer.anonymous:
            continue
        ident = layer.identifier
        real = layer.realPath
        rel = os.path.relpath(real, base) if real and os.path.isabs(real) else ident.rsplit("/", 1)[-1]
        h.update(b"\0" + rel.encode("utf-8", "replace") + b"\0")
        if real and os.path.isfile(real):
            h.update(_hash_file(hashlib.sha256(), real).digest())
        else:  # a layer inside a .usdz (its bytes are in the root file) or one USD made in memory
            h.update(hashlib.sha256(layer.ExportToString().encode()).digest())
    return h.hexdigest()
