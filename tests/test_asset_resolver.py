"""Asset resolution in both modes: the CLI's local files and the service's sandboxed uploads."""
from __future__ import annotations

import zipfile

import pytest
from pxr import Usd, UsdGeom

from shadowopt.renderers.asset_resolver import check_asset_path, unsafe_usdz_entries
from shadowopt.renderers.usd_loader import load_scene

# A layer that USD could not parse: if it were ever read, a parse error would appear in the warnings.
POISON = '#usda 1.0\ndef Mesh "Poison" {\n point3f[] points = [(0,0'
CUBE = '#usda 1.0\n(\n defaultPrim = "{name}"\n metersPerUnit = 1\n)\ndef Cube "{name}" {{\n double size = 1\n}}\n'


def scene_with_refs(path, refs):
    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(s, 1.0)
    UsdGeom.Cube.Define(s, "/Own")
    for k, r in enumerate(refs):
        s.DefinePrim(f"/Ref{k}").GetReferences().AddReference(r)
    s.GetRootLayer().Save()
    return path


def test_decisions_are_pure_and_name_the_reason(tmp_path):
    anchor = str(tmp_path / "scene.usda")
    assert check_asset_path("../x.usda", anchor, "local") == (True, "ok")
    ok, why = check_asset_path("../x.usda", anchor, "local", asset_root=str(tmp_path))
    assert not ok and "outside the asset root" in why
    assert check_asset_path("sub/x.usda", anchor, "local", asset_root=str(tmp_path))[0]
    ok, why = check_asset_path("x.usda", anchor, "sandbox")
    assert not ok and "single-file" in why
    arc = str(tmp_path / "up.usdz")
    assert check_asset_path("geo/x.usda", arc + "[root.usda]", "sandbox", archive=arc)[0]
    for bad, reason in [("/etc/passwd", "absolute"), ("../evil.usda", "leaves"), ("geo/../../e.usda", "leaves"),
                        ("http://host/x.usda", "URL")]:
        ok, why = check_asset_path(bad, arc + "[root.usda]", "sandbox", archive=arc)
        assert not ok and reason in why, (bad, why)


def test_local_mode_follows_parent_folders_unless_an_asset_root_says_no(tmp_path):
    (tmp_path / "lib").mkdir()
    (tmp_path / "proj").mkdir()
    (tmp_path / "lib" / "box.usda").write_text(CUBE.format(name="Box"))
    scene = scene_with_refs(tmp_path / "proj" / "scene.usda", ["../lib/box.usda"])
    free = load_scene(scene)
    assert "/Ref0" in free.geometry.prim_paths
    boxed = load_scene(scene, asset_root=str(tmp_path / "proj"))
    assert "/Ref0" not in boxed.geometry.prim_paths and "/Own" in boxed.geometry.prim_paths
    assert any("../lib/box.usda" in w and "asset root" in w for w in boxed.warnings)
    assert load_scene(scene, asset_root=str(tmp_path)).geometry.prim_paths == free.geometry.prim_paths


def test_sandboxed_single_file_opens_nothing_else(tmp_path):
    (tmp_path / "poison.usda").write_text(POISON)
    (tmp_path / "sibling.usda").write_text(CUBE.format(name="Sibling"))
    scene = scene_with_refs(tmp_path / "up" / "scene.usda" if False else tmp_path / "scene.usda",
                            ["./sibling.usda", "../poison.usda", str(tmp_path / "poison.usda")])
    sc = load_scene(scene, sandbox=True)
    assert sc.geometry.prim_paths == ["/Own"]
    text = " | ".join(sc.warnings)
    assert "sibling.usda" in text and "poison.usda" in text and "was not read" in text
    assert "parse error" not in text  # the poisoned layer was never opened
    # Without the sandbox the same file does read its sibling (and chokes on the poison).
    assert "/Ref0" in load_scene(scene).geometry.prim_paths


def _usdz(path, entries: dict[str, str]):
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as z:
        for name, text in entries.items():
            z.writestr(name, text)
    return path


def test_sandboxed_usdz_reads_its_own_entries_only(tmp_path):
    (tmp_path / "poison.usda").write_text(POISON)
    root = ('#usda 1.0\n(\n metersPerUnit = 1\n)\ndef Cube "Own" {\n double size = 1\n}\n'
            'def "Inside" (\n references = @geo/box.usda@\n) {\n}\n'
            'def Xform "Climb" (\n references = @../poison.usda@\n) {\n}\n'
            'def Xform "Abs" (\n references = @' + str(tmp_path / "poison.usda") + '@\n) {\n}\n')
    arc = _usdz(tmp_path / "upload.usdz", {"root.usda": root, "geo/box.usda": CUBE.format(name="Box") .replace(
        'def Cube "Box"', 'def Cube "Box"') + "", "../evil.usda": POISON})
    assert unsafe_usdz_entries(str(arc)) == ["../evil.usda"]
    sc = load_scene(arc, sandbox=True)
    text = " | ".join(sc.warnings)
    assert "/Own" in sc.geometry.prim_paths and "/Inside" in sc.geometry.prim_paths
    assert "/Climb" not in sc.geometry.prim_paths and "/Abs" not in sc.geometry.prim_paths
    assert "unsafe names" in text and "../evil.usda" in text and "parse error" not in text
