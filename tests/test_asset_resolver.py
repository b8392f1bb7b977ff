"""Asset resolution in both modes: the CLI's local files and the service's sandboxed uploads."""
from __future__ import annotations

import os
import random
import zipfile

import pytest
from pxr import Usd, UsdGeom

from shadowopt.renderers.asset_resolver import (check_asset_path, is_unsafe_entry_name, join_inside,
                                                resolve_asset_path, unsafe_usdz_entries)
from shadowopt.renderers.scene_data import SceneError
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
    ok, why = check_asset_path('`"${X}.usda"`', anchor, "local", asset_root=str(tmp_path))
    assert not ok and "expression" in why
    arc = str(tmp_path / "up.usdz")
    assert check_asset_path("geo/x.usda", arc + "[root.usda]", "sandbox", archive=arc)[0]
    assert check_asset_path("../x.usda", arc + "[geo/root.usda]", "sandbox", archive=arc)[0]  # still inside
    for name, bad in [("a/b.usda", False), ("../a.usda", True), ("/abs.usda", True), ("a/../../b", True),
                      ("C:/x.usda", True), ("..", True), ("..foo.usda", False)]:
        assert is_unsafe_entry_name(name) is bad, name
    for bad, reason in [("/etc/passwd", "absolute"), ("../evil.usda", "leaves"), ("geo/../../e.usda", "leaves"),
                        ("http://host/x.usda", "URL"), ('`"${X}.usda"`', "expression"),
                        ("C:/Windows/x.usda", "URL"), ("sub/x.usdz[y.usda]", "package")]:
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
    up = tmp_path / "upload"
    up.mkdir()
    (tmp_path / "poison.usda").write_text(POISON)
    (tmp_path / "outside.usda").write_text(CUBE.format(name="Outside"))
    (up / "sibling.usda").write_text(CUBE.format(name="Sibling"))
    (up / "payload.usda").write_text(CUBE.format(name="Payload"))
    scene = scene_with_refs(up / "scene.usda", ["./sibling.usda", "../poison.usda", "../outside.usda",
                                                 str(tmp_path / "outside.usda"), "/etc/passwd"])
    stage = Usd.Stage.Open(str(scene))
    stage.GetRootLayer().subLayerPaths.append("../outside.usda")
    stage.DefinePrim("/Pay").GetPayloads().AddPayload("./payload.usda")
    stage.GetRootLayer().Save()
    del stage
    sc = load_scene(scene, sandbox=True)
    assert sc.geometry.prim_paths == ["/Own"]  # none of the other files' geometry
    text = " | ".join(sc.warnings)
    for name in ("./sibling.usda", "../poison.usda", "../outside.usda", "/etc/passwd", "./payload.usda"):
        assert f"@{name}@" in text, name
    assert "was not read" in text and "parse error" not in text  # the poisoned layer was never opened
    # Control: without the sandbox the same file does read them (and chokes on the poison).
    free = load_scene(scene)
    assert {"/Ref0", "/Ref2", "/Ref3", "/Outside", "/Pay"} <= set(free.geometry.prim_paths)
    assert any("parse error" in w for w in free.warnings)


CLIP_SCENE = """#usda 1.0
(
 metersPerUnit = 1
 expressionVariables = { string WHICH = "../poison" }
)
def Mesh "C" (
  clips = {
    dictionary default = {
      asset[] assetPaths = [@./clip.usda@]
      string primPath = "/C"
      double2[] active = [(0, 0)]
    }
  }
) {
  int[] faceVertexCounts = [3]
  int[] faceVertexIndices = [0,1,2]
}
def Cube "Own" {
  double size = 1
}
def "Expr" (
  references = @`"${WHICH}.usda"`@
) {
}
"""


def test_sandbox_refuses_value_clips_and_variable_expressions(tmp_path):
    d = tmp_path / "scene"
    d.mkdir()
    (d / "clip.usda").write_text(
        '#usda 1.0\ndef Mesh "C" {\n point3f[] points.timeSamples = { 0: [(0,0,0),(9,0,0),(0,9,0)] }\n}\n')
    (d / "scene.usda").write_text(CLIP_SCENE)
    (tmp_path / "poison.usda").write_text(CUBE.format(name="Poison"))
    free = load_scene(d / "scene.usda", time_code=0)
    assert free.geometry.bounds()[1][0] == pytest.approx(9.0)  # control: the clip supplies the points
    assert "/Expr" in free.geometry.prim_paths  # and the expression reaches ../poison.usda
    sc = load_scene(d / "scene.usda", time_code=0, sandbox=True)
    assert sc.geometry.prim_paths == ["/Own"]  # /C has no points of its own: they were in the clip
    text = " | ".join(sc.warnings)
    assert "clip.usda" in text and "value clip" in text and "variable expression" in text
    # with an asset root, the clip inside it is read but the expression is refused
    rooted = load_scene(d / "scene.usda", time_code=0, asset_root=str(d))
    assert rooted.geometry.bounds()[1][0] == pytest.approx(9.0) and rooted.geometry.prim_paths == ["/C", "/Own"]
    assert any("variable expression" in w for w in rooted.warnings)


