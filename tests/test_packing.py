"""Multi-file scenes as one package (service/packing.py): `shadowopt pack`, the client packing a stage that
names other files, a .zip of a scene's folder uploaded over a real uvicorn (tests/serverkit.py) and read in
the sandbox, and zips whose entries would leave their folder refused naming the entry."""
from __future__ import annotations

import io
import json
import os
import stat
import struct
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import httpx
import pytest
from serverkit import REPO, TOKENS, auth, running

from shadowopt.api.client import Client, scene_bytes, zip_folder_bytes
from shadowopt.renderers.scene_data import SceneError
from shadowopt.service import packing
from shadowopt.service.packing import MAX_ZIP_ENTRIES, needs_package, zip_to_usdz

CHESS = REPO.parent / "shared" / "usd-assets" / "full_assets" / "OpenChessSet" / "chess_set.usda"  # read in place
def cli(capsys, *argv: str):
    """`shadowopt ARGV` in process (`main(argv)`, what the installed script calls; the process boundary is crossed
    by test_cli.py): (exit code, stdout, stderr). An exception escaping main fails the test as a traceback would."""
    from shadowopt.api.cli import main

    capsys.readouterr()
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err

PART = """#usda 1.0
(
    defaultPrim = "Part"
)
def Mesh "Part"
{
    int[] faceVertexCounts = [3, 3]
    int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]
    point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
}
"""
ROOT = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    defaultPrim = "World"
)
def Xform "World"
{
    def Mesh "Ground"
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 3, 2, 1]
        point3f[] points = [(-5, 0, -5), (5, 0, -5), (5, 0, 5), (-5, 0, 5)]
    }
    def "A" (
        prepend references = @./parts/part.usda@
    )
    {
        double3 xformOp:translate = (0, 1, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def "B" (
        prepend payload = @./parts/part.usda@
    )
    {
        double3 xformOp:translate = (2, 1, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
}
"""
TRIANGLES = 2 + 2 * 2  # the ground quad, and the part's two triangles referenced once and loaded once as a payload


def multi_file_stage(folder: Path) -> Path:
    (folder / "parts").mkdir(parents=True)
    (folder / "parts" / "part.usda").write_text(PART)
    (folder / "scene.usda").write_text(ROOT)
    return folder / "scene.usda"


def zip_bytes(entries: dict[str, bytes], links: tuple[str, ...] = ()) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in entries.items():
            info = zipfile.ZipInfo(name)
            if name in links:
                info.external_attr = (stat.S_IFLNK | 0o777) << 16
            z.writestr(info, data)
    return buf.getvalue()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("packing") / "data") as srv:
        yield srv


# -- the package functions ---------------------------------------------------------------------------

@pytest.mark.parametrize("bad, shown, why", [("../escape.usda", "../escape.usda", "'..' leads out"),
                                             ("/etc/abs.usda", "etc/abs.usda", "an absolute path"),
                                             ("scene/..\\..\\up.usda", "scene/..\\..\\up.usda", "'..' leads out"),
                                             ("C:/drive.usda", "C:/drive.usda", "a path on a drive")])
def test_a_zip_entry_leaving_the_folder_is_refused_naming_it(bad, shown, why):
    data = zip_bytes({"scene/scene.usda": ROOT.encode(), bad: PART.encode()})
    with pytest.raises(SceneError) as e:
        zip_to_usdz(data, "scene.zip")
    assert e.value.code == "unsafe_archive" and f"zip entry {shown!r}: {why}" in e.value.message


def test_a_symlink_entry_is_refused():
    data = zip_bytes({"scene.usda": ROOT.encode(), "parts/part.usda": b"/etc/passwd"}, links=("parts/part.usda",))
    with pytest.raises(SceneError, match="'parts/part.usda': a symbolic link"):
        zip_to_usdz(data, "scene.zip")


def test_a_damaged_or_oversized_zip_is_refused_naming_why():
    data = bytearray(zip_bytes({"scene.usda": ROOT.encode(), "parts/part.usda": PART.encode()}))
    at = bytes(data).index(b"[3, 3]")  # flip a byte of the stored part: its CRC no longer matches
    data[at] ^= 0x20
    with pytest.raises(SceneError) as e:
        zip_to_usdz(bytes(data), "scene.zip")
    assert e.value.code == "corrupt" and "'parts/part.usda'" in e.value.message
    big = zip_bytes({"scene.usda": ROOT.encode(), "pad.bin": b"\0" * 5000})
    with pytest.raises(SceneError) as e:
        zip_to_usdz(big, "scene.zip", max_unpacked=4096)
    assert e.value.code == "sandbox_limit" and "4096" in e.value.message


def test_a_zip_of_a_folder_becomes_a_package_with_its_root_layer_first(tmp_path):
    stage = multi_file_stage(tmp_path / "site")
    assert needs_package(stage) and not needs_package(REPO / "configs" / "demo_scene.usda")
    data, name = zip_folder_bytes(tmp_path / "site")
    usdz, pkg = zip_to_usdz(data, name)
    assert pkg == "scene.usdz"
    with zipfile.ZipFile(io.BytesIO(usdz)) as z:
        assert z.namelist() == ["scene.usda", "parts/part.usda"]
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())  # as a usdz must be
    assert zip_to_usdz(data, name)[0] == usdz  # the same zip gives the same package (the same scene id)
    two = zip_bytes({"a.usda": ROOT.encode(), "b.usda": ROOT.encode()})
    with pytest.raises(SceneError) as e:
        zip_to_usdz(two, "x.zip")
    assert e.value.code == "ambiguous_root" and "a.usda, b.usda" in e.value.message
    assert zip_to_usdz(two, "b.zip")[1] == "b.usdz"  # the zip's name says which


def test_cli_pack_writes_a_usdz_the_sandbox_loads_whole(tmp_path, capsys):
    from shadowopt.renderers.usd_loader import load_scene

    stage = multi_file_stage(tmp_path / "site")
    out = tmp_path / "site.usdz"
    code, stdout, stderr = cli(capsys, "pack", str(stage), "--out", str(out), "--json")
    assert code == 0, stderr
    res = json.loads(stdout)
    assert res["entries"] == 2 and res["layers"] == 2 and res["unresolved"] == []
    assert load_scene(out, sandbox=True).info()["triangles"] == TRIANGLES
    alone = load_scene(stage).info()["triangles"]  # the same stage read from its folder
    assert alone == TRIANGLES
    code, _, stderr = cli(capsys, "pack", str(stage), "--out", str(tmp_path / "x.zip"))
    assert code == 2 and "--out" in stderr and "Traceback" not in stderr


# -- over a real server ----------------------------------------------------------------------------

@pytest.mark.server
def test_client_packs_a_multi_file_stage_and_uploads_a_folder(server, tmp_path):
    stage = multi_file_stage(tmp_path / "site")
    with Client(server.base, token=TOKENS["alice"]) as c:
        info = c.upload_scene(stage)
        assert info.triangles == TRIANGLES and info.filename == "scene.usdz"
        folder = c.upload_scene(tmp_path / "site")  # a folder goes as a .zip; the server finds scene.usda
        assert folder.triangles == TRIANGLES and folder.filename == "scene.usdz"
        alone = c.upload_scene(stage, pack=False)  # as it is, the single file may not open its parts
    assert alone.triangles == 2 and alone.filename == "scene.usda"
    refused = [w for w in alone.warnings if "parts/part.usda" in w]
    assert refused and all("one package" in w and str(tmp_path) not in w for w in refused)


@pytest.mark.server
@pytest.mark.parametrize("bad, shown", [("../../escape.usda", "../../escape.usda"), ("/abs/escape.usda", "abs/escape.usda")])
def test_server_refuses_an_unsafe_zip_entry_with_422_naming_it(server, bad, shown):
    data = zip_bytes({"scene/scene.usda": ROOT.encode(), bad: PART.encode()})
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "scene.zip"}, content=data,
                   headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=60)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "unsafe_archive" and err["field"] == "file" and f"zip entry {shown!r}" in err["message"]
    assert str(server.data_dir) not in r.text and "/tmp" not in r.text


@pytest.mark.server
def test_server_refuses_a_symlink_zip_entry(server):
    data = zip_bytes({"scene.usda": ROOT.encode(), "parts/part.usda": b"/etc/passwd"}, links=("parts/part.usda",))
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "scene.zip"}, content=data,
                   headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=60)
    assert r.status_code == 422 and "'parts/part.usda': a symbolic link" in r.json()["error"]["message"]


@pytest.mark.server
@pytest.mark.skipif(not CHESS.exists(), reason="the OpenChessSet asset is not on this machine")
def test_the_chess_set_packs_uploads_and_optimizes(server, tmp_path, capsys):
    """The chess set (references and payloads over 29 layers) packed by `shadowopt pack`, uploaded and
    optimized with an explicit camera and sun: every one of its triangles is read in the sandbox (the same
    count as reading it from its folder) and the solution is for that camera."""
    from shadowopt.renderers.usd_loader import load_scene

    out = tmp_path / "chess.usdz"
    code, _, stderr = cli(capsys, "pack", str(CHESS), "--out", str(out))
    assert code == 0, stderr
    local = load_scene(CHESS).info()["triangles"]
    with Client(server.base, token=TOKENS["alice"], timeout=300) as c:
        info = c.upload_scene(out)
        assert info.triangles == local > 1_000_000
        lo, hi = info.bounds["min"], info.bounds["max"]
        centre = [(a + b) / 2 for a, b in zip(lo, hi)]
        size = max(b - a for a, b in zip(lo, hi))
        rig = {"camera": {"position": [centre[0], centre[1] + 0.6 * size, centre[2] + 0.9 * size], "target": centre,
                          "resolution": [160, 90]},
               "lights": [{"type": "directional", "direction": [0.3, -1.0, -0.4]}],
               "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}
        sol = c.optimize(info.scene_id, rig, method="focused")
    assert sol.lights[0].predicted_error["samples"] > 0
    assert sol.lights[0].cascades[0].resolution == (256, 256)


@pytest.mark.server
@pytest.mark.skipif(not CHESS.exists(), reason="the OpenChessSet asset is not on this machine")
def test_the_chess_set_alone_is_refused_saying_how_and_showing_no_server_path(server):
    """Its root layer by itself holds no geometry (all of it is in referenced files): 422 empty_stage whose
    message says how to upload the scene whole, and names no folder of the server."""
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": CHESS.name}, content=CHESS.read_bytes(),
                   headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=120)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "empty_stage" and "one package" in err["message"] and ".zip" in err["message"]
    assert str(server.data_dir) not in r.text and str(server.data_dir.parent) not in r.text


# -- a stage naming files outside its folder is not packed unasked ---------------------------------

def stage_naming(folder: Path, asset: str) -> Path:
    """A one-file stage whose prim names `asset` (an asset-valued attribute usd-core's packager follows)."""
    stage = multi_file_stage(folder)
    stage.write_text(ROOT.replace('def Mesh "Ground"', f'asset info:tex = @{asset}@\n    def Mesh "Ground"'))
    return stage


def secret_file(tmp_path: Path) -> Path:
    (tmp_path / "home" / ".ssh").mkdir(parents=True)
    secret = tmp_path / "home" / ".ssh" / "id_secret"
    secret.write_text("PRIVATE KEY 0123456789")
    return secret


def package_holds(data: bytes, text: str) -> bool:
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        return any(text.encode() in z.read(n) for n in z.namelist())


@pytest.mark.parametrize("how", ["absolute", "relative", "link"])
def test_client_does_not_pack_a_file_outside_the_stage_folder_unless_asked(tmp_path, how):
    """An untrusted stage naming ~/.ssh/... (by absolute path, by '../..', or through a symbolic link in its
    folder) is refused by upload_scene's automatic packing, naming the local file; pack=True packs it."""
    secret = secret_file(tmp_path)
    site = tmp_path / "downloads" / "site"
    if how == "absolute":
        stage = stage_naming(site, str(secret))
    elif how == "relative":
        stage = stage_naming(site, "../../home/.ssh/id_secret")
    else:
        stage = stage_naming(site, "./tex.png")
        os.symlink(secret, site / "tex.png")
    with pytest.raises(SceneError) as e:
        scene_bytes(stage)
    assert e.value.code == "outside_folder" and str(secret) in e.value.message and "pack=True" in e.value.message
    data, name = scene_bytes(stage, pack=True)  # the user's explicit choice
    assert name == "scene.usdz" and package_holds(data, "PRIVATE KEY")
    alone, _ = scene_bytes(stage, pack=False)
    assert alone == stage.read_bytes()


def test_cli_pack_refuses_a_file_outside_the_stage_folder_unless_allowed(tmp_path, capsys):
    secret = secret_file(tmp_path)
    stage = stage_naming(tmp_path / "site", str(secret))
    out = tmp_path / "site.usdz"
    code, _, stderr = cli(capsys, "pack", str(stage), "--out", str(out))
    assert code == 2 and str(secret) in stderr and "--allow-outside" in stderr, stderr
    assert "Traceback" not in stderr and not out.exists()
    code, _, stderr = cli(capsys, "pack", str(stage), "--out", str(out), "--allow-outside")
    assert code == 0, stderr
    assert package_holds(out.read_bytes(), "PRIVATE KEY")


# -- zips whose names collide are refused with a 422, not a 500 -------------------------------------

@pytest.mark.parametrize("entries, shown, why", [
    ({"scene.usda": ROOT, "tex": "x", "tex/a.png": "y"}, "tex", "also a folder"),
    ({"scene.usda": ROOT, "tex/a.png": "y", "tex": "x"}, "tex", "also a folder"),
    ({"scene/scene.usda": ROOT, "scene/tex": "x", "scene/tex/a.png": "y"}, "tex", "also a folder"),
    ({"scene.usda": ROOT, "a/..": "x"}, "a/..", "names the folder itself"),
    ({"scene.usda": ROOT, "a" * 300 + ".png": "x"}, "a" * 300 + ".png", "cannot be unpacked"),
])
def test_a_zip_whose_entries_collide_is_refused_naming_the_entry(entries, shown, why):
    with pytest.raises(SceneError) as e:
        zip_to_usdz(zip_bytes({k: v.encode() for k, v in entries.items()}), "scene.zip")
    assert e.value.code == "unsafe_archive" and f"zip entry {shown!r}" in e.value.message and why in e.value.message
    assert "/tmp" not in e.value.message and "shadowopt-zip" not in e.value.message


def test_an_entry_named_like_the_package_being_written_is_just_a_file():
    usdz, name = zip_to_usdz(zip_bytes({"scene.usda": ROOT.encode(), ".package.usdz": b"junk", "out.usdz": b"j2"}),
                             "scene.zip")
    with zipfile.ZipFile(io.BytesIO(usdz)) as z:
        assert z.namelist() == ["scene.usda", ".package.usdz", "out.usdz"] and z.read(".package.usdz") == b"junk"
    assert name == "scene.usdz"


@pytest.mark.server
def test_server_answers_a_colliding_zip_with_422_naming_the_entry(server):
    for entries in ({"scene.usda": ROOT.encode(), "tex": b"x", "tex/a.png": b"y"},
                    {"scene.usda": ROOT.encode(), "tex/a.png": b"y", "tex": b"x"},
                    {"scene.usda": ROOT.encode(), "b" * 300: b"x"}):
        r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "scene.zip"}, content=zip_bytes(entries),
                       headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=60)
        assert r.status_code == 422, r.text
        err = r.json()["error"]
        assert err["code"] == "unsafe_archive" and "zip entry" in err["message"]
        assert str(server.data_dir) not in r.text and "/tmp" not in r.text


# -- the entry count is checked from the end record, before zipfile reads the central directory ------

def many_entries(n: int) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("scene.usda", ROOT)
        for i in range(n - 1):
            z.writestr(f"e{i}", b"")
    return buf.getvalue()


def as_zip64(data: bytes, declared: int | None = None) -> bytes:
    """The same zip ended by a ZIP64 end record and locator (APPNOTE 4.3.14-4.3.16), the classic end record's
    counts and offsets set to 0xFFFF / 0xFFFFFFFF as ZIP64 writers do; `declared` overrides the count."""
    at = data.rindex(b"PK\x05\x06")
    _, _, _, n, total, size_cd, off_cd, _ = struct.unpack("<4s4H2LH", data[at:at + 22])
    total = total if declared is None else declared
    z64 = struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, total, total, size_cd, off_cd)
    loc = struct.pack("<4sLQL", b"PK\x06\x07", 0, at, 1)
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    return data[:at] + z64 + loc + end


def with_declared_count(data: bytes, count: int) -> bytes:
    at = data.rindex(b"PK\x05\x06")
    return data[:at + 8] + struct.pack("<2H", count, count) + data[at + 12:]


def test_too_many_entries_are_refused_before_zipfile_reads_the_central_directory(monkeypatch):
    """A zip over MAX_ZIP_ENTRIES is refused from its end record (classic or ZIP64, or a count that lies and
    the central directory's records counted), without zipfile parsing the records; a ZIP64 zip within the
    limit is read as any other."""
    small = many_entries(3)
    assert len(zipfile.ZipFile(io.BytesIO(as_zip64(small))).namelist()) == 3  # the ZIP64 ending is valid
    assert zip_to_usdz(as_zip64(small), "scene.zip")[1] == "scene.usdz"
    big = many_entries(MAX_ZIP_ENTRIES + 1)
    assert len(zipfile.ZipFile(io.BytesIO(as_zip64(big))).namelist()) == MAX_ZIP_ENTRIES + 1

    def no_parse(*a, **k):
        raise AssertionError("zipfile.ZipFile parsed a zip over the entry limit")

    monkeypatch.setattr(packing.zipfile, "ZipFile", no_parse)
    for data in (big, as_zip64(big), with_declared_count(big, 7), as_zip64(big, declared=7)):
        with pytest.raises(SceneError) as e:
            zip_to_usdz(data, "scene.zip")
        assert e.value.code == "sandbox_limit" and f"limit of {MAX_ZIP_ENTRIES}" in e.value.message


# -- the bare client install zips a folder --------------------------------------------------------------

@pytest.mark.server
def test_the_bare_client_uploads_a_folder_without_numpy_or_usd_core(tmp_path):
    """With numpy and usd-core unimportable (the client install: httpx and pydantic), the client zips a
    folder and sends a stage that would need packing as it is; nothing of the rendering stack is imported."""
    multi_file_stage(tmp_path / "site")
    code = textwrap.dedent(f"""
        import sys
        for m in ("numpy", "pxr", "mitsuba", "drjit", "scipy"):
            sys.modules[m] = None  # import numpy -> ImportError
        import io, zipfile
        from pathlib import Path
        from shadowopt.api.client import scene_bytes
        data, name = scene_bytes(Path({str(tmp_path / 'site')!r}))
        print(name, sorted(zipfile.ZipFile(io.BytesIO(data)).namelist()))
        data, name = scene_bytes(Path({str(tmp_path / 'site' / 'scene.usda')!r}))
        print(name, len(data))
        print(sorted(m for m in sys.modules if m.startswith(("shadowopt.renderers.", "shadowopt.service."))))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == "site.zip ['parts/part.usda', 'scene.usda']"
    assert lines[1] == f"scene.usda {len(ROOT)}" and lines[2] == "[]"


def test_a_folder_with_an_empty_file_and_a_link_out_uploads_without_them(tmp_path):
    """An empty file (a .gitkeep) is left out of the package (usd-core cannot map it; before, the whole zip was
    refused), an empty root layer is refused saying so, and the client's folder zip leaves out symbolic links
    to files and folders outside it."""
    multi_file_stage(tmp_path / "site")
    (tmp_path / "site" / "parts" / ".gitkeep").write_bytes(b"")
    (tmp_path / "away").mkdir()
    (tmp_path / "away" / "secret.txt").write_text("PRIVATE")
    os.symlink(tmp_path / "away", tmp_path / "site" / "linked")
    os.symlink(tmp_path / "away" / "secret.txt", tmp_path / "site" / "secret.txt")
    data, name = zip_folder_bytes(tmp_path / "site")
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        assert sorted(z.namelist()) == ["parts/.gitkeep", "parts/part.usda", "scene.usda"]
    usdz, pkg = zip_to_usdz(data, name)
    with zipfile.ZipFile(io.BytesIO(usdz)) as z:
        assert z.namelist() == ["scene.usda", "parts/part.usda"] and pkg == "scene.usdz"
    with pytest.raises(SceneError) as e:
        zip_to_usdz(zip_bytes({"scene.usda": b"", "parts/part.usda": PART.encode()}), "scene.zip")
    assert e.value.code == "empty_stage" and "'scene.usda' is empty" in e.value.message


@pytest.mark.server
def test_server_refuses_a_zip_over_the_entry_limit_with_413(server):
    data = with_declared_count(many_entries(MAX_ZIP_ENTRIES + 1), 7)  # the count lies; the records are counted
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": "scene.zip"}, content=data,
                   headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=60)
    assert r.status_code == 413, r.text
    err = r.json()["error"]
    assert err["code"] == "sandbox_limit" and f"limit of {MAX_ZIP_ENTRIES}" in err["message"] and err["field"] == "file"
