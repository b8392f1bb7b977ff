"""Multi-file scenes as one package: a stage with the layers it references, sublayers and payloads.

- `pack_stage(scene, out)`: a local stage and everything it depends on as one .usdz (usd-core's
  UsdUtils.CreateNewUsdzPackage: the root layer first, dependencies at their paths relative to it,
  paths outside its folder remapped inside the package). `shadowopt pack` and the client use it.
- `needs_package(scene)`: whether a local stage names other files (UsdUtils.ComputeAllDependencies).
- `zip_to_usdz(data, name)`: an uploaded .zip of a scene's folder turned into a .usdz the sandboxed
  loader reads like any package (its internal paths resolve inside it and nowhere else). Fail closed:
  an entry that is absolute, climbs out with '..', names a drive, is a symbolic link, is encrypted, or
  a zip over MAX_ZIP_ENTRIES entries or MAX_UNPACKED_BYTES unpacked is refused (SceneError
  "unsafe_archive" / "sandbox_limit", naming the entry as the zip names it, never a server path).
  The root layer is the one USD layer at the top of the folder (a single top-level folder, as zipping
  a folder makes, is looked into).
"""
from __future__ import annotations

import os
import posixpath
import re
import stat
import tempfile
import zipfile
from io import BytesIO
from pathlib import Path

from ..renderers.asset_resolver import USD_LAYER_EXTENSIONS, is_unsafe_entry_name
from ..renderers.scene_data import SceneError

MAX_ZIP_ENTRIES = 4096
MAX_UNPACKED_BYTES = 512 * 1024 * 1024  # as the loader's SANDBOX_MAX_LAYER_BYTES
ROOT_LAYER_EXTENSIONS = (".usd", ".usda", ".usdc")


# -- local stages ----------------------------------------------------------------------------------

def dependencies(scene) -> tuple[list[str], list[str], list[str]]:
    """(layers, other assets, unresolved paths) the stage at `scene` depends on, as paths relative to
    its folder where they lie inside it (usd-core's UsdUtils.ComputeAllDependencies)."""
    from pxr import UsdUtils

    src = os.path.abspath(os.fspath(scene))
    base = os.path.dirname(src)
    try:
        layers, assets, unresolved = UsdUtils.ComputeAllDependencies(src)
    except Exception as e:  # pxr.Tf.ErrorException: a layer that does not parse
        raise SceneError("corrupt", f"{os.path.basename(src)}: usd-core cannot read the stage or a layer it names "
                         f"({type(e).__name__})") from e
    rel = lambda p: os.path.relpath(p, base) if os.path.abspath(p).startswith(base + os.sep) else p  # noqa: E731
    return ([rel(l.realPath or l.identifier) for l in layers], [rel(a) for a in assets],
            [str(u) for u in unresolved])


def needs_package(scene) -> bool:
    """True when the stage names any file besides itself (a sublayer, reference, payload or asset)."""
    path = os.fspath(scene)
    if path.lower().endswith(".usdz") or not path.lower().endswith(USD_LAYER_EXTENSIONS):
        return False
    layers, assets, unresolved = dependencies(path)
    return len(layers) > 1 or bool(assets) or bool(unresolved)


def pack_stage(scene, out) -> dict:
    """Write `scene` and its dependencies to the .usdz `out`; returns {"out", "entries", "bytes", "layers",
    "assets", "unresolved"} (unresolved: paths the stage names that do not exist, left out)."""
    from pxr import UsdUtils

    src, out = Path(scene), Path(out)
    if not src.is_file():
        raise SceneError("not_found", f"cannot open scene {src.name!r}: no such file")
    if src.suffix.lower() not in ROOT_LAYER_EXTENSIONS:
        raise SceneError("not_usd", f"{src.name}: pack a .usd, .usda or .usdc stage (a .usdz is a package already)")
    if out.suffix.lower() != ".usdz":
        raise SceneError("bad_option", f"--out: {out.name!r}: the package is a .usdz file")
    layers, assets, unresolved = dependencies(src)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not UsdUtils.CreateNewUsdzPackage(os.fspath(src), os.fspath(out)):
        raise SceneError("corrupt", f"{src.name}: usd-core could not package the stage")
    with zipfile.ZipFile(out) as z:
        entries = z.namelist()
    return {"out": os.fspath(out), "entries": len(entries), "bytes": out.stat().st_size, "layers": len(layers),
            "assets": assets, "unresolved": unresolved}


def pack_bytes(scene) -> tuple[bytes, str]:
    """`scene` packed as .usdz bytes and the package's file name (the stage's name with .usdz)."""
    src = Path(scene)
    with tempfile.TemporaryDirectory(prefix="shadowopt-pack-") as tmp:
        out = Path(tmp) / (src.stem + ".usdz")
        pack_stage(src, out)
        return out.read_bytes(), out.name


def zip_folder_bytes(folder) -> tuple[bytes, str]:
    """A local folder as .zip bytes (regular files only, symbolic links left out) and its name."""
    folder = Path(folder)
    buf = BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(folder.rglob("*")):
            if p.is_file() and not p.is_symlink():
                z.write(p, p.relative_to(folder).as_posix())
    return buf.getvalue(), folder.name + ".zip"


# -- uploaded zips -----------------------------------------------------------------------------------

def _refuse(name: str, why: str) -> SceneError:
    """The entry named as the zip names it, less a leading slash (so no message carries an absolute path)."""
    return SceneError("unsafe_archive", f"zip entry {name.lstrip('/').lstrip(chr(92))!r}: {why}; the upload is refused")