def test_asset_root_refuses_outside_folders_on_a_real_asset(usd_assets):
    chess = usd_assets / "full_assets/OpenChessSet/chess_set.usda"
    only_pawn = load_scene(chess, asset_root=str(usd_assets / "full_assets/OpenChessSet/assets/Pawn"))
    assert only_pawn.geometry.prim_paths and all("/Pawn" in p for p in only_pawn.geometry.prim_paths)
    assert any("Bishop.usd" in w and "outside the asset root" in w for w in only_pawn.warnings)
    sub = usd_assets / "test_assets/foundation/stage_composition/subLayer"
    assert load_scene(sub / "sublayer_parent_folder.usda", asset_root=str(sub.parent)).geometry.triangle_count > 0


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


def test_sandboxed_usdz_whose_root_entry_climbs_out_is_refused(tmp_path):
    arc = _usdz(tmp_path / "evil.usdz", {"../root.usda": CUBE.format(name="Box")})
    with pytest.raises(SceneError) as e:
        load_scene(arc, sandbox=True)
    assert e.value.code == "unsafe_archive" and "evil.usdz" in e.value.message


def test_usdz_made_by_usd_itself_loads_in_the_sandbox(tmp_path):
    from pxr import UsdUtils

    (tmp_path / "geo").mkdir()
    (tmp_path / "geo" / "box.usda").write_text(CUBE.format(name="Box"))
    scene_with_refs(tmp_path / "main.usda", ["./geo/box.usda"])
    assert UsdUtils.CreateNewUsdzPackage(str(tmp_path / "main.usda"), str(tmp_path / "pkg.usdz"))
    sc = load_scene(tmp_path / "pkg.usdz", sandbox=True)
    assert sorted(sc.geometry.prim_paths) == ["/Own", "/Ref0"]
    assert not any("refused" in w for w in sc.warnings)


def test_join_inside_is_the_one_check_that_a_path_stays_in_an_archive():
    from shadowopt.renderers.asset_resolver import is_unsafe_entry_name, join_inside

    assert join_inside("a/b", "../c.usda") == "a/c.usda"
    assert join_inside("a", "..\\..\\x.usda") is None  # backslashes read as slashes
    assert join_inside("", "../x.usda") is None and join_inside("a/b", "../../..") is None
    assert join_inside("", "/etc/x.usda") is None and join_inside("a", "./b/./c.usda") == "a/b/c.usda"
    assert is_unsafe_entry_name("a/../../x.usda") and not is_unsafe_entry_name("a/../x.usda")


def stay_inside(folder: str, rel: str) -> str | None:
    """Independent model of joining `rel` to `folder` inside an archive: walk the components, '..' pops one and
    may not climb above the top, an absolute `rel` leaves; the top itself is '.'."""
    rel = rel.replace("\\", "/")
    if rel.startswith("/"):
        return None
    stack: list[str] = []
    for part in folder.split("/") + rel.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not stack:
                return None
            stack.pop()
        else:
            stack.append(part)
    return "/".join(stack) or "."


def test_join_inside_agrees_with_a_component_walk_on_random_paths():
    # names sorting before '..' ('-x', '+y', '!') and the archive's top ('.') are ordinary results, not escapes
    parts = ["a", "b", "..", ".", "-x.usda", "+y", "!", "c.usda", ""]
    rng = random.Random(15)
    cases = [("a", ".."), ("", "-x.usda"), ("", "+y/../!"), ("a/b", "../.."), ("", "a/.."), ("a", "..\\..")]
    for _ in range(3000):
        folder = "/".join(rng.choice(["a", "b", "-x"]) for _ in range(rng.randrange(0, 3)))
        rel = "/".join(rng.choice(parts) for _ in range(rng.randrange(1, 5)))
        cases.append((folder, rel))
    for folder, rel in cases:
        assert join_inside(folder, rel) == stay_inside(folder, rel), (folder, rel)
    assert join_inside("a", "..") == "." and join_inside("", "-x.usda") == "-x.usda"
    assert not is_unsafe_entry_name("-x.usda") and not is_unsafe_entry_name("!/a.usda")


@pytest.mark.parametrize("bad, reason", [("", "empty asset path"), ("a\x00.usda", "NUL"),
                                         ("anon:0x7f00:layer.usda", "anonymous")])
def test_every_refusal_says_no(tmp_path, bad, reason):
    # check_asset_path's refusals are refusals in every restricted mode (ok is False, whatever the reason)
    root = str(tmp_path)
    arc = str(tmp_path / "up.usdz")
    for args in ((bad, str(tmp_path / "s.usda"), "local", root),
                 (bad, f"{arc}[root.usda]", "sandbox", None, arc)):
        ok, why = check_asset_path(*args)
        assert ok is False and reason in why, (args, why)
        ident, why = resolve_asset_path(*args)
        assert ident is None and reason in why


