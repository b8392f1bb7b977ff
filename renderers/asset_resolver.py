"""Which asset paths a scene may open (the two resolution modes).

- "local" (the CLI): USD resolves as usual, `../` included; with an `asset_root`, a path that
  resolves outside that folder is refused.
- "sandbox" (scenes uploaded to the service): only the upload itself. For a plain file that means
  no other file at all; for a .usdz, only entries of the archive. Absolute paths, `..` that leaves
  the archive, URLs and search paths are refused, and usdz entries with traversal names are refused
  before USD opens the archive.
Refused paths are never opened: the loader drops them from (copies of) the layers that name them.
Variable expressions (`"${VAR}.usda"` in backquotes) are refused whenever a restriction applies,
since what they resolve to is only known inside USD.
Decisions here are pure functions of strings and folder names; nothing is read (except the zip
directory in `unsafe_usdz_entries` / `usdz_entries`).

`resolve_asset_path` is what the loader uses in the restricted modes: the same decision, plus the exact
layer identifier the asset path stands for (anchored by hand, never through USD's search paths), which
is checked again (inside the asset root / an entry of the uploaded archive) and is what USD is then told
to open. It also refuses what a restricted mode cannot check before USD opens it: file format arguments,
formats other than USD's own (a .mtlx, say, which MaterialX reads with its own includes), and packages
nested in packages.
"""
from __future__ import annotations

import os
import posixpath
import re
import zipfile

_URL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # scheme: (but not a Windows drive in practice)
_PACKAGE = re.compile(r"^(?P<pkg>.+?\.usdz)\[(?P<inner>.+)\]$")
USD_LAYER_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")  # USD's own file formats (the loader's too)


def split_package_path(path: str) -> tuple[str, str | None]:
    """'a.usdz[b/c.usda]' -> ('a.usdz', 'b/c.usda'); a plain path -> (path, None)."""
    m = _PACKAGE.match(path)
    return (m.group("pkg"), m.group("inner")) if m else (path, None)


def join_inside(folder: str, rel: str) -> str | None:
    """`rel` (backslashes read as slashes) joined to `folder` inside an archive and normalised, or None
    when the result leaves the archive ('..' above its top, or absolute)."""
    joined = posixpath.normpath(posixpath.join(folder, rel.replace("\\", "/")))
    return None if joined == ".." or joined.startswith(("../", "/")) else joined


def is_inside(path: str, root: str) -> bool:
    path, root = os.path.realpath(path), os.path.realpath(root)
    return path == root or path.startswith(root.rstrip(os.sep) + os.sep)


def check_asset_path(asset_path: str, anchor: str, mode: str, asset_root: str | None = None,
                     archive: str | None = None) -> tuple[bool, str]:
    """May `asset_path`, written in the layer `anchor` (a file path or 'pkg.usdz[inner]'), be opened?

    mode "local": allowed unless `asset_root` is given and the resolved file lies outside it.
    mode "sandbox": allowed only as an entry of `archive` (the uploaded .usdz) that stays inside it.
    Returns (ok, reason).
    """
    if not asset_path:
        return False, "empty asset path"
    if mode not in ("local", "sandbox"):
        raise ValueError(f"mode must be 'local' or 'sandbox', got {mode!r}")
    if mode == "local" and asset_root is None:
        return True, "ok"
    if asset_path.lstrip().startswith("`"):
        return False, f"{asset_path!r} is a variable expression, which cannot be checked before USD evaluates it"
    if "\x00" in asset_path:
        return False, f"{asset_path!r} contains a NUL character"
    if asset_path.startswith("anon:"):
        return False, f"{asset_path!r} names an anonymous (in-memory) layer, which an uploaded scene may not reach"
    if _URL.match(asset_path) and not os.path.isabs(asset_path):
        return False, f"{asset_path!r} is a URL"
    if mode == "local":
        pkg, _ = split_package_path(asset_path)
        anchor_pkg, _ = split_package_path(anchor)
        base = os.path.dirname(os.path.abspath(anchor_pkg))
        target = pkg if os.path.isabs(pkg) else os.path.join(base, pkg)
        if not is_inside(target, asset_root):
            return False, f"{asset_path!r} resolves outside the asset root {asset_root!r}"
        return True, "ok"
    # sandbox
    if archive is None:
        return False, (f"{asset_path!r}: an uploaded single-file scene may not open other files (upload the scene "
                       "with the files it names as one package: a .usdz, e.g. from `shadowopt pack`, or a .zip of "
                       "its folder)")
    if os.path.isabs(asset_path) or asset_path.startswith("\\"):
        return False, f"{asset_path!r} is an absolute path"
    if "[" in asset_path:
        return False, f"{asset_path!r} names a package"
    _, inner_anchor = split_package_path(anchor)
    if join_inside(posixpath.dirname(inner_anchor) if inner_anchor else "", asset_path) is None:
        return False, f"{asset_path!r} leaves the uploaded archive"
    return True, "ok"


