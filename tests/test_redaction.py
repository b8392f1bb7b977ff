"""renderers.redaction.PathRedactor: the one redactor of server paths (loader, isolated loads, server)."""
from __future__ import annotations

import os
import sys
import tempfile

from shadowopt.renderers.redaction import PathRedactor


def test_a_root_is_dropped_and_the_scene_relative_rest_kept(tmp_path):
    scene = tmp_path / "scenes" / "0123abcd" / "s1"
    r = PathRedactor([scene], hidden=[])
    assert r.text(f"cannot open @{scene}/sub/x.usda@ at {scene}/x.usda:3:26: bad") == \
        "cannot open @sub/x.usda@ at x.usda:3:26: bad"
    assert r.text(f"{scene}/a.usdz[inner/b.usda] failed") == "a.usdz[inner/b.usda] failed"
    assert r.text(f"file://{scene}/x.usda") == "x.usda"
    assert r.text(f"the folder {scene} is empty") == "the folder . is empty"
    # whole components only: a sibling folder sharing the prefix is not the root
    assert r.text(f"{scene}x/y.usda") == "y.usda"  # (cut by the file rule, not kept as 'x/y.usda')
    assert r.text(f"{scene}-old/notes") == f"{scene}-old/notes"


def test_a_hidden_folder_is_cut_to_base_names_so_the_storage_layout_does_not_show(tmp_path):
    data = tmp_path / "data"
    r = PathRedactor(hidden=[data])
    stored = data / "scenes" / "0123456789abcdef" / "fedcba9876543210"
    assert r.text(f"@{stored}/x.usda@ failed") == "@x.usda@ failed"
    assert r.text(f"cannot list {stored}") == "cannot list fedcba9876543210"
    assert r.text(f"{data} is full") == "data is full"
    assert "scenes/" not in r.text(f"{stored}/y")


def test_default_server_folders_and_any_absolute_file_path():
    r = PathRedactor()
    venv = f"{sys.prefix}/lib/python3.12/site-packages/pxr/Usd/__init__.py"
    assert r.text(f"see {venv}:12") == "see __init__.py:12"
    assert r.text(f"{tempfile.gettempdir()}/pytest-of-x/t0/y") == "y"
    assert r.text(f"{os.getcwd()}/configs/some_folder") == "some_folder"
    # any absolute path ending in a file name, anywhere
    assert r.text("references @/srv/elsewhere/bob/secret.usdc@ refused") == "references @secret.usdc@ refused"
    assert r.text("file:///srv/x/y.usda") == "y.usda"


def test_what_is_not_a_server_path_is_left_alone():
    r = PathRedactor(["/srv/scene"])
    for s in ("prim </World/Geo/Mesh> has no points", "attribute /World/Mesh.points is empty",
              "/usr/share/doc stays", "relative/x.usda stays", "a ratio 1/2 and a date 2026/12/01", "",
              "no slash at all"):
        assert r.text(s) == s, s


def test_a_folder_matches_only_as_a_whole_component_at_the_start_of_a_path(tmp_path):
    base = tmp_path / "tmpx"
    r = PathRedactor(hidden=[base])
    assert r.text(f"{base}files/a") == f"{base}files/a"  # another folder whose name starts the same
    assert r.text(f"/mirror{base}/a") == f"/mirror{base}/a"  # the folder inside another path


def test_symlinked_and_relative_folders_are_matched_as_given_and_resolved(tmp_path, monkeypatch):
    real = tmp_path / "real"
    (real / "scenes").mkdir(parents=True)
    link = tmp_path / "link"
    link.symlink_to(real)
    r = PathRedactor(hidden=[link])
    assert r.text(f"{real}/scenes/x.bin and {link}/scenes/y.bin") == "x.bin and y.bin"
    monkeypatch.chdir(tmp_path)
    r = PathRedactor(hidden=["real/scenes"])
    assert r.text("cannot read real/scenes/abc/x.bin") == "cannot read x.bin"
    assert r.text(f"cannot read {real}/scenes/abc/x.bin") == "cannot read x.bin"


