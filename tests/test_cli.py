"""The `shadowopt` command line, run as a user runs it (a subprocess of the installed script: `run`); the refusals
that come before any work, the commands a test runs several times to compare their answers and the benchmarks run
in process (`run_here`: the answers are the point, and a process start costs ~5 s: tests/clikit.py)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from clikit import run, run_here

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo_scene.usda"
DEMO_RIG = REPO / "configs" / "demo_rig.json"


@pytest.mark.server
def test_scene_info_json_on_the_demo_scene():
    info = json.loads(run("scene-info", DEMO, "--json", check=0).stdout)
    assert info["triangles"] > 1000 and info["warnings"] == []
    assert [c["usd_path"] for c in info["cameras"]] == ["/World/Camera"]
    assert info["lights"][0]["usd_path"] == "/World/Sun" and info["lights"][0]["type"] == "directional"
    assert info["cameras"][0]["position"] == pytest.approx([0, 1.7, 0])  # eye height
    assert info["frame"]["world"].startswith("right-handed, +Y up, meters")


@pytest.mark.server
def test_coarse_writes_buffers_and_previews(tmp_path):
    out = tmp_path / "buffers"
    summary = json.loads(run("coarse", DEMO, "--rig", DEMO_RIG, "--out", out, "--json", check=0).stdout)
    assert (summary["width"], summary["height"]) == (180, 101)  # the rig's 1280x720 aspect at 180 px
    hit = np.load(out / "hit.npy")
    pos = np.load(out / "position.npy")
    assert hit.shape == (101, 180) and pos.shape == (101, 180, 3)
    assert np.allclose(pos[hit][:, 1].min(), 0.0, atol=1e-3)  # the ground is y = 0
    assert summary["lights"][0]["boundary_pixels"] == int(np.load(out / "light0_boundary.npy").sum()) > 0
    for png in ("depth.png", "normal.png", "light0_lit.png"):
        assert (out / png).stat().st_size > 100


def test_cli_flags_override_the_rig_and_bad_flags_exit_2(tmp_path, capsys):
    p = run_here(capsys, "coarse", DEMO, "--rig", DEMO_RIG, "--out", tmp_path, "--cascades", "x", check=2)
    assert "--cascades" in p.stderr and "Traceback" not in p.stderr
    p = run_here(capsys, "coarse", DEMO, "--rig", DEMO_RIG, "--out", tmp_path, "--lambda", "2", check=2)
    assert "shadow.lambda" in p.stderr


@pytest.mark.parametrize("content, words", [
    ("not json", "not valid JSON"),
    ('{"camera": {"position": [0, 1, 0], "target": [0, 0, 5]}, "lights": [{"type": "sun"}]}', "lights.0.type"),
    ('{"camera": {"usd_path": "/World/NoCam"}, "lights": [{"usd_path": "/World/Sun"}]}', "camera.usd_path"),
    ('{"camera": {"usd_path": "/World/Camera", "target": [0, 0, 5]}, "lights": [{"usd_path": "/World/Sun"}]}',
     "camera: target and forward need a position"),
])
def test_bad_rigs_exit_2_naming_the_field(tmp_path, capsys, content, words):
    rig = tmp_path / "rig.json"
    rig.write_text(content)
    p = run_here(capsys, "coarse", DEMO, "--rig", rig, "--out", tmp_path / "o", check=2)
    assert words in p.stderr and "Traceback" not in p.stderr


def test_malformed_scene_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.usdc"
    bad.write_bytes(b"PXR-USDC" + b"\0" * 40)
    p = run_here(capsys, "scene-info", bad, check=2)
    assert "bad.usdc" in p.stderr and "[corrupt]" in p.stderr and "Traceback" not in p.stderr
    p = run_here(capsys, "scene-info", tmp_path / "missing.usda", check=2)
    assert "No such file" in p.stderr and "[not_found]" in p.stderr


def test_bench_coarse_json_on_the_demo_scene(capsys):
    res = json.loads(run_here(capsys, "bench", "coarse", "--scenes", "demo", "--runs", "3", "--no-write", "--json", check=0).stdout)
    demo = res["scenes"]["demo"]
    assert demo["triangles"] > 1000 and demo["runs"] == 3 and demo["coarse_ms_p50"] > 0
    assert "| demo |" in res["table"]


def test_demo_scene_is_what_the_generator_writes(tmp_path):
    from shadowopt.renderers.demo_scene import write_demo_scene

    out = tmp_path / "demo.usda"
    write_demo_scene(str(out))
    assert out.read_text() == DEMO.read_text()


CASCADE_FIELDS = {"split", "light_depth", "view_matrix", "projection_matrix", "texture_matrix", "resolution",
                  "warp", "depth_bias", "predicted_error"}
ERROR_FIELDS = {"objective", "mean_m", "median_m", "p95_m", "max_m", "frac_m_gt_1", "samples"}


@pytest.mark.parametrize("method", ["uniform", "focused", "lispsm", "logpsm"])
def test_optimize_writes_the_solution_schema_and_evaluate_reads_it(tmp_path, method, capsys):
    sol_path = tmp_path / "sol.json"
    sol = json.loads(run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--method", method, "--shadow-resolution", "512x512",
                         "--out", sol_path, "--json", check=0).stdout)
    assert json.loads(sol_path.read_text()) == sol
    cas = sol["lights"][0]["cascades"][0]
    assert CASCADE_FIELDS <= set(cas) and ERROR_FIELDS <= set(cas["predicted_error"])
    assert len(cas["view_matrix"]) == 16 and cas["resolution"] == [512, 512]
    assert cas["warp"]["kind"] in ("none", "perspective", "log")
    assert {"coarse", "optimize", "total"} <= set(sol["timings_ms"])
    assert sol["provenance"]["scene_hash"] and sol["provenance"]["software"].startswith("shadowopt")
    heat = tmp_path / "heat.png"
    ev = json.loads(run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, "--screen", "320x180",
                        "--heatmap", heat, "--json", check=0).stdout)
    assert ev["outside_pixels"] == 0 and ev["receiver_pixels"] > 10000
    assert {"mean_m", "median_m", "p95_m", "max_m", "frac_m_gt_1", "samples"} <= set(ev["measured_error"])
    assert heat.stat().st_size > 1000


def test_evaluate_refuses_a_solution_for_another_scene(tmp_path, capsys):
    sol_path = tmp_path / "sol.json"
    run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--out", sol_path, check=0)
    sol = json.loads(sol_path.read_text())
    sol["provenance"]["scene_hash"] = "0" * 64
    sol_path.write_text(json.dumps(sol))
    p = run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, check=2)
    assert "scene_hash" in p.stderr and "another scene" in p.stderr
    sol_path.write_text("{}")
    p = run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, check=2)
    assert "not a shadowopt solution" in p.stderr


def bench_json(capsys, *args) -> dict:
    """`shadowopt bench ... --no-write --json` in process (`main(argv)`, what the installed script calls): the
    benchmark's figures are the point, not the process boundary, which the other commands' tests cross."""
    from shadowopt.api.cli import main

    capsys.readouterr()
    code = main(["bench", *args, "--no-write", "--json"])
    out = capsys.readouterr()
    assert code == 0, (code, out.err[-3000:])
    return json.loads(out.out)


@pytest.mark.slow
def test_bench_quality_json_small_run(capsys):
    res = bench_json(capsys, "quality", "--lights", "2", "--part", "single")
    assert res["lights"] == 2 and set(res["totals"]["single"]) == {"uniform", "focused", "lispsm", "logpsm", "optimized"}
    assert all(len(v) == 2 for v in res["misclassified"]["single"].values())
    assert res["totals"]["single"]["uniform"] > res["totals"]["single"]["lispsm"]  # the classic ordering holds on the demo


def test_hemisphere_directions_point_down_above_the_elevation():
    from shadowopt.service.bench.definitions import hemisphere_directions

    d = hemisphere_directions(500, 5.0, 1)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.all(-d[:, 1] >= np.sin(np.radians(5.0)) - 1e-12)
    assert abs(np.mean(-d[:, 1]) - (1 + np.sin(np.radians(5))) / 2) < 0.05  # uniform in height


@pytest.mark.slow
def test_bench_trust_ranks_configurations_as_measured(capsys):
    res = bench_json(capsys, "trust", "--lights", "2")
    assert len(res["rigs"]) == 2 and len(res["configurations"]) == 15
    # predicted objective and measured misclassified pixels rank the 15 configurations alike
    assert res["mean_within_rig_spearman"] >= 0.8, [r["spearman"] for r in res["rigs"]]


def _coloured(png: Path, w: int, h: int) -> tuple[int, int]:
    from PIL import Image

    from shadowopt.renderers.heatmap import WRONGLY_LIT, WRONGLY_SHADOWED

    img = np.asarray(Image.open(png).convert("RGB")).astype(int)[:h, :w]  # the picture; the legend is below
    return tuple(int(np.all(img == np.array(c), axis=-1).sum()) for c in (WRONGLY_SHADOWED, WRONGLY_LIT))


def test_evaluate_errors_heatmap_and_a_bad_mode(tmp_path, capsys):
    sol_path, heat = tmp_path / "sol.json", tmp_path / "errors.png"
    run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--method", "lispsm", "--shadow-resolution", "128x128", "--out", sol_path,
        check=0)
    ev = json.loads(run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, "--screen", "320x180",
                        "--heatmap", heat, "--heatmap-mode", "errors", "--json", check=0).stdout)
    shadowed, lit = _coloured(heat, 320, 180)
    assert shadowed > 0 and lit > 0 and shadowed + lit == ev["misclassified_pixels"]
    assert (shadowed, lit) == (ev["wrongly_shadowed_pixels"], ev["wrongly_lit_pixels"])
    assert ev["screen"] == [320, 180] and ev["rig_resolution"] == [1280, 720]
    text = run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, "--screen", "320x180", check=0).stdout
    assert f"wrongly shadowed {shadowed}, wrongly lit {lit}" in text and "at the 320x180 screen" in text
    assert "in 320x180 pixels" in text and "in the rig's 1280x720 pixels" in text
    p = run_here(capsys, "evaluate", DEMO, "--rig", DEMO_RIG, "--solution", sol_path, "--heatmap", heat, "--heatmap-mode", "aliasing",
            check=2)
    assert "--heatmap-mode" in p.stderr and "errors" in p.stderr and "Traceback" not in p.stderr


def test_compare_with_a_screen_predicts_exactly_what_optimize_predicts(tmp_path, capsys):
    """The predicted error is in the rig's own pixels whatever --screen the evaluation uses (issue 10, item 6)."""
    res = json.loads(run_here(capsys, "compare", DEMO, "--rig", DEMO_RIG, "--methods", "lispsm,optimized", "--screen", "320x180",
                         "--json", check=0).stdout)
    assert res["screen"] == [320, 180] and res["rig_resolution"] == [1280, 720]
    for name, r in res["methods"].items():
        sol = json.loads(run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--method", name, "--json", check=0).stdout)
        assert r["predicted_error"] == sol["lights"][0]["predicted_error"], name
        assert r["evaluation"]["screen"] == [320, 180] and "320x180 screen's pixels" in r["evaluation"]["pixels"]
    table = run_here(capsys, "compare", DEMO, "--rig", DEMO_RIG, "--methods", "lispsm", "--screen", "320x180", check=0).stdout
    assert "predicted p95 m (1280x720)" in table and "measured p95 m (320x180)" in table
    assert "misclassified (320x180)" in table


def _readme_block(heading: str) -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text[text.index(heading):]
    block = section[section.index("```sh\n") + 6:]
    return [line for line in block[:block.index("```")].splitlines() if line.strip()]


@pytest.mark.server
@pytest.mark.slow
def test_the_readme_heatmap_example_runs_verbatim(tmp_path):
    """The README's heatmap example, line by line, in a scratch folder (configs/ linked in, so its outputs
    land in the scratch out/), with .venv/bin/shadowopt being this environment's script."""
    import shlex

    lines = _readme_block("### Heatmaps: what went wrong")
    assert len(lines) == 3 and all(line.startswith(".venv/bin/shadowopt ") for line in lines)
    (tmp_path / "configs").symlink_to(REPO / "configs")
    exe = Path(sys.executable).with_name("shadowopt")
    outs = []
    for line in lines:
        p = subprocess.run([str(exe), *shlex.split(line)[1:]], capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert p.returncode == 0, (line, p.stdout, p.stderr)
        outs.append(p.stdout)
    assert "wrongly shadowed" in outs[1] and "in the rig's 1280x720 pixels" in outs[1]
    assert (tmp_path / "out" / "lispsm256_errors.png").stat().st_size > 1000
    assert {"heatmaps.png", "errors.png", "compare.md"} <= {f.name for f in (tmp_path / "out" / "compare256").iterdir()}


def _strict_json(text: str):
    """json.loads refusing NaN, Infinity and -Infinity (standard JSON, RFC 8259, has none)."""
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def test_cli_json_is_standard_json_with_null_for_an_infinite_candidate_score(tmp_path, capsys):
    """issue 25: with 4 cascades on the demo a candidate that leaves a receiver outside its map scores inf,
    and the CLI printed `"uniform": Infinity` (solver.cascades[].receiver_h), which strict parsers refuse.
    stdout and the --out file parse strictly; the score is null, as the schema's `solver` field says."""
    out = tmp_path / "sol.json"
    p = run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--cascades", "4", "--json", "--out", out, check=0)
    sol = _strict_json(p.stdout)
    assert _strict_json(out.read_text()) == sol
    report = sol["solver"].get("lights", [sol["solver"]])[0]  # one light: its report is the solver block
    scores = [v for c in report["cascades"] for key in ("baselines", "receiver_h") for v in (c.get(key) or {}).values()]
    assert None in scores and all(v is None or v >= 0 for v in scores)


def test_compare_accepts_every_method_optimize_accepts(capsys):
    """issue 25: `compare --methods stable_csm` exited 2 ("unknown stable_csm") although optimize accepts it.
    Every choice of `optimize --method` (read from its --help) is accepted by compare; an unknown name still
    exits 2 naming the known ones."""
    help_text = " ".join(run_here(capsys, "optimize", "--help", check=0).stdout.split())
    choices = help_text.split("--method {", 1)[1].split("}", 1)[0].split(",")
    assert {"stable_csm", "path", "optimized"} <= set(choices)
    res = json.loads(run_here(capsys, "compare", DEMO, "--rig", DEMO_RIG, "--methods", "stable_csm,path", "--screen", "160x90",
                         "--shadow-resolution", "256x256", "--cascades", "2", "--json", check=0).stdout)
    assert set(res["methods"]) == {"stable_csm", "path"}
    assert all(r["evaluation"]["receiver_pixels"] > 0 for r in res["methods"].values())
    p = run_here(capsys, "compare", DEMO, "--rig", DEMO_RIG, "--methods", "focused,nosuch", check=2)
    known = p.stderr.split("(known: ", 1)[1].split(")", 1)[0].split(", ")
    assert "nosuch" in p.stderr and sorted(known) == sorted(choices)


def test_stable_csm_honours_optimized_splits(capsys):
    """issue 25: `--method stable_csm --splits optimized` returned the practical splits (the search ran and its
    splits were dropped). Its inner splits are now the split search's: the same ones focused gets from the
    same search (an unwarped map's search), and not the practical ones."""
    def splits(method, kind):
        sol = json.loads(run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, "--method", method, "--cascades", "3", "--splits",
                             kind, "--shadow-resolution", "512x512", "--json", check=0).stdout)
        return [c["split"] for c in sol["lights"][0]["cascades"]]
    practical, searched = splits("stable_csm", "practical"), splits("stable_csm", "optimized")
    inner = [s[1] for s in searched[:-1]]
    assert inner == pytest.approx([s[1] for s in splits("focused", "optimized")[:-1]], rel=1e-9)
    assert not np.allclose(inner, [s[1] for s in practical[:-1]], rtol=0.05)
    assert searched[0][0] == practical[0][0] and searched[-1][1] == practical[-1][1]


@pytest.mark.parametrize("args, flag", [
    (["--method", "focused", "--solver", "nlopt:LN_BOBYQA"], "--solver"),
    (["--method", "lispsm", "--time-budget-ms", "50"], "--time-budget-ms"),
    (["--method", "stable_csm", "--previous", "prev.json"], "--previous"),
    (["--hysteresis", "0.5"], "--hysteresis"),  # optimized without --previous: nothing to keep
    (["--method", "path", "--previous", "prev.json", "--hysteresis", "0.5"], "--hysteresis"),
    (["--method", "lispsm", "--cascades", "2", "--splits", "log", "--lambda", "0.9"], "--lambda"),
])
def test_an_option_the_method_would_ignore_exits_2_naming_it(capsys, args, flag):
    """issue 25: options a method does not read were dropped silently (stable_csm and --splits optimized, a
    baseline and --solver ...); now exit 2 naming the flag and why, before any work."""
    p = run_here(capsys, "optimize", DEMO, "--rig", DEMO_RIG, *args, check=2)
    assert p.stderr.startswith(f"shadowopt: error: {flag}") and "not used by --method" in p.stderr, p.stderr
    assert p.stdout == ""
