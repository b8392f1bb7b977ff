"""Tests written to kill mutants that `make mutate` found surviving (tests/mutation/survivors.md names them)."""
from __future__ import annotations

import os

from shadowopt.renderers.asset_resolver import resolve_asset_path


def test_sandboxed_package_entry_must_be_one_of_the_archives_entries(tmp_path):
    # renderers/asset_resolver.py `entries is not None and joined not in entries` (mutant: `is None`): a layer
    # inside the uploaded archive may name another entry of it, and only an entry the archive has
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
