"""USD stage -> LoadedScene: every renderable triangle merged into one mesh in the world frame,
plus cameras and lights with their USD paths.

- Composition (sublayers, references, payloads) as USD does it, in the unrestricted local mode.
- Restricted modes (`sandbox`, or `asset_root` given) fail closed: before USD may open any layer, the
  loader walks the layer graph itself (sublayers, references and payloads, inside variants too, and
  value clips), checks every asset path with renderers.asset_resolver, opens only the layers it
  accepted, and hands USD anonymous copies whose every asset path is the exact, absolute identifier
  of a layer it checked (refused ones removed). Internal references (`</Proto>`) are legal and left
  alone. Before Usd.Stage.Open the rewritten graph is verified to name nothing unchecked, and after
  it the stage's layers are verified to be the checked ones. Reaching a limit refuses the whole
  load with SceneError("sandbox_limit", "<which limit>: ...; refused"):
    SANDBOX_MAX_DEPTH = 32          layers nested below the root (sublayer/reference/payload arcs);
    SANDBOX_MAX_LAYERS = 256        distinct layers (value-clip layers included);
    SANDBOX_MAX_LAYER_BYTES = 512 MiB  the layers' sizes added up (file size, or the usdz entry's
                                    size), each counted before it is opened.
    SANDBOX_MAX_PRIM_SPECS = 50,000 prim specs over all layers (variants included): a text layer's
                                    def/over/class keywords bound it before Sdf parses the layer, the
                                    parsed count replaces the bound; refused before Usd.Stage.Open;
    SANDBOX_MAX_CRATE_SPECS = 250,000  all specs of one binary layer (its table of contents), before reading it;
    SANDBOX_MAX_PRIMS = 50,000      composed prims (max_prims' restricted default; references and
                                    instancing multiply specs): counted with Pcp before Usd.Stage.Open
                                    (_count_composed_prims) and again by the traversal.
  The prim limits answer SceneError("too_many_prims"). 300,000 empty Xforms (6.8 MB) took 20-24 s to
  load (parse 2.1 s, walk 5.3 s, Usd.Stage.Open 3.7 s, traversal 10.9 s); now refused in 0.6 s.
  Real assets stay far below them (largest composed: the Intent teapot scene, 7,370 prims, 1,766 specs) (the OpenChessSet: 29 layers, 3 deep, 8.3 MiB; the Intent VFX
  teapot scene: 11 layers, 6 deep). Fail-closed choices: dependencies other than USD layers (.mtlx,
  whose includes MaterialX follows itself), file format arguments, packages nested in packages and
  value-clip templates (their files are only known once USD expands the pattern) are refused.
- Budget: `max_triangles` is charged prim by prim during the traversal, before anything is
  tessellated, triangulated or copied: meshes by faceVertexCounts (a face of n corners is n - 2
  triangles), implicit prims by their fixed tessellation counts, point instancers as visible
  instances x prototype triangles; SceneError("too_many_triangles") as soon as the count exceeds it.
- Traversal includes instance proxies (instanceable prims) and expands PointInstancers (masked ids
  skipped); invisible prims are skipped with their subtrees; gprims are drawn when their computed
  purpose is default or render.
- Meshes are triangulated as authored (subdivision meshes as their cage): triangles and quads
  vectorised, larger faces fanned when a vectorised check finds them convex, the others projected on
  their Newell plane and triangulated by earcut (mapbox-earcut, C++); a face of more than 256
  corners is first cut along checked diagonals into pieces (earcut is quadratic on star-like faces).
- Implicit prims (Cube, Sphere, Cylinder, Cone, Capsule, Plane, and the *_1 variants) are tessellated.
- Units: the stage's upAxis and metersPerUnit (USD's fallbacks: Y and 0.01) -> solvers.frames world.
- At the default time code, attributes with time samples but no default are read at their first sample.
- usd-core's diagnostics (missing files, MaterialX it cannot read) become scene warnings.
- Messages and warnings name files as the scene knows them (the file's base name, a usdz entry, a
  path relative to the scene's folder), never by a server path: every message leaving load_scene goes
  once through renderers.redaction.PathRedactor (the scene's folder and the asset root dropped, the
  Python installation, the repository, the working, temporary and home folders and any absolute path
  ending in a file name cut to base names).
Malformed input raises SceneError with a machine-readable code (not_found, not_usd, corrupt,
unsafe_archive, empty_stage, bad_option, too_large, too_many_triangles, too_many_prims, sandbox_limit, sandbox_unchecked
(the last checks before and after USD opens the stage found a layer the walk did not check), internal);
nothing else escapes.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
import tempfile
import threading
import time
import zipfile

import numpy as np

from ..solvers.frames import stage_to_world as _stage_to_world
from ..solvers.frames import transform_directions, transform_points
from .asset_resolver import (USD_LAYER_EXTENSIONS, is_unsafe_entry_name, resolve_asset_path, split_package_path,
                             usdz_entries)
from .redaction import PathRedactor
from .scene_data import LoadedScene, SceneError, SceneGeometry, UsdCamera, UsdLight

SEGMENTS = 32  # tessellation of implicit round prims (around), half of it along
MAX_WARNINGS = 50
SANDBOX_MAX_DEPTH = 32
SANDBOX_MAX_LAYERS = 256
SANDBOX_MAX_LAYER_BYTES = 512 * 1024 * 1024
SANDBOX_MAX_PRIM_SPECS = 50_000  # prim specs over all layers (variants included), counted before composing
SANDBOX_MAX_CRATE_SPECS = 250_000  # all specs of one binary (.usdc) layer, read from its table of contents
SANDBOX_MAX_PRIMS = 50_000  # composed prims the traversal may visit (restricted modes' default max_prims)


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
        line = re.sub(r"anon:0x[0-9a-f]+:([^@\s]*?)\.checked\.usda", r"\1", line)
        if line not in out:
            out.append(line)
    return out


# ---------------------------------------------------------------- pre-checks
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


# ---------------------------------------------------------------- asset resolution
def _limit(which: str, detail: str) -> SceneError:
    return SceneError("sandbox_limit", f"{which}: {detail}; refused")


class _LayerWalk:
    """The restricted modes' layer graph, walked before USD opens anything (fail closed).

    Every layer is reached through an asset path accepted by asset_resolver.resolve_asset_path, is
    counted against the limits (depth, number of layers, total bytes) BEFORE it is opened, and is
    opened alone with Sdf (which reads no dependency). A layer naming dependencies or value clips is
    replaced by an anonymous copy in which each asset path is the identifier of the checked layer (or
    removed), so USD resolves nothing by itself: no search path, no unvisited depth."""

    def __init__(self, root: str, mode: str, asset_root: str | None, warnings: list[str], name):
        self.mode, self.asset_root, self.warnings, self.name = mode, asset_root, warnings, name
        self.archive = root if root.lower().endswith(".usdz") else None
        self.memo: dict[str, str | None] = {}  # checked identifier -> identifier to compose (None: unreadable)
        self.originals: dict[str, object] = {}  # checked identifier -> its Sdf.Layer (kept alive)
        self.copies: dict[str, object] = {}  # anonymous identifier -> the copy
        self.origin: dict[str, str] = {}  # anonymous identifier -> the checked identifier it copies
        self.total_bytes = 0
        self.prim_specs = 0  # an upper bound before a layer is parsed, its exact prim spec count after
        self.bounds: dict[str, int] = {}  # identifier -> the bound charged before parsing it
        self._zips: dict[str, dict[str, int]] = {}
        self.root = self.visit(os.path.normpath(root), 0)

    # --- bookkeeping
    def entries(self, package: str) -> dict[str, int]:
        if package not in self._zips:
            try:
                with zipfile.ZipFile(package) as z:
                    self._zips[package] = {i.filename: i.file_size for i in z.infolist()}
            except (OSError, zipfile.BadZipFile):
                self._zips[package] = {}
        return self._zips[package]

    def anchor(self, identifier: str) -> str:
        """The identifier relative asset paths in this layer are anchored to (a whole .usdz: its first entry)."""
        pkg, inner = split_package_path(identifier)
        if inner is None and identifier.lower().endswith(".usdz"):
            names = list(self.entries(identifier))
            return f"{identifier}[{names[0]}]" if names else identifier
        return identifier

    def size(self, identifier: str) -> int:
        pkg, inner = split_package_path(identifier)
        if inner is not None:
            return self.entries(pkg).get(inner, 0)
        if identifier.lower().endswith(".usdz"):
            sizes = list(self.entries(identifier).values())
            return sizes[0] if sizes else 0
        try:
            return os.stat(identifier).st_size
        except OSError:
            return 0

    def charge(self, identifier: str, depth: int) -> None:
        """Count one more layer, before it is opened; raise when a limit is reached."""
        if depth > SANDBOX_MAX_DEPTH:
            raise _limit(f"layer depth limit {SANDBOX_MAX_DEPTH}",
                         f"{self.name(identifier)} is nested {depth} layers deep (sublayers, references and "
                         f"payloads may nest at most {SANDBOX_MAX_DEPTH} deep below the scene's root layer)")
        n = len(self.memo) + 1
        if n > SANDBOX_MAX_LAYERS:
            raise _limit(f"layer count limit {SANDBOX_MAX_LAYERS}",
                         f"the scene names more than {SANDBOX_MAX_LAYERS} layers (reached at {self.name(identifier)})")
        size = self.size(identifier)
        if self.total_bytes + size > SANDBOX_MAX_LAYER_BYTES:
            raise _limit(f"layer bytes limit {SANDBOX_MAX_LAYER_BYTES} ({SANDBOX_MAX_LAYER_BYTES // 2**20} MiB)",
                         f"the scene's layers add up to more than {SANDBOX_MAX_LAYER_BYTES} bytes "
                         f"(reached at {self.name(identifier)}, {size} bytes)")
        self.total_bytes += size
        self.bounds[identifier] = _spec_bound(identifier, self.entries)  # before Sdf parses it
        self.prim_specs += self.bounds[identifier]
        self.check_prim_specs(identifier)

    def check_prim_specs(self, identifier: str) -> None:
        if self.prim_specs > SANDBOX_MAX_PRIM_SPECS:
            raise SceneError("too_many_prims", f"prim spec limit {SANDBOX_MAX_PRIM_SPECS}: the scene's layers define more "
                             f"than {SANDBOX_MAX_PRIM_SPECS} prims (reached at {self.name(identifier)}); refused "
                             "before composing")

    def refuse(self, dep: str, identifier: str, reason: str) -> None:
        self.warnings.append(f"refused asset @{dep}@ named in {self.name(identifier)}: {reason}; it was not read")

    # --- the walk
    def visit(self, identifier: str, depth: int) -> str | None:
        from pxr import Sdf, Tf

        if identifier in self.memo:
            return self.memo[identifier]
        self.charge(identifier, depth)
        self.memo[identifier] = None
        if depth == 0:
            layer = _open_fresh(identifier)  # the root: failing to read it is the caller's error
            if layer is None:
                return None
        else:
            try:
                layer = _open_fresh(identifier)
            except Tf.ErrorException as e:
                layer = None
                why = _usd_error_text(_tf_text(e))[:200]
            else:
                pkg, inner = split_package_path(identifier)
                why = "no such file" if not os.path.exists(pkg) else \
                    "no such entry" if inner is not None and inner not in self.entries(pkg) else "USD could not open it"
            if layer is None:
                self.warnings.append(f"{self.name(identifier)} could not be read ({why}); it was not composed")
                return None
        self.originals[identifier] = layer
        anchor = self.anchor(identifier)
        deps = [d for d in layer.GetCompositionAssetDependencies() if d]  # '': internal references, legal
        clip_prims, n_prims = _scan_layer(layer)
        self.prim_specs += n_prims - self.bounds.pop(identifier, 0)  # the exact count replaces the bound
        self.check_prim_specs(identifier)
        if not deps and not clip_prims:
            self.memo[identifier] = identifier
            return identifier
        copy = Sdf.Layer.CreateAnonymous(os.path.basename(split_package_path(identifier)[1] or identifier)
                                         + ".checked.usda")
        copy.TransferContent(layer)
        self.memo[identifier] = copy.identifier  # before the dependencies: a cycle comes back to the copy
        if anchor != identifier and anchor not in self.memo:
            self.memo[anchor] = copy.identifier  # a whole .usdz is its first entry: naming it is naming this layer
        self.copies[copy.identifier] = copy
        self.origin[copy.identifier] = identifier
        new_paths: dict[str, str] = {}
        sublayers = [d for d in layer.subLayerPaths]
        for dep in deps:
            target, reason = resolve_asset_path(dep, anchor, self.mode, self.asset_root, self.archive,
                                                self.entries(self.archive) if self.archive else None)
            if target is None:
                self.refuse(dep, identifier, reason)
                new_paths[dep] = ""
                continue
            sub = self.visit(target, depth + 1)
            new_paths[dep] = sub or ""
        if sublayers:
            copy.subLayerPaths[:] = self.checked_sublayers(identifier, sublayers, new_paths, copy.identifier)
        changed = [dep for dep in deps if new_paths[dep] != dep]
        for _ in range(8):  # one call may rewrite only the sublayers (usd-core 26.11): repeat until done
            for dep in changed:
                copy.UpdateCompositionAssetDependency(dep, new_paths[dep])
            left = set(copy.GetCompositionAssetDependencies())
            changed = [dep for dep in changed if dep in left]
            if not changed:
                break
        for prim_path in clip_prims:
            self.rewrite_clips(copy, prim_path, anchor, identifier, depth)
        return copy.identifier

    def checked_sublayers(self, identifier: str, sublayers: list[str], new_paths: dict[str, str],
                          own: str) -> list[str]:
        """The copy's sublayer list: each sublayer as the layer it was checked as; refused ones, the
        layer itself (`l0.usda sublayers itself`) and repeats of a sublayer already listed are left out
        with a warning (USD refuses a list naming one layer twice, and a layer cannot contain itself)."""
        out: list[str] = []
        shown = self.name(identifier)
        for dep in sublayers:
            target = new_paths.get(dep, "")
            if not target:
                continue  # refused or unreadable: already warned about
            if target == own:
                self.warnings.append(f"{shown} sublayers itself (@{dep}@); that sublayer was ignored")
                continue
            if target in out:
                self.warnings.append(f"{shown} lists the same sublayer twice (@{dep}@); the repeat was ignored")
                continue
            out.append(target)
        return out

    def clip_target(self, asset: str, anchor: str, identifier: str, what: str, depth: int) -> str | None:
        """The identifier a value clip's asset path is rewritten to: the clip layer walked like any
        other layer (its own dependencies checked too), or None when refused or unreadable."""
        target, reason = resolve_asset_path(asset, anchor, self.mode, self.asset_root, self.archive,
                                            self.entries(self.archive) if self.archive else None)
        if target is None:
            self.refuse(asset, identifier, f"{what}: {reason}")
            return None
        return self.visit(target, depth + 1)

    def rewrite_clips(self, copy, prim_path, anchor: str, identifier: str, depth: int) -> None:
        """Value-clip sets of one prim spec: a set naming a refused asset (or a template, whose files
        cannot be listed before USD expands it) is dropped; the others get checked identifiers."""
        from pxr import Sdf

        spec = copy.GetObjectAtPath(prim_path)
        kept = {}
        for name, clip in dict(spec.GetInfo("clips")).items():
            clip = dict(clip) if clip else {}
            what = f"value clip set {name!r} of {prim_path}"
            ok = True
            if clip.get("templateAssetPath"):
                self.refuse(str(clip["templateAssetPath"]), identifier,
                            f"{what}: clip templates can name any file matching a pattern")
                ok = False
            paths = [getattr(a, "path", str(a)) for a in (clip.get("assetPaths") or [])]
            targets = [self.clip_target(a, anchor, identifier, what, depth) for a in paths]
            manifest = clip.get("manifestAssetPath")
            m_target = None
            if manifest:
                m_target = self.clip_target(getattr(manifest, "path", str(manifest)), anchor, identifier, what, depth)
                ok = ok and m_target is not None
            if not ok or any(t is None for t in targets):
                continue
            if paths:
                clip["assetPaths"] = Sdf.AssetPathArray([Sdf.AssetPath(t) for t in targets])
            if manifest:
                clip["manifestAssetPath"] = Sdf.AssetPath(m_target)
            kept[name] = clip
        if kept:
            spec.SetInfo("clips", kept)
        else:
            spec.ClearInfo("clips")

    # --- verification
    def allowed(self, identifier: str) -> bool:
        """A checked layer USD may open as it is (no dependencies) or a copy."""
        return identifier in self.copies or self.memo.get(identifier) == identifier

    def verify_graph(self) -> None:
        """Before Usd.Stage.Open: every asset path left in the layers USD will compose is a checked layer."""
        for ident, layer in list(self.copies.items()) + [(i, l) for i, l in self.originals.items()
                                                          if self.memo.get(i) == i]:
            for dep in layer.GetCompositionAssetDependencies():
                if dep and not self.allowed(dep):
                    raise SceneError("sandbox_unchecked", f"{self.name(self.origin.get(ident, ident))} still names "
                                     f"@{dep}@, which was not checked; refused")
            for prim_path in _clip_prims(layer):
                for clip in dict(layer.GetObjectAtPath(prim_path).GetInfo("clips")).values():
                    clip = dict(clip) if clip else {}
                    assets = [getattr(a, "path", str(a)) for a in (clip.get("assetPaths") or [])]
                    if clip.get("manifestAssetPath"):
                        assets.append(getattr(clip["manifestAssetPath"], "path", str(clip["manifestAssetPath"])))
                    if clip.get("templateAssetPath") or any(not self.allowed(a) for a in assets):
                        raise SceneError("sandbox_unchecked", f"{self.name(self.origin.get(ident, ident))} still names a "
                                         "value clip that was not checked; refused")

    def verify_stage(self, stage) -> None:
        """After Usd.Stage.Open: the stage composed checked layers (or their copies) only."""
        for used in stage.GetUsedLayers():
            if used.anonymous and (used.identifier in self.copies or used == stage.GetSessionLayer()):
                continue
            if used.anonymous and all(not d or self.allowed(d) for d in used.GetCompositionAssetDependencies()):
                continue  # made by USD in memory (a value clip's generated manifest)
            if not used.anonymous and self.memo.get(used.identifier) == used.identifier:
                continue
            raise SceneError("sandbox_unchecked", f"the stage composed {self.name(used.identifier)}, which was not "
                             "checked; refused")

    def file_layers(self):
        """The checked, file-backed layers (for the scene hash)."""
        return [self.originals[i] for i in sorted(self.originals)]

    def display(self, layer) -> str:
        return self.name(self.origin.get(layer.identifier, layer.identifier))


def _count_composed_prims(layer, limit: int) -> int:
    """The prims a stage on `layer` composes (all of them: classes, inactive and instanced prims
    included, payloads loaded), counted with Pcp one prim index at a time, depth first, and refused
    (too_many_prims) as soon as the count passes `limit`: references, inherits and payloads multiply a
    few specs into many prims (1,000 references to a 1,000-prim class: 1 M prims from 2,000 specs,
    30 s in Usd.Stage.Open), and this stops after `limit` indices (50,000: ~0.6 s) instead."""
    from pxr import Pcp, Sdf

    cache = Pcp.Cache(Pcp.LayerStackIdentifier(layer), usd=True)
    count = 0
    stack = [Sdf.Path.absoluteRootPath]
    while stack:
        path = stack.pop()
        index, _errors = cache.ComputePrimIndex(path)  # errors: Usd.Stage.Open reports them
        if index.hasAnyPayloads and not cache.IsPayloadIncluded(path):
            cache.RequestPayloads([path], [])
            index, _errors = cache.ComputePrimIndex(path)
        if path != Sdf.Path.absoluteRootPath:
            count += 1
            if count > limit:
                raise SceneError("too_many_prims", f"the scene composes more than {limit} prims (limit {limit}); "
                                 f"counted before composing the stage, the limit was passed at {path}")
        names, _prohibited = index.ComputePrimChildNames()
        stack.extend(path.AppendChild(n) for n in reversed(names))
    return count


def _clip_prims(layer) -> list:
    """Paths of the prim specs (variants included) of `layer` that author value clips."""
    return _scan_layer(layer)[0]


def _scan_layer(layer) -> tuple[list, int]:
    """One Sdf traversal of `layer`: (paths of the prim specs, variants included, that author value
    clips; the number of prim specs, variants' prims included)."""
    found = []
    count = 0

    def on_spec(path):
        nonlocal count
        if not path.IsPrimPath() and not path.IsPrimVariantSelectionPath():
            return
        if path.IsPrimPath():
            count += 1
        spec = layer.GetObjectAtPath(path)
        if spec is not None and spec.HasInfo("clips"):
            found.append(path)

    layer.Traverse(layer.pseudoRoot.path, on_spec)
    return found, count


_PRIM_KEYWORDS = re.compile(rb"(?<![\w\"'])(?:def|over|class)(?=[\s\"{(])")


def _layer_bytes(identifier: str, entries) -> bytes | None:
    """The bytes of a file layer or a usdz entry, None when they cannot be read here."""
    pkg, inner = split_package_path(identifier)
    try:
        if inner is None and not identifier.lower().endswith(".usdz"):
            with open(identifier, "rb") as f:
                return f.read()
        with zipfile.ZipFile(pkg) as z:
            names = list(entries(pkg))
            name = inner if inner is not None else (names[0] if names else None)
            return z.read(name) if name is not None else None
    except (OSError, KeyError, zipfile.BadZipFile, ValueError, RuntimeError):
        return None


def _spec_bound(identifier: str, entries) -> int:
    """An upper bound of the prim specs a layer holds, found without parsing it: in a text layer the
    def/over/class keywords (every prim spec starts with one; bytes.count first, the token regex only
    when that passes the limit), in a binary layer the number of all its specs (its table of contents,
    refused past SANDBOX_MAX_CRATE_SPECS). 0 when unknown: the exact count follows the parse."""
    data = _layer_bytes(identifier, entries)
    if not data:
        return 0
    if data.startswith(b"#usda"):
        rough = data.count(b"def") + data.count(b"over") + data.count(b"class")
        return rough if rough <= SANDBOX_MAX_PRIM_SPECS else len(_PRIM_KEYWORDS.findall(data))
    if data.startswith(b"PXR-USDC"):
        n = _crate_spec_count(data)
        if n is not None and n > SANDBOX_MAX_CRATE_SPECS:
            raise SceneError("too_many_prims", f"spec limit {SANDBOX_MAX_CRATE_SPECS}: a binary layer holds {n} specs "
                             f"(more than {SANDBOX_MAX_CRATE_SPECS}); refused before reading it")
    return 0


def _crate_spec_count(data: bytes) -> int | None:
    """The spec count of a .usdc (crate) file from its table of contents: the bootstrap header gives the
    TOC's offset, the TOC the SPECS section, whose first 8 bytes are the number of specs. None when the
    file does not have that layout (USD then reads or refuses it)."""
    import struct

    try:
        (toc,) = struct.unpack_from("<q", data, 16)
        (nsec,) = struct.unpack_from("<Q", data, toc)
        if nsec > 64:
            return None
        for k in range(nsec):
            name, start, _size = struct.unpack_from("<16sqq", data, toc + 8 + 32 * k)
            if name.rstrip(b"\0") == b"SPECS":
                return struct.unpack_from("<Q", data, start)[0]
    except struct.error:
        return None
    return None


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


def _scene_name(identifier: str, scene_dir: str) -> str:
    """How a message names a layer: relative to the scene's folder when inside it (a usdz entry as
    'archive.usdz[entry]'), else by its base name; anonymous layers by their tag."""
    if identifier.startswith("anon:"):
        return identifier.rsplit(":", 1)[-1]
    pkg, inner = split_package_path(identifier)
    rel = os.path.relpath(pkg, scene_dir) if os.path.isabs(pkg) else pkg
    name = rel if not rel.startswith("..") else os.path.basename(pkg)
    return f"{name}[{inner}]" if inner is not None else name


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


_SPLIT_MIN = 256  # polygons with more corners are first cut along diagonals into pieces of at most this size


def _earcut(p2: np.ndarray) -> np.ndarray:
    import mapbox_earcut

    tris = mapbox_earcut.triangulate_float64(np.ascontiguousarray(p2), np.array([len(p2)], np.uint32))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _cross2(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def _in_cone(p2: np.ndarray, a, b, eps: float):
    """Does the segment from corner a towards corner b start into the polygon (O'Rourke's InCone;
    counter-clockwise p2; near the cone's sides counts as outside)? a, b: ints or index arrays."""
    n = len(p2)
    a, b = np.asarray(a), np.asarray(b)
    prev, nxt, pa, pb = p2[(a - 1) % n], p2[(a + 1) % n], p2[a % n], p2[b % n]
    convex = _cross2(pa, nxt, prev) >= 0
    inside_convex = (_cross2(pa, pb, prev) > eps) & (_cross2(pb, pa, nxt) > eps)
    inside_reflex = ~((_cross2(pa, pb, nxt) >= -eps) & (_cross2(pb, pa, prev) >= -eps))
    return np.where(convex, inside_convex, inside_reflex)


def _crosses_no_edge(p2: np.ndarray, i: int, j: int, eps: float) -> bool:
    """Does the segment between corners i and j cross or touch no edge that is not incident to i or j
    (near-touching counts as touching, so the answer errs on no)?"""
    n = len(p2)
    k = np.arange(n)
    k1 = (k + 1) % n
    edges = (k != i) & (k1 != i) & (k != j) & (k1 != j)
    a, b = p2[k[edges]], p2[k1[edges]]
    pi, pj = p2[i][None, :], p2[j][None, :]
    o1, o2 = _cross2(pi, pj, a), _cross2(pi, pj, b)
    o3, o4 = _cross2(a, b, pi), _cross2(a, b, pj)
    touching = (np.minimum(o1, o2) <= eps) & (np.maximum(o1, o2) >= -eps) \
        & (np.minimum(o3, o4) <= eps) & (np.maximum(o3, o4) >= -eps)
    return not bool(np.any(touching))


def _split(p2: np.ndarray, idx: np.ndarray, eps: float, pieces: list) -> bool:
    """Cut the sub-polygon p2[idx] along diagonals between roughly opposite corners (O'Rourke's
    Diagonal: in the cone at both ends, crossing no edge) until every piece has at most _SPLIT_MIN corners; False when some piece has
    no such diagonal. Candidates are screened by the cone test (vectorised); at most 12 per piece
    get the O(m) edge test."""
    m = len(idx)
    if m <= _SPLIT_MIN:
        pieces.append(idx)
        return True
    sub = p2[idx]
    i = np.repeat((np.arange(64) * m) // 128, 7)  # starts over the first half, partners about half-way
    j = i + m // 2 + np.tile([0, 1, -1, 2, -2, 3, -3], 64)
    ok = _in_cone(sub, i, j, eps) & _in_cone(sub, j, i, eps)
    for a, b in list(zip(i[ok].tolist(), j[ok].tolist()))[:12]:
        if _crosses_no_edge(sub, a, b, eps):
            return (_split(p2, idx[a:b + 1], eps, pieces)
                    and _split(p2, np.concatenate([idx[b:], idx[:a + 1]]), eps, pieces))
    return False


def _triangulate_ccw(p2: np.ndarray, eps: float) -> np.ndarray:
    """Triangles of the counter-clockwise polygon p2. earcut is quadratic on spiky polygons such as
    stars (every needle's bounding box spans many corners), so a big polygon is first cut into
    pieces of at most _SPLIT_MIN corners along checked diagonals, each piece cut by earcut; when the
    polygon has no such cut all the way down (a comb, say, on which earcut is fast anyway), earcut
    takes it whole."""
    idx = np.arange(len(p2))
    pieces: list[np.ndarray] = []
    if len(p2) > _SPLIT_MIN and _split(p2, idx, eps, pieces):
        return np.concatenate([piece[_earcut(p2[piece])] for piece in pieces])
    return _earcut(p2)


def ear_clip(pts: np.ndarray) -> np.ndarray:
    """Triangulate one simple polygon (n, 3) given in order, concave or not; returns (T, 3) local indices.

    The polygon is projected on its best-fit plane (Newell normal), counter-clockwise, cut along
    checked diagonals into pieces of about _SPLIT_MIN corners when it is bigger, and each piece
    triangulated by earcut (mapbox-earcut, C++); every triangle keeps the polygon's winding. A
    polygon earcut cannot cover (self-intersecting, e.g. a pentagram: its triangles do not add up to
    the polygon's signed area) is fanned, as is a degenerate one: there is no right answer."""
    n = len(pts)
    fan = np.stack([np.zeros(max(n - 2, 0), np.int64), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    if n < 3:
        return np.zeros((0, 3), np.int64)
    if n == 3:
        return fan
    p2 = _project_ccw(np.asarray(pts, dtype=np.float64))
    if p2 is None or not np.all(np.isfinite(p2)):
        return fan  # degenerate: any fan has zero area
    scale = float(np.abs(p2).max()) or 1.0
    eps = 1e-12 * scale * scale
    tris = _triangulate_ccw(p2, eps)
    a, b, c = p2[tris[:, 0]], p2[tris[:, 1]], p2[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    nxt = np.roll(p2, -1, axis=0)
    area2 = float(np.sum(p2[:, 0] * nxt[:, 1] - nxt[:, 0] * p2[:, 1]))  # shoelace: twice the signed area
    if len(tris) != n - 2 and not math.isclose(float(np.abs(cross).sum()), area2, rel_tol=1e-6, abs_tol=eps):
        return fan
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
    one vectorised pass and fanned, and only the concave ones go to earcut (ear_clip) one by one."""
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
            if len(t):
                out.append(pl[t])
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


def implicit_triangle_count(type_name: str) -> int:
    """Triangles implicit_mesh makes for a prim of this type (0: not an implicit prim), known without
    tessellating: a revolved profile of k points whose ends are poles gives 2 * SEGMENTS * (k - 2)."""
    half = SEGMENTS // 2
    profile = {"Sphere": half + 1, "Cylinder": 4, "Cylinder_1": 4, "Cone": 3,
               "Capsule": 2 * (max(half // 2, 2) + 1), "Capsule_1": 2 * (max(half // 2, 2) + 1)}
    if type_name == "Cube":
        return 12
    if type_name == "Plane":
        return 2
    k = profile.get(type_name)
    return 2 * SEGMENTS * (k - 2) if k else 0


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


class _Budget:
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


def _face_triangles(counts) -> int:
    """Triangles a faceVertexCounts array stands for: n - 2 per face of n >= 3 corners."""
    c = _as_array(counts, None, np.int64)
    if c is None or not len(c):
        return 0
    c = c[c >= 3]
    return int(np.sum(c - 2)) if len(c) else 0


def _mesh_triangles(prim, time_code, warnings, charge=None):
    """(points, triangles) of a Mesh or None; with `charge`, its faces are charged from
    faceVertexCounts before points and indices are read or anything is triangulated."""
    from pxr import UsdGeom

    if charge is None:
        return _mesh_geometry(prim, time_code, warnings)
    est = _face_triangles(_get(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr(), time_code))
    charge(est, str(prim.GetPath()))
    r = _mesh_geometry(prim, time_code, warnings)
    charge((len(r[1]) if r is not None else 0) - est, str(prim.GetPath()))  # what it really made
    return r


def _mesh_geometry(prim, time_code, warnings):
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
        scene = _load(path, time_code, asset_root, sandbox, max_triangles, max_prims)
    except SceneError as e:
        raise SceneError(e.code, scrub(e.message)) from e.__cause__
    scene.warnings = [scrub(w) for w in scene.warnings]
    scene.load_s = time.perf_counter() - t_start
    return scene


def _load(path, time_code, asset_root, sandbox, max_triangles, max_prims=None, read=None) -> LoadedScene:
    """The stage opened with the mode's checks, then _extract; or `read(stage, warnings)`'s value instead
    (read_animation: the same opening, checks and error handling, no geometry)."""
    name = os.path.basename(path) or path
    _check_file(path)
    warnings: list[str] = []
    diag: list[str] = []
    walk = None
    try:
        from pxr import Tf, Usd
    except ImportError as e:  # pragma: no cover - set-up problem
        raise SceneError("unavailable", f"usd-core is not installed: {e}") from e
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
                walk = _LayerWalk(root, mode, asset_root, warnings, layer_name)
                if walk.root is None:
                    raise SceneError("corrupt", f"{name}: USD could not read the file (truncated or damaged)")
                walk.verify_graph()
                root = walk.root
            layer = (walk.copies.get(root) or walk.originals.get(root)) if walk else _open_fresh(root)
            if layer is None:
                raise SceneError("corrupt", f"{name}: USD could not read the file (truncated or damaged)")
            if walk is not None and max_prims is not None:
                _count_composed_prims(layer, max_prims)  # references multiply specs: bound before composing
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
            scene = _extract(stage, path, time_code, warnings, _Budget(max_triangles, max_prims), name, shown)
    except SceneError:
        raise
    except Tf.ErrorException as e:
        msg = _usd_error_text(_tf_text(e))
        raise SceneError("corrupt", f"{name}: USD could not read the file: {msg[:300]}") from e
    except RecursionError as e:
        raise SceneError("too_large", f"{name}: the scene nests too deeply to be read") from e
    except (RuntimeError, ValueError, OSError, zipfile.BadZipFile) as e:
        raise SceneError("corrupt", f"{name}: {type(e).__name__}: {str(e)[:300]}") from e
    except MemoryError as e:
        raise SceneError("too_large", f"{name}: the scene does not fit in memory") from e
    except Exception as e:  # never let anything else escape: the caller handles SceneError only
        raise SceneError("internal", f"{name}: the loader failed ({type(e).__name__}: {str(e)[:300]})") from e
    all_warnings = _dedupe(warnings + diag)
    scene.warnings = all_warnings[:MAX_WARNINGS]
    if len(all_warnings) > MAX_WARNINGS:
        scene.warnings.append(f"... and {len(all_warnings) - MAX_WARNINGS} more warnings")
    try:
        scene.scene_hash = _scene_hash(stage, path, walk.file_layers() if walk is not None else None)
    except OSError as e:
        raise SceneError("not_found", f"{name}: a layer could not be read for hashing ({e.strerror})") from e
    del walk
    return scene


def _dedupe(items: list[str]) -> list[str]:
    seen, out = set(), []
    for w in items:
        if w not in seen:
            seen.add(w)
            out.append(w)
    return out


def _tf_text(e) -> str:
    """str() of a Tf error: USD's parser message quotes the damaged file, whose bytes may not be UTF-8."""
    try:
        return str(e)
    except UnicodeDecodeError:
        return "the file is not valid UTF-8 text"


def _usd_error_text(text: str) -> str:
    """The useful part of a Tf error: drop the C++ location and namespaces."""
    text = text.strip().strip("'")
    m = re.search(r" : '(.*)'?$", text, re.S)
    if m:
        text = m.group(1)
    text = re.sub(r"pxrInternal_v\w+::", "", text).strip().strip("'")
    return text or "unreadable"


def _scene_hash(stage, path, layers=None) -> str:
    """sha256 of the root file's bytes, then of every file-backed layer the stage composed, sorted by
    identifier (each as its name inside the scene folder and its own digest). Anonymous layers (the
    session layer, sandboxed copies) are derived from those files and left out, so the hash does not
    depend on memory addresses; in the restricted modes `layers` are the checked originals."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read())
    base = os.path.dirname(os.path.abspath(path))
    for layer in sorted(stage.GetUsedLayers() if layers is None else layers, key=lambda l: l.identifier):
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


def _stage_frame(stage, warnings, layer_name=None):
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
        shown = layer_name(other) if layer_name else (None if other.anonymous else os.path.basename(other.identifier))
        if other == layer or shown is None:
            continue
        try:
            info = other.pseudoRoot.GetInfo("metersPerUnit") if other.pseudoRoot.HasInfo("metersPerUnit") else None
        except Exception:  # noqa: BLE001 - metadata we cannot read is not worth failing for
            info = None
        if info is not None and not math.isclose(float(info), mpu, rel_tol=1e-9):
            warnings.append(f"layer {shown} is authored with metersPerUnit {float(info):g} but "
                            f"the stage uses {mpu:g}; USD does not rescale it, so it is read in the stage's units")
    return up, mpu


def _extract(stage, path, time_code, warnings, budget: _Budget | None = None, name=None,
             layer_name=None) -> LoadedScene:
    from pxr import Usd, UsdGeom, UsdLux

    budget = budget or _Budget(None)
    name = name or os.path.basename(path)
    tc = Usd.TimeCode.Default() if time_code is None else Usd.TimeCode(time_code)
    up, mpu = _stage_frame(stage, warnings, layer_name)
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
            return _mesh_triangles(prim, tc, warnings, None if charged else budget.charge)
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
            return _face_triangles(_get(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr(), tc))
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


def _expand_instancer(prim, tc, xcache, add, geometry_of, triangles_of, skip_subtree, warnings, budget):
    """Every visible instance of a PointInstancer: prototype geometry placed by the instance
    transforms (which include each prototype root's own transform); invisibleIds/inactiveIds masked.

    The budget is charged visible instances x prototype triangles (counted without tessellating)
    before any instance transform is computed or any prototype tessellated."""
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
    indices = _as_array(inst.GetProtoIndicesAttr().Get(t), None, np.int64)
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
    inst_world = _np_matrix(xcache.GetLocalToWorldTransform(prim))
    proto_geo = []
    for k, root in enumerate(roots):
        parts = []
        if root and per_proto[k] and proto_tris[k] and not skip_subtree(root):
            # relative to the prototype root: its own transform comes with the instance transforms
            root_inv = np.linalg.inv(_np_matrix(xcache.GetLocalToWorldTransform(root)))
            rng = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
            for p in rng:
                if skip_subtree(p):
                    rng.PruneChildren()
                    continue
                g = geometry_of(p, charged=True)
                if g is not None:
                    rel = root_inv @ _np_matrix(xcache.GetLocalToWorldTransform(p))
                    parts.append((g, rel, str(p.GetPath())))
        proto_geo.append(parts)
    for k in np.flatnonzero(named):
        pi = indices[k]
        if not proto_geo[pi]:
            continue
        m = inst_world @ _np_matrix(xforms[int(k)])
        for (pts, tris), rel, ppath in proto_geo[pi]:
            sub = ppath[len(ipath):] if ppath.startswith(ipath) else ppath
            add(pts, tris, m @ rel, f"{ipath}[{k}]{sub}")


def read_animation(path, camera_path: str | None, time_codes: list[float], *, light_paths: list[str] | None = None,
                   asset_root: str | None = None, sandbox: bool = False, max_prims: int | None = None) -> dict:
    """A camera and lights read at each of `time_codes` (their time samples, USD's interpolation), the stage
    opened as load_scene opens it (same checks in the restricted modes), without reading geometry.

    Returns {"camera": [UsdCamera per time] or None when `camera_path` is None, "camera_type": the prim's
    type name ("" when there is no such prim), "lights": {usd_path: [UsdLight per time]} for `light_paths`
    (default: every light of the stage), "moving": prim paths (up to 20) of geometry whose transform or
    points have time samples, "time_range": [start, end] time codes of the stage or None, "warnings", "camera_problems":
    the camera values replaced by fallbacks (not finite or not positive) or a non-finite transform, per time code,
    "triangles_added": per time code the triangles the geometry's sampled topology adds to the default time's
    count (_triangle_change; None when no prim's count changes), "growing": up to 5 of those prims}.
    A time code is read as Usd.TimeCode(t): world transforms from UsdGeom.XformCache(t)."""
    path = os.fspath(path)
    scrub = PathRedactor([os.path.dirname(os.path.abspath(path)), asset_root]).text
    times = [float(t) for t in time_codes]

    def read(stage, warnings):
        from pxr import Usd, UsdGeom, UsdLux

        up, mpu = _stage_frame(stage, warnings)
        s2w = _stage_to_world(up, mpu)
        out = {"camera": None, "camera_type": "", "lights": {}, "moving": [], "time_range": None,
               "camera_problems": []}
        if stage.HasAuthoredTimeCodeRange():
            out["time_range"] = [float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode())]
        caches = [UsdGeom.XformCache(Usd.TimeCode(t)) for t in times]
        if camera_path is not None:
            prim = stage.GetPrimAtPath(camera_path) if camera_path.startswith("/") else None
            out["camera_type"] = str(prim.GetTypeName()) if prim else ""
            if prim and prim.IsA(UsdGeom.Camera):
                out["camera"] = [_camera(prim, Usd.TimeCode(t), xc, s2w, mpu, warnings, out["camera_problems"])
                                 for t, xc in zip(times, caches)]
        budget = _Budget(None, max_prims)
        extra, growing = None, []
        for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
            budget.prim(prim)
            p = str(prim.GetPath())
            if prim.HasAPI(UsdLux.LightAPI) or "Light" in prim.GetTypeName():
                if light_paths is None or p in light_paths:
                    ls = [_light(prim, Usd.TimeCode(t), xc, s2w) for t, xc in zip(times, caches)]
                    if ls and ls[0] is not None:
                        out["lights"][p] = ls
            elif prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer):
                if _changes_over_time(prim):
                    if len(out["moving"]) < 20:
                        out["moving"].append(p)
                    delta = _triangle_change(prim, times)
                    if delta is not None:
                        extra = [a + b for a, b in zip(extra, delta)] if extra else delta
                        growing.append(p)
        out["triangles_added"] = extra  # per time code, or None when no prim's triangle count changes
        out["growing"] = growing[:5]
        out["warnings"] = [scrub(w) for w in _dedupe(warnings)][:MAX_WARNINGS]
        out["camera_problems"] = [scrub(w) for w in out["camera_problems"][:MAX_WARNINGS]]
        return out

    try:
        return _load(path, None, asset_root, sandbox, None, max_prims, read=read)
    except SceneError as e:
        raise SceneError(e.code, scrub(e.message)) from e.__cause__


def _changes_over_time(prim) -> bool:
    """Whether what the loader reads of a Gprim or PointInstancer can change with the time code: its transform
    or an ancestor's, its own or an ancestor's visibility, or any of its own attributes (points, topology, an
    instancer's positions, orientations, scales, protoIndices, invisibleIds) having time samples."""
    from pxr import Usd, UsdGeom

    def varies(attr) -> bool:  # one sample and no default reads the same at every time code (_get)
        n = attr.GetNumTimeSamples()
        return n > 1 or (n == 1 and attr.Get(Usd.TimeCode.Default()) is not None)

    chain = [prim, *_ancestors(prim)]
    if any(UsdGeom.Xformable(a).TransformMightBeTimeVarying() for a in chain if a.IsA(UsdGeom.Xformable)):
        return True
    if any(varies(UsdGeom.Imageable(a).GetVisibilityAttr()) for a in chain if a.IsA(UsdGeom.Imageable)):
        return True
    return any(varies(attr) for attr in prim.GetAttributes())


def _held(attr, times: list[float]) -> list:
    """attr's value at each time code for an attribute USD holds rather than interpolates (integer arrays:
    topology, protoIndices), read once per time sample it lands on (its lower bracketing sample)."""
    from pxr import Usd

    values, out = {}, []
    for t in times:
        bracket = attr.GetBracketingTimeSamples(t)  # (lower, upper), empty without samples
        key = float(bracket[0]) if bracket else None
        if key not in values:
            values[key] = attr.Get(Usd.TimeCode(key)) if key is not None else attr.Get(Usd.TimeCode(t))
        out.append(values[key])
    return out


def _triangle_change(prim, times: list[float]) -> list[int] | None:
    """What a Mesh with sampled faceVertexCounts, or a PointInstancer with sampled protoIndices, adds at each
    time code to the triangles the loader counts at the default time (a stage light there and heavy at t = 5);
    None when its triangle count cannot change. Instances counted whatever their mask (an upper bound);
    prototypes' triangles as at the default time."""
    from pxr import Usd, UsdGeom

    default = Usd.TimeCode.Default()
    if prim.IsA(UsdGeom.Mesh):
        attr = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr()
        if attr.GetNumTimeSamples() == 0:
            return None
        base = _face_triangles(_get(attr, default))
        return [_face_triangles(v) - base for v in _held(attr, times)]
    if not prim.IsA(UsdGeom.PointInstancer):
        return None
    inst = UsdGeom.PointInstancer(prim)
    attr = inst.GetProtoIndicesAttr()
    if attr.GetNumTimeSamples() == 0:
        return None
    stage = prim.GetStage()
    proto_tris = []
    for target in inst.GetPrototypesRel().GetTargets():
        root, n = stage.GetPrimAtPath(target), 0
        if root:
            for q in Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
                if q.IsA(UsdGeom.Mesh):
                    n += _face_triangles(_get(UsdGeom.Mesh(q).GetFaceVertexCountsAttr(), default))
                elif q.IsA(UsdGeom.Gprim):
                    n += implicit_triangle_count(q.GetTypeName())
        proto_tris.append(n)
    tris = np.asarray(proto_tris + [0], np.int64)  # an index naming no prototype: no triangles

    def count(v) -> int:
        idx = _as_array(v, None, np.int64)
        if idx is None or not len(idx):
            return 0
        idx = np.where((idx >= 0) & (idx < len(proto_tris)), idx, len(proto_tris))
        return int(tris[idx].sum())

    base = count(_get(attr, default))
    return [count(v) - base for v in _held(attr, times)]


def _ancestors(prim):
    p = prim.GetParent()
    while p and not p.IsPseudoRoot():
        yield p
        p = p.GetParent()


CAMERA_FALLBACKS = {"focalLength": 50.0, "horizontalAperture": 20.955, "verticalAperture": 15.2908}  # USD's
CLIPPING_FALLBACK = (1.0, 1e6)  # UsdGeom.Camera's clippingRange fallback, stage units


def _camera(prim, tc, xcache, s2w, mpu, warnings, problems: list | None = None) -> UsdCamera:
    """Position and axes from the camera's transform (it looks along local -Z, up is local +Y);
    clipping range from stage units to meters; fov from the vertical aperture and focal length.
    A focalLength or aperture that is not a finite positive number (NaN, inf, 0, negative), or a clipping
    range that is not 0 < near < far (finite), is replaced by USD's fallback with a warning naming the
    attribute, its value and the time code; with `problems` (read_animation) the same text is appended there
    too, so a path can refuse the frame instead of solving it with a made-up field of view."""
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    at = "" if tc.IsDefault() else f" at time code {tc.GetValue():g}"

    def bad(text: str, fallback: str) -> None:
        warnings.append(f"{text}; USD's fallback {fallback} used")
        if problems is not None:
            problems.append(text)

    vals = {}
    for name, attr in (("focalLength", cam.GetFocalLengthAttr()), ("horizontalAperture", cam.GetHorizontalApertureAttr()),
                       ("verticalAperture", cam.GetVerticalApertureAttr())):
        v = _get(attr, tc)
        try:
            v = CAMERA_FALLBACKS[name] if v is None else float(v)
        except (TypeError, ValueError):
            v = math.nan
        if not (math.isfinite(v) and v > 0):
            bad(f"{prim.GetPath()}: {name} {v:g}{at} is not a finite positive number (the field of view is "
                f"2 atan(verticalAperture / (2 focalLength)))", f"{CAMERA_FALLBACKS[name]:g}")
            v = CAMERA_FALLBACKS[name]
        vals[name] = v
    focal, hap, vap = vals["focalLength"], vals["horizontalAperture"], vals["verticalAperture"]
    clip = _get(cam.GetClippingRangeAttr(), tc)
    try:
        near, far = (float(clip[0]), float(clip[1])) if clip is not None else CLIPPING_FALLBACK
    except (TypeError, ValueError, IndexError):
        near, far = math.nan, math.nan
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        bad(f"{prim.GetPath()}: clippingRange ({near:g}, {far:g}){at} is not 0 < near < far (finite)",
            f"({CLIPPING_FALLBACK[0]:g}, {CLIPPING_FALLBACK[1]:g})")
        near, far = CLIPPING_FALLBACK
    m = s2w @ _np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    fwd = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    up = transform_directions(m, np.array([0.0, 1.0, 0.0]))
    if problems is not None and not (np.all(np.isfinite(m)) and np.linalg.norm(fwd) > 1e-12 and np.linalg.norm(up) > 1e-12):
        problems.append(f"{prim.GetPath()}: its world transform{at} is not finite or collapses the view axes "
                        "(NaN, infinite or zero scale)")
    fov = math.degrees(2.0 * math.atan(vap / (2.0 * focal)))
    return UsdCamera(str(prim.GetPath()), pos, fwd, up, fov, near * mpu, far * mpu, focal, hap, vap)


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
