"""Tests written to kill the mutants of renderers/, api/ and service/ that `make mutate` (or a scratch run of
cosmic-ray's operators over the same modules) found surviving; each checks a property against an independent
truth, never the implementation's own output. Fast and pure (no Mitsuba, no server): every mutant's run of
this file takes a second or two."""
from __future__ import annotations

import os
import posixpath
import random

import pytest

from shadowopt.renderers.asset_resolver import (check_asset_path, is_unsafe_entry_name, join_inside,
                                                resolve_asset_path)


# --- renderers/asset_resolver.py -------------------------------------------------------------------------

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