def test_resolve_is_only_for_the_restricted_modes(tmp_path):
    with pytest.raises(ValueError, match="restricted modes"):
        resolve_asset_path("x.usda", str(tmp_path / "s.usda"), "local")


def _cases(tmp_path):
    """(arguments, expected result) of resolve_asset_path for a table written out by hand: anchors in and out of
    packages, both modes; identifiers are the absolute normalised layer paths (package[entry])."""
    root = tmp_path / "assets"
    root.mkdir(exist_ok=True)
    r = str(root)
    arc = str(tmp_path / "up.usdz")
    # two packages that sort before and after the uploaded archive's path
    before, after = str(tmp_path / "a-other.usdz"), str(tmp_path / "zz-other.usdz")
    entries = {"scene/root.usda", "scene/parts/chair.usda"}
    return [
        # local mode with an asset root, anchor inside a package inside the root: another entry of that package
        (("parts/c.usda", f"{r}/pkg.usdz[scene/root.usda]", "local", r), (f"{r}/pkg.usdz[scene/parts/c.usda]", "ok")),
        (("../x.usda", f"{r}/d/e/pkg.usdz[root.usda]", "local", r), (None, "'../x.usda' leaves the package 'pkg.usdz'")),
        # ... and a package outside the root is refused even for its own entries
        (("parts/c.usda", f"{tmp_path}/pkg.usdz[scene/root.usda]", "local", r),
         (None, f"'parts/c.usda' resolves outside the asset root {r!r}")),
        # local mode, plain anchor, a path naming an entry of a package
        (("sub/p.usdz[a/./b.usda]", f"{r}/s.usda", "local", r), (f"{r}/sub/p.usdz[a/b.usda]", "ok")),
        (("sub/p.usdz[../x.usda]", f"{r}/s.usda", "local", r),
         (None, "'sub/p.usdz[../x.usda]' leaves the package it names")),
        (("sub/x.usda", f"{r}/s.usda", "local", r), (f"{r}/sub/x.usda", "ok")),
        # sandbox: an entry of the uploaded archive only
        (("parts/chair.usda", f"{arc}[scene/root.usda]", "sandbox", None, arc, entries),
         (f"{arc}[scene/parts/chair.usda]", "ok")),
        (("parts/chair.usda", f"{before}[scene/root.usda]", "sandbox", None, arc, entries),
         (None, "'parts/chair.usda' is not inside the uploaded archive")),
        (("parts/chair.usda", f"{after}[scene/root.usda]", "sandbox", None, arc, entries),
         (None, "'parts/chair.usda' is not inside the uploaded archive")),
        # sandbox, a layer outside any package (the archive given): names nothing
        (("x.usda", str(tmp_path / "s.usda"), "sandbox", None, arc),
         (None, "'x.usda': only entries of the uploaded archive may be opened")),
    ]


def test_resolution_table(tmp_path):
    for args, want in _cases(tmp_path):
        assert resolve_asset_path(*args) == want, args


def test_the_mode_is_compared_by_value(tmp_path):
    # a mode read at run time (a config file, a request) is a new string object: the decisions are the same
    def fresh(s: str) -> str:
        return "".join(list(s))

    assert fresh("local") is not "local"  # noqa: F632 (the point of the test)
    for args, want in _cases(tmp_path):
        args = args[:2] + (fresh(args[2]),) + args[3:]
        assert resolve_asset_path(*args) == want, args
    anchor = str(tmp_path / "assets" / "s.usda")
    assert check_asset_path("../x.usda", anchor, fresh("local")) == (True, "ok")  # no root: anything goes
    ok, why = check_asset_path("../x.usda", anchor, fresh("local"), asset_root=str(tmp_path / "assets"))
    assert not ok and "outside the asset root" in why
    with pytest.raises(ValueError, match="restricted modes"):
        resolve_asset_path("x.usda", anchor, fresh("local"))


def test_sandboxed_package_entry_must_be_one_of_the_archives_entries(tmp_path):
    # a layer inside the uploaded archive may name another entry of it, and only an entry the archive has
    arc = str(tmp_path / "up.usdz")
    anchor = f"{arc}[scene/root.usda]"
    entries = {"scene/root.usda", "scene/parts/chair.usda"}
    ident, why = resolve_asset_path("parts/chair.usda", anchor, "sandbox", archive=arc, entries=entries)
    assert (ident, why) == (f"{os.path.normpath(arc)}[scene/parts/chair.usda]", "ok")
    ident, why = resolve_asset_path("parts/table.usda", anchor, "sandbox", archive=arc, entries=entries)
    assert ident is None and why == "'parts/table.usda': the archive has no entry 'scene/parts/table.usda'"
    # without an entry list (the archive not listed yet) the path is joined inside the package
    ident, why = resolve_asset_path("parts/table.usda", anchor, "sandbox", archive=arc)
    assert why == "ok" and ident.endswith("[scene/parts/table.usda]")
