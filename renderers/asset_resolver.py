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
"""
from __future__ import annotations

import os
import posixpath
import re
import zipfile

_URL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # scheme: (but not a Windows drive in practice)
_PACKAGE = re.compile(r"^(?P<pkg>.+?\.usdz)\[(?P<inner>.+)\]$")


def split_package_path(path: str) -> tuple[str, str | None]:
    """'a.usdz[b/c.usda]' -> ('a.usdz', 'b/c.usda'); a plain path -> (path, None)."""
    m = _PACKAGE.match(path)
    return (m.group("pkg"), m.group("inner")) if m else (path, None)


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
        return False, f"{asset_path!r}: an uploaded single-file scene may not open other files"
    if os.path.isabs(asset_path) or asset_path.startswith("\\"):
        return False, f"{asset_path!r} is an absolute path"
    if "[" in asset_path:
        return False, f"{asset_path!r} names a package"
    _, inner_anchor = split_package_path(anchor)
    anchor_dir = posixpath.dirname(inner_anchor) if inner_anchor else ""
    joined = posixpath.normpath(posixpath.join(anchor_dir, asset_path.replace("\\", "/")))
    if joined.startswith("../") or joined == ".." or joined.startswith("/"):
        return False, f"{asset_path!r} leaves the uploaded archive"
    return True, "ok"


def is_unsafe_entry_name(name: str) -> bool:
    """A zip entry name that is absolute, names a drive, or climbs out with '..'."""
    norm = posixpath.normpath(name.replace("\\", "/"))
    return (name.startswith(("/", "\\")) or norm == ".." or norm.startswith("../")
            or re.match(r"^[A-Za-z]:", name) is not None or "\x00" in name)


def usdz_entries(path: str) -> list[str]:
    """Entry names of a .usdz (zip) archive in archive order (the first one is USD's root layer)."""
    with zipfile.ZipFile(path) as z:
        return z.namelist()


def unsafe_usdz_entries(path: str) -> list[str]:
    """Entry names of a .usdz (zip) archive that are absolute or climb out with '..'."""
    return [n for n in usdz_entries(path) if is_unsafe_entry_name(n)]