def resolve_asset_path(asset_path: str, anchor: str, mode: str, asset_root: str | None = None,
                       archive: str | None = None, entries=None) -> tuple[str | None, str]:
    """(identifier of the layer `asset_path` names, "ok") or (None, reason) in a restricted mode.

    `anchor` is the identifier of the layer that names it: a file path or 'pkg.usdz[inner]' (the
    archive's root layer is anchored as its first entry). `entries`: the entry names of `archive`
    (sandbox: a path naming no entry is refused). The identifier is absolute and normalised: a file
    path, 'pkg.usdz' (a whole package, local mode) or 'pkg.usdz[inner]'."""
    ok, why = check_asset_path(asset_path, anchor, mode, asset_root, archive)
    if not ok:
        return None, why
    if mode == "local" and asset_root is None:
        raise ValueError("resolve_asset_path is for the restricted modes (sandbox, or an asset root)")
    if ":SDF_FORMAT_ARGS:" in asset_path:
        return None, f"{asset_path!r} carries file format arguments"
    pkg, inner = split_package_path(asset_path)
    if inner is not None and "[" in inner:
        return None, f"{asset_path!r} names a package inside a package"
    last = (inner if inner is not None else pkg).replace("\\", "/")
    if not last.lower().endswith(USD_LAYER_EXTENSIONS):
        return None, (f"{asset_path!r} is not a USD layer (.usd, .usda, .usdc, .usdz); other formats are read "
                      "by plug-ins this check cannot follow")
    anchor_pkg, anchor_inner = split_package_path(anchor)
    if anchor_inner is not None and inner is None and not os.path.isabs(pkg) and not pkg.startswith("\\"):
        # relative to a layer inside a package: another entry of that package
        joined = join_inside(posixpath.dirname(anchor_inner), pkg)
        if joined is None:
            return None, f"{asset_path!r} leaves the package {os.path.basename(anchor_pkg)!r}"
        if joined.lower().endswith(".usdz"):
            return None, f"{asset_path!r} names a package inside a package"
        package = os.path.normpath(os.path.abspath(anchor_pkg))
        if mode == "sandbox":
            if archive is None or os.path.realpath(package) != os.path.realpath(archive):
                return None, f"{asset_path!r} is not inside the uploaded archive"
            if entries is not None and joined not in entries:
                return None, f"{asset_path!r}: the archive has no entry {joined!r}"
        elif not is_inside(package, asset_root):
            return None, f"{asset_path!r} resolves outside the asset root {asset_root!r}"
        return f"{package}[{joined}]", "ok"
    if mode == "sandbox":  # a sandboxed layer outside a package may not name anything
        return None, f"{asset_path!r}: only entries of the uploaded archive may be opened"
    base = os.path.dirname(os.path.abspath(anchor_pkg))
    target = os.path.normpath(pkg if os.path.isabs(pkg) else os.path.join(base, pkg))
    if not is_inside(target, asset_root):
        return None, f"{asset_path!r} resolves outside the asset root {asset_root!r}"
    if inner is not None:
        inner = join_inside("", inner)
        if inner is None:
            return None, f"{asset_path!r} leaves the package it names"
        return f"{target}[{inner}]", "ok"
    return target, "ok"


def is_unsafe_entry_name(name: str) -> bool:
    """A zip entry name that is absolute, names a drive, or climbs out with '..'."""
    return (name.startswith(("/", "\\")) or join_inside("", name) is None
            or re.match(r"^[A-Za-z]:", name) is not None or "\x00" in name)


def usdz_entries(path: str) -> list[str]:
    """Entry names of a .usdz (zip) archive in archive order (the first one is USD's root layer)."""
    with zipfile.ZipFile(path) as z:
        return z.namelist()


def unsafe_usdz_entries(path: str) -> list[str]:
    """Entry names of a .usdz (zip) archive that are absolute or climb out with '..'."""
    return [n for n in usdz_entries(path) if is_unsafe_entry_name(n)]
