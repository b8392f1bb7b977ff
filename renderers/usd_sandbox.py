"""The restricted modes' layer walk (renderers.usd_loader: `sandbox`, or `asset_root` given) and its limits.

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
                                    (count_composed_prims) and again by the traversal.
  The prim limits answer SceneError("too_many_prims"). 300,000 empty Xforms (6.8 MB) took 20-24 s to
  load (parse 2.1 s, walk 5.3 s, Usd.Stage.Open 3.7 s, traversal 10.9 s); now refused in 0.6 s.
  Real assets stay far below them (largest composed: the Intent teapot scene, 7,370 prims, 1,766 specs) (the OpenChessSet: 29 layers, 3 deep, 8.3 MiB; the Intent VFX
  teapot scene: 11 layers, 6 deep). Fail-closed choices: dependencies other than USD layers (.mtlx,
  whose includes MaterialX follows itself), file format arguments, packages nested in packages and
  value-clip templates (their files are only known once USD expands the pattern) are refused.
"""
from __future__ import annotations

import os
import re
import struct
import zipfile

from pxr import Pcp, Sdf, Tf

from .asset_resolver import resolve_asset_path, split_package_path
from .scene_data import SceneError
from .usd_diagnostics import tf_text, usd_error_text

SANDBOX_MAX_DEPTH = 32
SANDBOX_MAX_LAYERS = 256
SANDBOX_MAX_LAYER_BYTES = 512 * 1024 * 1024
SANDBOX_MAX_PRIM_SPECS = 50_000  # prim specs over all layers (variants included), counted before composing
SANDBOX_MAX_CRATE_SPECS = 250_000  # all specs of one binary (.usdc) layer, read from its table of contents
SANDBOX_MAX_PRIMS = 50_000  # composed prims the traversal may visit (restricted modes' default max_prims)


def _limit(which: str, detail: str) -> SceneError:
    return SceneError("sandbox_limit", f"{which}: {detail}; refused")


class LayerWalk:
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
        self.bounds[identifier] = spec_bound(identifier, self.entries)  # before Sdf parses it
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
        if identifier in self.memo:
            return self.memo[identifier]
        self.charge(identifier, depth)
        self.memo[identifier] = None
        if depth == 0:
            layer = open_fresh(identifier)  # the root: failing to read it is the caller's error
            if layer is None:
                return None
        else:
            try:
                layer = open_fresh(identifier)
            except Tf.ErrorException as e:
                layer = None
                why = usd_error_text(tf_text(e))[:200]
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
        clip_prims, n_prims = scan_layer(layer)
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


def count_composed_prims(layer, limit: int) -> int:
    """The prims a stage on `layer` composes (all of them: classes, inactive and instanced prims
    included, payloads loaded), counted with Pcp one prim index at a time, depth first, and refused
    (too_many_prims) as soon as the count passes `limit`: references, inherits and payloads multiply a
    few specs into many prims (1,000 references to a 1,000-prim class: 1 M prims from 2,000 specs,
    30 s in Usd.Stage.Open), and this stops after `limit` indices (50,000: ~0.6 s) instead."""
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
    return scan_layer(layer)[0]


def scan_layer(layer) -> tuple[list, int]:
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


def spec_bound(identifier: str, entries) -> int:
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
        n = crate_spec_count(data)
        if n is not None and n > SANDBOX_MAX_CRATE_SPECS:
            raise SceneError("too_many_prims", f"spec limit {SANDBOX_MAX_CRATE_SPECS}: a binary layer holds {n} specs "
                             f"(more than {SANDBOX_MAX_CRATE_SPECS}); refused before reading it")
    return 0


def crate_spec_count(data: bytes) -> int | None:
    """The spec count of a .usdc (crate) file from its table of contents: the bootstrap header gives the
    TOC's offset, the TOC the SPECS section, whose first 8 bytes are the number of specs. None when the
    file does not have that layout (USD then reads or refuses it)."""
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


def open_fresh(identifier: str):
    """Sdf.Layer.FindOrOpen, but a layer already in USD's registry (held by some other live stage)
    is reloaded first when its file changed on disk, so what is checked and composed is the file as
    it is now. Layers with unsaved in-memory edits are left alone."""
    layer = Sdf.Layer.Find(identifier)
    if layer is not None and not layer.anonymous and not layer.dirty:
        layer.Reload()  # a no-op unless the file's modification time changed
        return layer
    return Sdf.Layer.FindOrOpen(identifier)