def _why_unsafe(name: str) -> str:
    if name.startswith(("/", "\\")):
        return "an absolute path"
    if re.match(r"^[A-Za-z]:", name):
        return "a path on a drive"
    if "\x00" in name:
        return "a NUL character in its name"
    return "'..' leads out of the folder"


def _checked_entries(z: zipfile.ZipFile, max_unpacked: int = MAX_UNPACKED_BYTES) -> list[zipfile.ZipInfo]:
    infos = z.infolist()
    if len(infos) > MAX_ZIP_ENTRIES:
        raise SceneError("sandbox_limit", f"zip entries: {len(infos)} entries, over the limit of {MAX_ZIP_ENTRIES}; "
                         "refused")
    files, total = [], 0
    for info in infos:
        name = info.filename
        if is_unsafe_entry_name(name):
            raise _refuse(name, _why_unsafe(name))
        mode = info.external_attr >> 16
        if stat.S_ISLNK(mode):
            raise _refuse(name, "a symbolic link")
        if info.flag_bits & 0x1:
            raise _refuse(name, "encrypted")
        if info.is_dir():
            continue
        if stat.S_IFMT(mode) not in (0, stat.S_IFREG):  # no type bits (e.g. a zip made on Windows): a file
            raise _refuse(name, "not a regular file")
        total += info.file_size
        if total > max_unpacked:
            raise SceneError("sandbox_limit", f"zip size: over {max_unpacked} bytes unpacked; refused")
        files.append(info)
    if not files:
        raise SceneError("empty_stage", "the zip holds no files")
    return files


def _inside_names(files: list[zipfile.ZipInfo]) -> tuple[str, dict[str, zipfile.ZipInfo]]:
    """(prefix, {name below the prefix: entry}); the prefix is a single top-level folder shared by all."""
    names = {posixpath.normpath(i.filename.replace("\\", "/")): i for i in files}
    tops = {n.split("/", 1)[0] for n in names}
    prefix = ""
    if len(tops) == 1 and all("/" in n for n in names):
        prefix = next(iter(tops)) + "/"
    out = {}
    for n, info in names.items():
        inner = n[len(prefix):]
        if inner in out:
            raise _refuse(info.filename, "a second entry of the same name")
        out[inner] = info
    return prefix, out


def _root_layer(names: list[str], zip_name: str, prefix: str) -> str:
    top = sorted(n for n in names if "/" not in n and n.lower().endswith(ROOT_LAYER_EXTENSIONS))
    if len(top) == 1:
        return top[0]
    if not top:
        raise SceneError("empty_stage", "the zip has no .usd, .usda or .usdc layer at the top of its folder "
                         "(the scene's root layer)")
    stems = {Path(zip_name).stem.lower(), prefix.rstrip("/").lower()}
    named = [n for n in top if Path(n).stem.lower() in stems]
    if len(named) == 1:
        return named[0]
    raise SceneError("ambiguous_root", f"the zip's folder has {len(top)} top-level layers ({', '.join(top[:5])}); "
                     "keep only the scene's root layer at the top, or name the zip after it")


def zip_to_usdz(data: bytes, name: str, max_unpacked: int = MAX_UNPACKED_BYTES) -> tuple[bytes, str]:
    """An uploaded .zip of a scene's folder as .usdz bytes (root layer first; usd-core's Sdf.ZipFileWriter,
    which stores entries uncompressed and aligned as a usdz needs) and the package's name. The entries'
    sizes as the zip declares them add up to at most `max_unpacked` bytes, and no entry is read past its
    declared size; a damaged entry (bad CRC, unknown compression) is refused naming it."""
    import zlib

    from pxr import Sdf

    try:
        z = zipfile.ZipFile(BytesIO(data))
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise SceneError("corrupt", f"{os.path.basename(name)}: the zip archive is damaged ({type(e).__name__})") from e
    with z:
        files = _checked_entries(z, max_unpacked)
        prefix, inside = _inside_names(files)
        root = _root_layer(list(inside), name, prefix)
        with tempfile.TemporaryDirectory(prefix="shadowopt-zip-") as tmp:
            for inner, info in inside.items():
                target = os.path.join(tmp, *inner.split("/"))
                os.makedirs(os.path.dirname(target), exist_ok=True)
                try:
                    with z.open(info) as src, open(target, "wb") as dst:
                        left = info.file_size
                        while True:
                            chunk = src.read(min(1 << 20, left + 1))
                            if not chunk:
                                break
                            left -= len(chunk)
                            if left < 0:
                                raise _refuse(info.filename, "more bytes than its header says")
                            dst.write(chunk)
                except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as e:
                    raise SceneError("corrupt", f"zip entry {info.filename.lstrip('/')!r} is damaged or cannot be "
                                     f"unpacked ({type(e).__name__})") from e
            out = os.path.join(tmp, ".package.usdz")
            try:
                writer = Sdf.ZipFileWriter.CreateNew(out)
                for inner in [root] + sorted(n for n in inside if n != root):
                    writer.AddFile(os.path.join(tmp, *inner.split("/")), inner)
                writer.Save()
            except Exception as e:  # pxr.Tf.ErrorException
                raise SceneError("corrupt", f"{os.path.basename(name)}: the package could not be written "
                                 f"({type(e).__name__})") from e
            with open(out, "rb") as f:
                package = f.read()
    return package, Path(root).stem + ".usdz"
