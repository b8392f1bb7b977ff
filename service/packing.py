"""Multi-file scenes as one package: a stage with the layers it references, sublayers and payloads.

- `pack_stage(scene, out, allow_outside=False)`: a local stage and everything it depends on as one .usdz
  (usd-core's UsdUtils.CreateNewUsdzPackage: the root layer first, dependencies at their paths relative
  to it). A stage naming a file outside its own folder (an absolute path, '..', a symbolic link leading
  out) is refused naming those files unless `allow_outside`: a downloaded stage could otherwise pull
  ~/.ssh/... into a package that is then uploaded. `shadowopt pack` and the client use it.
- `needs_package(scene)`: whether a local stage names other files (UsdUtils.ComputeAllDependencies).
- `zip_to_usdz(data, name)` (bytes) / `zip_to_usdz_file(data, name, work_dir)` (a file; what the server uses,
  after `zip_declared_bytes` told it what unpacking will write): an uploaded .zip of a scene's folder turned
  into a .usdz the sandboxed loader reads like any package (its internal paths resolve inside it and nowhere else). Fail closed:
  an entry that is absolute, climbs out with '..', names a drive, is a symbolic link, is encrypted, names
  the folder itself ('a/..') or is also the folder of another entry, or a zip over MAX_ZIP_ENTRIES entries
  (counted from its end records before zipfile reads the central directory) or MAX_UNPACKED_BYTES unpacked
  is refused (SceneError "unsafe_archive" / "sandbox_limit", naming the entry as the zip names it, never a
  server path).
  The root layer is the one USD layer at the top of the folder (a single top-level folder, as zipping
  a folder makes, is looked into).
"""
from __future__ import annotations

