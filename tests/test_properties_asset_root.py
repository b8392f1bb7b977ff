"""The asset root is a folder, not a string prefix.

Independent truth: a path is inside the folder `root` when, after resolving `..` and symlinks, `root` is one
of its ancestor folders (os.path.commonpath([root, path]) == root). A sibling folder whose name merely
starts with the root's name (`assets-private` next to `assets`) is outside: a bare `startswith(root)` check
would let `../assets-private/x.usda` through for the root `.../assets`."""
from __future__ import annotations

import os

import pytest
from pxr import Usd, UsdGeom

from shadowopt.renderers.asset_resolver import check_asset_path, is_inside, resolve_asset_path
from shadowopt.renderers.usd_loader import load_scene

CUBE = '#usda 1.0\n(\n defaultPrim = "{name}"\n metersPerUnit = 1\n)\ndef Cube "{name}" {{\n double size = 1\n}}\n'
SIBLINGS = ("assets-private", "assets2", "assets.bak", "assets_old")


def truly_inside(path: str, root: str) -> bool:
    path, root = os.path.realpath(path), os.path.realpath(root)
    return os.path.commonpath([path, root]) == root


@pytest.fixture
def tree(tmp_path):
    root = tmp_path / "assets"
    (root / "sub").mkdir(parents=True)
    (root / "sub" / "ok.usda").write_text(CUBE.format(name="Ok"))
    for name in SIBLINGS:
        (tmp_path / name).mkdir()
        (tmp_path / name / "x.usda").write_text(CUBE.format(name="Secret"))
    return tmp_path, root


@pytest.mark.parametrize("trailing", ["", os.sep], ids=["root", "root/"])
def test_a_sibling_folder_named_like_the_root_is_outside_it(tree, trailing):
    tmp, root = tree
    root_s = str(root) + trailing
    anchor = str(root / "scene.usda")
    for name in SIBLINGS:
        target = str(tmp / name / "x.usda")
        assert not truly_inside(target, root_s)
        assert is_inside(target, root_s) is False, name
        for asset in (f"../{name}/x.usda", target):  # relative and absolute spellings
            ok, why = check_asset_path(asset, anchor, "local", asset_root=root_s)
            assert not ok and "outside the asset root" in why, (asset, why)
            ident, why = resolve_asset_path(asset, anchor, "local", asset_root=root_s)
            assert ident is None and "outside the asset root" in why, (asset, why)
    # ... while what is inside stays allowed (the check is not simply refusing everything)
    for asset in ("sub/ok.usda", "./sub/../sub/ok.usda", str(root / "sub" / "ok.usda")):
        assert check_asset_path(asset, anchor, "local", asset_root=root_s) == (True, "ok"), asset
        ident, why = resolve_asset_path(asset, anchor, "local", asset_root=root_s)
        assert why == "ok" and ident == str(root / "sub" / "ok.usda")
    assert is_inside(str(root), root_s) and truly_inside(str(root), root_s)


def test_the_loader_does_not_open_a_sibling_folder_named_like_the_root(tree):
    tmp, root = tree
    s = Usd.Stage.CreateNew(str(root / "scene.usda"))
    UsdGeom.SetStageMetersPerUnit(s, 1.0)
    UsdGeom.Cube.Define(s, "/Own")
    s.DefinePrim("/Inside").GetReferences().AddReference("sub/ok.usda")
    for k, name in enumerate(SIBLINGS):
        s.DefinePrim(f"/Sibling{k}").GetReferences().AddReference(f"../{name}/x.usda")
    s.GetRootLayer().Save()
    sc = load_scene(root / "scene.usda", asset_root=str(root))
    assert sorted(sc.geometry.prim_paths) == ["/Inside", "/Own"]
    for name in SIBLINGS:
        assert any(f"../{name}/x.usda" in w and "asset root" in w for w in sc.warnings), (name, sc.warnings)