def test_longest_folder_wins_and_a_root_inside_a_hidden_folder_stays_relative(tmp_path):
    data = tmp_path / "data"
    scene = data / "scenes" / "t" / "s"
    r = PathRedactor([scene], hidden=[data])
    assert r.text(f"{scene}/sub/a.usda vs {data}/scenes/t/other/b.usda") == "sub/a.usda vs b.usda"


def test_redacting_twice_is_redacting_once(tmp_path):
    r = PathRedactor([tmp_path / "s"], hidden=[tmp_path])
    for s in (f"{tmp_path}/s/sub/a.usda:3", f"@{tmp_path}/x/y.usdz[e/l.usda]@", f"{sys.prefix}/lib/z.so", "/abs/q.usdc"):
        once = r.text(s)
        assert r.text(once) == once
        assert str(tmp_path) not in once and sys.prefix not in once


def test_add_registers_a_folder_later(tmp_path):
    r = PathRedactor(hidden=[])
    assert r.text(f"{tmp_path}/store/abc") == f"{tmp_path}/store/abc"
    r.add(tmp_path)
    assert r.text(f"{tmp_path}/store/abc") == "abc"
    r.add(tmp_path / "store", relative=True)
    assert r.text(f"{tmp_path}/store/abc") == "abc" and r.text(f"{tmp_path}/store/d/e") == "d/e"


def test_anonymous_layer_identifiers_and_heap_addresses_never_reach_a_message():
    """The leak an attacker found: "Duplicate item 'anon:0x55a6175187e0:root.usda.checked.usda' not
    allowed for field 'subLayers'" (a process pointer and the loader's internal layer name)."""
    r = PathRedactor(hidden=[])
    msg = "Duplicate item 'anon:0x55a6175187e0:root.usda.checked.usda' not allowed for field 'subLayers' on </>"
    out = r.text(msg)
    assert out == "Duplicate item 'root.usda' not allowed for field 'subLayers' on </>"
    assert r.text("@anon:0x7f00aa:sub/b.usda@ and anon:0xdeadbeef00: and anon:0x1:") == \
        "@sub/b.usda@ and an anonymous layer and an anonymous layer"
    assert r.text("stage @x.usda@ <0x55a6175187e0> at 0x55a6175187e0 failed") == \
        "stage @x.usda@ <address> at <address> failed"
    # short hex values are data, not pointers; a prim path with 0x in a name is left alone
    assert r.text("flags 0xff, id 0x1234abcd, </World/box0x55a6175187e0>") == \
        "flags 0xff, id 0x1234abcd, </World/box0x55a6175187e0>"
    assert r.text(out) == out and r.text(r.text(msg)) == out


def test_only_the_temp_dir_is_hidden_one_level_below_root():
    import tempfile

    from shadowopt.renderers.redaction import PathRedactor

    tmp = tempfile.gettempdir().rstrip("/")
    # "/home" and "/srv" sort before "/tmp": a folder one level below / is never hidden, whatever its name
    r = PathRedactor(hidden=["/home", "/srv", "/aaa", tmp])
    assert r.text("see /home/alice/notes and /srv/x/y and /aaa/b/c") == "see /home/alice/notes and /srv/x/y and /aaa/b/c"
    assert r.text(f"at {tmp}/abc/def") == "at def"
    assert PathRedactor(hidden=["/home/alice"]).text("see /home/alice/notes") == "see notes"  # two levels: hidden


def test_a_relative_root_is_matched_as_written_only_with_two_components_or_more():
    from shadowopt.renderers.redaction import PathRedactor

    assert PathRedactor(roots=["out/data"], hidden=[]).text("at out/data/x.usda") == "at x.usda"
    # a one-word relative folder ("data") would cut the word wherever it appears: only its absolute form counts
    assert PathRedactor(roots=["data"], hidden=[]).text("at data/y.usda") == "at data/y.usda"
    assert PathRedactor(roots=["./data"], hidden=[]).text("at data/y.usda") == "at data/y.usda"