import os
import posixpath
import re
import shutil
import stat
import struct
import tempfile
import time
import zipfile
import zlib
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
    its folder where they lie inside it, else as the absolute path of the file read (symbolic links
    followed: a link in the folder leading out is outside) (usd-core's UsdUtils.ComputeAllDependencies)."""
    from pxr import UsdUtils  # lazy: usd-core is the server extra; api.client imports this module

    src = os.path.abspath(os.fspath(scene))
    base = os.path.dirname(src)
    try:
        layers, assets, unresolved = UsdUtils.ComputeAllDependencies(src)
    except Exception as e:  # pxr.Tf.ErrorException: a layer that does not parse
        raise SceneError("corrupt", f"{os.path.basename(src)}: usd-core cannot read the stage or a layer it names "
                         f"({type(e).__name__})") from e
    real_base = os.path.realpath(base)

    def rel(p: str) -> str:
        real = os.path.realpath(p)
        return os.path.relpath(real, real_base) if real.startswith(real_base + os.sep) else real

    return ([rel(l.realPath or l.identifier) for l in layers], [rel(a) for a in assets],
            [str(u) for u in unresolved])


def outside_files(layers: list[str], assets: list[str]) -> list[str]:
    """The dependencies (as `dependencies` gives them) that lie outside the stage's folder."""
    return [p for p in layers + assets if os.path.isabs(p)]


def needs_package(scene) -> bool:
    """True when the stage names any file besides itself (a sublayer, reference, payload or asset)."""
    path = os.fspath(scene)
    if path.lower().endswith(".usdz") or not path.lower().endswith(USD_LAYER_EXTENSIONS):
        return False
    layers, assets, unresolved = dependencies(path)
    return len(layers) > 1 or bool(assets) or bool(unresolved)


def pack_stage(scene, out, allow_outside: bool = False) -> dict:
    """Write `scene` and its dependencies to the .usdz `out`; returns {"out", "entries", "bytes", "layers",
    "assets", "unresolved", "outside"} (unresolved: paths the stage names that do not exist, left out;
    outside: files outside the stage's folder, packed only with `allow_outside`, else SceneError
    "outside_folder" naming them)."""
    from pxr import UsdUtils  # lazy: usd-core is the server extra; api.client imports this module

    src, out = Path(scene), Path(out)
    if not src.is_file():
        raise SceneError("not_found", f"cannot open scene {src.name!r}: no such file")
    if src.suffix.lower() not in ROOT_LAYER_EXTENSIONS:
        raise SceneError("not_usd", f"{src.name}: pack a .usd, .usda or .usdc stage (a .usdz is a package already)")
    if out.suffix.lower() != ".usdz":
        raise SceneError("bad_option", f"--out: {out.name!r}: the package is a .usdz file")
    layers, assets, unresolved = dependencies(src)
    outside = outside_files(layers, assets)
    if outside and not allow_outside:
        shown = ", ".join(outside[:5]) + (f" and {len(outside) - 5} more" if len(outside) > 5 else "")
        raise SceneError("outside_folder", f"{src.name} names {len(outside)} file(s) outside its folder ({shown}); "
                         "packing would upload them. Pack them anyway only if you trust the stage: "
                         "`shadowopt pack --allow-outside`, or upload_scene(..., pack=True) in the client "
                         "(pack=False sends the stage alone)")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not UsdUtils.CreateNewUsdzPackage(os.fspath(src), os.fspath(out)):
        raise SceneError("corrupt", f"{src.name}: usd-core could not package the stage")
    with zipfile.ZipFile(out) as z:
        entries = z.namelist()
    return {"out": os.fspath(out), "entries": len(entries), "bytes": out.stat().st_size, "layers": len(layers),
            "assets": assets, "unresolved": unresolved, "outside": outside}


def pack_bytes(scene, allow_outside: bool = False) -> tuple[bytes, str]:
    """`scene` packed as .usdz bytes and the package's file name (the stage's name with .usdz)."""
    src = Path(scene)
    with tempfile.TemporaryDirectory(prefix="shadowopt-pack-") as tmp:
        out = Path(tmp) / (src.stem + ".usdz")
        pack_stage(src, out, allow_outside=allow_outside)
        return out.read_bytes(), out.name


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


_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record (APPNOTE.TXT 4.3.16)
_EOCD64_LOCATOR = struct.Struct("<4sLQL")  # ZIP64 end of central directory locator (4.3.15)
_EOCD64 = struct.Struct("<4sQ2H2L4Q")  # ZIP64 end of central directory record (4.3.14)
_CENTRAL = struct.Struct("<4s4B4HL2L5H2L")  # central directory file header (4.3.12), 46 bytes


def _declared_entries(data: bytes) -> int | None:
    """How many entries the zip's central directory holds, from its end records and at most
    MAX_ZIP_ENTRIES + 1 of its records, found as Python's zipfile finds them (_EndRecData, _RealGetContents):
    the larger of the declared count and the records walked (zipfile walks the directory's declared size, not
    its count, so a count that lies does not hide records). None when there is no end record (zipfile then
    says the zip is damaged)."""
    size = len(data)
    at = size - _EOCD.size
    if not (at >= 0 and data[at:at + 4] == b"PK\x05\x06" and data[-2:] == b"\0\0"):
        at = data.rfind(b"PK\x05\x06", max(size - (1 << 16) - _EOCD.size, 0))
        if at < 0 or at + _EOCD.size > size:
            return None
    _, _, _, _, count, size_cd, offset_cd, _ = _EOCD.unpack_from(data, at)
    start = at - size_cd  # the directory ends where the end records begin (a zip appended to other bytes too)
    loc = at - _EOCD64_LOCATOR.size
    if loc >= 0 and data[loc:loc + 4] == b"PK\x06\x07" and loc - _EOCD64.size >= 0:
        z64 = _EOCD64.unpack_from(data, loc - _EOCD64.size)
        if z64[0] == b"PK\x06\x06":
            count, size_cd = max(z64[6], z64[7]), z64[8]
            start = loc - _EOCD64.size - size_cd
    records, pos, end = 0, max(start, 0), max(start, 0) + size_cd
    while pos < end and records <= MAX_ZIP_ENTRIES and pos + _CENTRAL.size <= size:
        head = _CENTRAL.unpack_from(data, pos)
        if head[0] != b"PK\x01\x02":
            break
        records += 1
        pos += _CENTRAL.size + head[12] + head[13] + head[14]  # name, extra field and comment lengths
    return max(count, records)


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
    """(prefix, {name below the prefix: entry}); the prefix is a single top-level folder shared by all.
    An entry that names the folder itself ('a/..', '.') or whose name is also a folder holding another
    entry ('tex' and 'tex/a.png') is refused, named by its name below the prefix."""
    names: dict[str, zipfile.ZipInfo] = {}
    for i in files:
        n = posixpath.normpath(i.filename.replace("\\", "/"))
        if n in ("", "."):
            raise _refuse(i.filename, "names the folder itself, not a file")
        if n in names:
            raise _refuse(i.filename, "a second entry of the same name")
        names[n] = i
    tops = {n.split("/", 1)[0] for n in names}
    prefix = ""
    if len(tops) == 1 and all("/" in n for n in names):
        prefix = next(iter(tops)) + "/"
    out = {n[len(prefix):]: info for n, info in names.items()}
    folders = {inner.rsplit("/", 1)[0] for inner in out if "/" in inner}
    folders |= {f.rsplit("/", k)[0] for f in folders for k in range(1, f.count("/") + 1)}
    for inner in sorted(out):
        if inner in folders:
            raise _refuse(inner, "a file whose name is also a folder of other entries")
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


def _open_zip(data: bytes, name: str) -> zipfile.ZipFile:
    count = _declared_entries(data)
    if count is not None and count > MAX_ZIP_ENTRIES:
        least = "at least " if count == MAX_ZIP_ENTRIES + 1 else ""  # the walk stops one record past the limit
        raise SceneError("sandbox_limit", f"zip entries: {least}{count} entries, over the limit of {MAX_ZIP_ENTRIES}; "
                         "refused")
    try:
        return zipfile.ZipFile(BytesIO(data))
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise SceneError("corrupt", f"{os.path.basename(name)}: the zip archive is damaged ({type(e).__name__})") from e


def zip_declared_bytes(data: bytes, name: str, max_unpacked: int = MAX_UNPACKED_BYTES) -> int:
    """The bytes an uploaded zip's files declare unpacked (its central directory: nothing is unpacked), after
    the checks of zip_to_usdz that need no unpacking (entry count, names, links, the `max_unpacked` bound): what
    a server counts against a tenant's quota before it unpacks anything."""
    with _open_zip(data, name) as z:
        files = _checked_entries(z, max_unpacked)
        prefix, inside = _inside_names(files)
        _root_layer(list(inside), name, prefix)
        return sum(i.file_size for i in files)


USDZ_ALIGN = 64  # a usdz entry's data starts at a multiple of 64 bytes (Pixar, "Usdz File Format Specification")
USDZ_PADDING_ID = 0x1986  # the extra-field header id usd-core's own writer pads with (pxr/usd/sdf/zipFile.cpp)


def write_usdz(out, entries: list[tuple[str, str]]) -> None:
    """A .usdz at `out` holding `entries` [(name inside, file), ...] in that order (the root layer first), as
    the usdz specification wants them: stored uncompressed, each entry's data at a multiple of 64 bytes (the
    local header's extra field pads it, as usd-core's Sdf.ZipFileWriter does). Copied 1 MiB at a time:
    Sdf.ZipFileWriter reads each file whole into memory (+256 MB in the server for a 250 MB entry)."""
    with open(out, "wb") as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as z:
        for inner, src in entries:
            info = zipfile.ZipInfo(inner, date_time=(1980, 1, 1, 0, 0, 0))  # fixed: the same zip, the same package
            info.compress_type = zipfile.ZIP_STORED
            info.file_size = os.path.getsize(src)
            start = f.tell() + 30 + len(inner.encode("utf-8")) + 4  # local header (APPNOTE 4.3.7), name, pad header
            pad = -start % USDZ_ALIGN
            info.extra = struct.pack("<HH", USDZ_PADDING_ID, pad) + b"\0" * pad
            with open(src, "rb") as s, z.open(info, "w") as d:
                shutil.copyfileobj(s, d, 1 << 20)


def zip_to_usdz_file(data: bytes, name: str, work_dir, max_unpacked: int = MAX_UNPACKED_BYTES) -> tuple[Path, str]:
    """An uploaded .zip of a scene's folder as a .usdz file in `work_dir` (an empty folder the caller owns and
    removes: the entries are unpacked below it, the package written beside them) and the package's name. The
    entries' sizes as the zip declares them add up to at most `max_unpacked` bytes, and the bytes actually
    written are counted while they stream out: no entry is written past its declared size (declared sizes can
    lie), so nothing past the declared total reaches the disk. The package is written by `write_usdz`, a chunk
    at a time. A damaged entry (bad CRC, unknown compression) is refused naming it."""
    with _open_zip(data, name) as z:
        files = _checked_entries(z, max_unpacked)
        prefix, inside = _inside_names(files)
        root = _root_layer(list(inside), name, prefix)
        declared = sum(i.file_size for i in files)
        written = 0
        files_dir = os.path.join(os.fspath(work_dir), "files")  # the entries; the package is written beside them
        for inner, info in inside.items():
            target = os.path.join(files_dir, *inner.split("/"))
            try:
                os.makedirs(os.path.dirname(target), exist_ok=True)
                with z.open(info) as src, open(target, "wb") as dst:
                    left = info.file_size
                    while True:
                        chunk = src.read(min(1 << 20, left + 1))
                        if not chunk:
                            break
                        left -= len(chunk)
                        written += len(chunk)
                        if left < 0 or written > declared:
                            raise _refuse(info.filename, "more bytes than its header says")
                        dst.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as e:
                raise SceneError("corrupt", f"zip entry {info.filename.lstrip('/')!r} is damaged or cannot be "
                                 f"unpacked ({type(e).__name__})") from e
            except OSError as e:  # a name the file system refuses (too long, ...): no server path shown
                raise _refuse(info.filename, f"cannot be unpacked ({type(e).__name__}: "
                              f"{e.strerror or 'refused by the file system'})") from e
        if inside[root].file_size == 0:
            raise SceneError("empty_stage", f"the zip's root layer {root!r} is empty")
        out = os.path.join(os.fspath(work_dir), "out.usdz")
        # an empty file is left out: usd-core cannot map it, and an empty file holds no layer or texel
        order = [root] + sorted(n for n in inside if n != root and inside[n].file_size > 0)
        try:
            write_usdz(out, [(inner, os.path.join(files_dir, *inner.split("/"))) for inner in order])
        except (OSError, ValueError, zipfile.LargeZipFile) as e:
            raise SceneError("corrupt", f"{os.path.basename(name)}: the package could not be written "
                             f"({type(e).__name__})") from e
        shutil.rmtree(files_dir, ignore_errors=True)  # the package holds them now
    return Path(out), Path(root).stem + ".usdz"


ZIP_TEMP_PREFIX = "shadowopt-zip-"


def sweep_system_temp(grace_s: float = 3600.0) -> int:
    """Remove the `shadowopt-zip-*` folders older than `grace_s` from the system temp dir (servers before issue 27
    unpacked zips there, and a killed one left them); how many. A server calls it at start."""
    removed, now = 0, time.time()
    root = Path(tempfile.gettempdir())
    for d in root.glob(ZIP_TEMP_PREFIX + "*"):
        try:
            st = d.lstat()
        except OSError:
            continue
        if stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and now - st.st_mtime >= grace_s:
            shutil.rmtree(d, ignore_errors=True)
            removed += 1
    return removed


def zip_to_usdz(data: bytes, name: str, max_unpacked: int = MAX_UNPACKED_BYTES, work_dir=None) -> tuple[bytes, str]:
    """zip_to_usdz_file's package as bytes, unpacked in a scratch folder under `work_dir` (default: the system
    temp dir; a server passes its data dir's, see service.store.Store.work_dir)."""
    with tempfile.TemporaryDirectory(prefix=ZIP_TEMP_PREFIX, dir=work_dir) as tmp:
        out, pkg = zip_to_usdz_file(data, name, tmp, max_unpacked)
        return out.read_bytes(), pkg
