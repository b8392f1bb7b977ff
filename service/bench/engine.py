"""The engine benchmark: what an engine gets when it pastes docs/engine-integration.md's listings.

Per scene and cascade count, one optimized solution; its maps rendered by the document's GLSL and HLSL in
Mesa's OpenGL (renderers.gl_listing, in a subprocess) in the opengl convention, the d3d convention
(glClipControl) and d3d with reversed_z; every pixel's shadow compared with exact ray-traced visibility
(renderers.ground_truth.render_screen's `visible` over its receivers). Beside it, `evaluate --depth`
(solution, hardware, linear) and the idealized `--depth ideal` for the same solution. Each light pass sets
the document's rasterizer-state block (light_pass_api: OpenGL's for the GLSL, Direct3D 11's for the HLSL,
Vulkan's in the vulkan convention) with the map's caster-side slope-scaled bias.

The same functions serve tests/test_engine_listing.py (`solve_for_listing`, `listing_wrong_pixels`).
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ...renderers.ground_truth import evaluate_buffers, screen_camera
from ..pipeline import scene_entry
from ..rigs import resolve_rig
from ..request import SolveRequest
from ..solution_json import maps_from_solution
from ..solve import solve
from .definitions import corpus_scenes
from .output import write_section

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "engine-integration.md"
MCUSD = ROOT.parent / "shared" / "usd-assets" / "full_assets" / "McUsd" / "McUsd.usda"
CONVENTIONS = {"opengl": ("opengl", False), "d3d": ("d3d", False), "vulkan": ("vulkan", False),
               "reversed_z": ("d3d", True)}
LANGUAGES = ("glsl", "hlsl")
ENGINE_MODES = ("solution", "hardware", "linear")  # evaluate --depth choices an engine can follow
# Corpus scenes with a sun of their own here (the corpus rigs give only a camera).
CORPUS_SUNS = {"street_canyon": [-0.45, -0.8, 0.4], "terrain": [0.55, -0.6, 0.35]}


def listings(text: str | None = None) -> dict:
    """{language: {piece: source}} from the document's fenced blocks tagged ```<language> <piece>```,
    verbatim (glsl, hlsl, and c for the light pass's rasterizer-state blocks)."""
    text = DOC.read_text() if text is None else text
    out: dict = {}
    for lang, piece, body in re.findall(r"^```(glsl|hlsl|c) ([a-z0-9-]+)\n(.*?)^```\s*$", text, re.M | re.S):
        if piece in out.setdefault(lang, {}):
            raise ValueError(f"the document has two ```{lang} {piece}``` blocks")
        out[lang][piece] = body
    return out


# The caster offset in the document's pieces: (language, piece, text, replacement) that removes it.
CASTER_OFFSET = (
    ("c", "light-pass-state-gl", "glPolygonOffsetClamp(reversedZ ? -k : k, 0.0f, reversedZ ? -m : m);\n", ""),
    ("c", "light-pass-state-d3d11", "rs.SlopeScaledDepthBias = reversedZ ? -k : k;\n", ""),
    ("c", "light-pass-state-vulkan", "rs.depthBiasSlopeFactor = reversedZ ? -k : k;\n", ""),
    ("glsl", "light-pass-linear", "d + min(uLinearOffset.x * dz, uLinearOffset.y)", "d"),
    ("hlsl", "light-pass-linear", "d + min(gLinearOffset.x * dz, gLinearOffset.y)", "d"),
)


def replaced(src: dict, lang: str, piece: str, text: str, instead: str = "") -> dict:
    """The listings `src` with `text` (which must occur) replaced in one piece."""
    body = src[lang][piece]
    if text not in body:
        raise ValueError(f"```{lang} {piece}``` no longer contains {text!r}")
    return {**src, lang: dict(src[lang], **{piece: body.replace(text, instead)})}


def without_caster_offset(src: dict) -> dict:
    """The listings with the light pass's slope-scaled offset taken out (the offset call / fields of the state
    blocks, the slope term of the linear light passes): what an engine gets that skips it."""
    for lang, piece, text, instead in CASTER_OFFSET:
        src = replaced(src, lang, piece, text, instead)
    return src


def hlsl_tools() -> str | None:
    """None when glslangValidator and spirv-cross are on the PATH, else what is missing."""
    missing = [t for t in ("glslangValidator", "spirv-cross") if shutil.which(t) is None]
    return None if not missing else (", ".join(missing) + " not found (Debian: apt-get install glslang-tools "
                                                          "spirv-cross)")


def scene_rigs(names=None, screen=None):
    """[(name, scene path, rig without shadow/output)]: McUsd with its own camera and sun (if present), and
    the corpus scenes of CORPUS_SUNS with their rigs' cameras."""
    names = list(names) if names else ["mcusd", *CORPUS_SUNS]
    out, skipped = [], {}
    for name in names:
        if name == "mcusd":
            if not MCUSD.exists():
                skipped[name] = "../shared/usd-assets (McUsd) is absent"
                continue
            cam = {"usd_path": "/McUsd/Camera"}
            if screen:
                cam["resolution"] = list(screen)
            out.append((name, MCUSD, {"camera": cam, "lights": [{"usd_path": "/McUsd/Lights/Sun"}]}))
            continue
        found, skip = corpus_scenes([name])
        skipped.update(skip)
        for _, (path, spec) in found.items():
            cam = dict(next(iter(spec["rigs"].values()))["camera"])
            cam["resolution"] = list(screen or (1280, 720))
            out.append((name, path, {"camera": cam, "lights": [{"type": "directional",
                                                                "direction": CORPUS_SUNS[name]}]}))
    return out, skipped


def solve_for_listing(validate_rig, entry, rig: dict, cascades: int, map_res: int = 1024,
                      depth_override: dict | None = None, cascade_override=None, conventions=CONVENTIONS) -> dict:
    """One optimized solution per convention of `conventions` and opengl (the same maps: asserted), and its maps.
    `depth_override`: {key: value} set in both blocks of every map's `depth` (e.g. a normal offset), in the
    solutions and so in the maps evaluate reads; a callable value is called with the block (e.g. a scaled
    constant). `cascade_override`: a function called with each solution's list of cascades (to change e.g.
    their blend bands), before the maps are read back."""
    sols = {}
    for conv in dict.fromkeys(["opengl", *conventions]):
        api, rz = CONVENTIONS[conv]
        bias = (rig.get("shadow") or {}).get("bias", "fitted")  # the rig's bias chooser (shadow.bias) is kept
        r = dict(rig, shadow={"resolution": [map_res, map_res], "cascades": cascades, "bias": bias},
                 output={"convention": api, "layout": "column_major", "reversed_z": rz})
        sols[conv] = solve(entry, validate_rig(r), SolveRequest(method="optimized"))
        for c in sols[conv]["lights"][0]["cascades"]:
            for mode in ("hardware", "linear"):
                blk = c["depth"][mode]
                blk.update({k: v(blk) if callable(v) else v for k, v in (depth_override or {}).items()})
        if cascade_override is not None:
            cascade_override(sols[conv]["lights"][0]["cascades"])
    ref = [c["internal"] for c in sols["opengl"]["lights"][0]["cascades"]]
    for conv, s in sols.items():
        got = [c["internal"] for c in s["lights"][0]["cascades"]]
        if json.dumps(got) != json.dumps(ref):
            raise AssertionError(f"the {conv} solution's maps differ from the opengl one's")
    r = dict(rig, shadow={"resolution": [map_res, map_res], "cascades": cascades})
    return {"solutions": sols, "maps": maps_from_solution(sols["opengl"])[0], "rig": validate_rig(r)}


def _m(flat) -> np.ndarray:
    return np.asarray(flat, dtype=np.float64).reshape(4, 4, order="F")  # column_major -> matrix


def camera_matrices(camera, rs, vertices: np.ndarray) -> dict:
    """OpenGL view and projection of the evaluator's camera, on re-centred points, with the pixel centres
    of Camera.ray_directions (row 0 at the top); the far plane pulled in to the scene's extent."""
    p = np.asarray(camera.position, float) - rs.origin
    r, u, f = (np.asarray(x, float) for x in (camera.right, camera.up, camera.forward))
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = r, u, -f
    view[:3, 3] = -view[:3, :3] @ p
    near = float(camera.near)
    far = min(float(camera.far), float(np.max((vertices - p) @ f)) * 1.01 + near)
    t = float(camera.tan_half_fov_y)
    proj = np.zeros((4, 4))
    proj[0, 0], proj[1, 1] = 1.0 / (t * camera.aspect), 1.0 / t
    proj[2, 2], proj[2, 3] = -(far + near) / (far - near), -2.0 * far * near / (far - near)
    proj[3, 2] = -1.0
    return {"view": view.ravel().tolist(), "projection": proj.ravel().tolist(),
            "resolution": list(camera.resolution)}


def listing_jobs(solved: dict, origin: np.ndarray, to_light, conventions=CONVENTIONS, languages=LANGUAGES,
                 mode: str = "solution") -> list:
    """The harness jobs: per convention and language, each map's matrices (re-centred on `origin` in
    float64, as an engine re-centres before its float32 upload) and its depth block: `mode` "solution" the
    map's own depth.mode, "hardware" / "linear" that block for every map (evaluate --depth likewise).
    Job names: <language>_<convention>_<mode>."""
    T = np.eye(4)
    T[:3, 3] = origin
    jobs = []
    for conv in conventions:
        cascades = solved["solutions"][conv]["lights"][0]["cascades"]
        maps = []
        for c in cascades:
            view, proj, tex = _m(c["view_matrix"]), _m(c["projection_matrix"]), _m(c["texture_matrix"])
            d = c["depth"]
            m = d["mode"] if mode == "solution" else mode
            block = d[m]
            maps.append({"view_matrix": (view @ T).ravel().tolist(),
                         "view_projection": (proj @ view @ T).ravel().tolist(),
                         "texture_matrix": (tex @ T).ravel().tolist(), "resolution": c["resolution"],
                         "split": c["split"], "blend_band": c.get("blend_band"),
                         "depth": {"mode": m, "constant": block["constant"], "slope": block["slope"],
                                   "normal_offset": block.get("normal_offset") or 0.0,
                                   "near": block.get("near", 0.0), "far": block.get("far", 1.0),
                                   "slope_scaled": block["slope_scaled"], "slope_clamp": block["slope_clamp"]}})
        for lang in languages:
            jobs.append({"name": f"{lang}_{conv}_{mode}", "language": lang, "clip": conv, "maps": maps,
                         "state": light_pass_api(lang, conv), "to_light": [float(x) for x in to_light]})
    return jobs


def light_pass_api(language: str, convention: str) -> str:
    """Which of the document's rasterizer-state blocks sets a job's light pass: Vulkan's for the vulkan
    convention, Direct3D 11's for the HLSL, OpenGL's for the GLSL."""
    return "vulkan" if convention == "vulkan" else ("d3d11" if language == "hlsl" else "gl")


def run_listing(vertices, faces, camera: dict, jobs: list, sources: dict, timeout: float = 600) -> dict:
    """renderers.gl_listing in a subprocess (Mesa's LLVM 15 must not meet Dr.Jit's). Raises RuntimeError
    with the harness's stderr; its message starts with "no OpenGL" when EGL or moderngl is missing."""
    spec = {"camera": camera, "sources": sources, "jobs": jobs}
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.uint32),
                 spec=json.dumps(spec))
        p = subprocess.run([sys.executable, "-m", "shadowopt.renderers.gl_listing", str(src), str(out)],
                           capture_output=True, text=True, timeout=timeout)
        if p.returncode != 0:
            tail = p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ""
            no_gl = ("EGL" in p.stderr or "moderngl" in p.stderr) and "glslang" not in p.stderr
            kind = "no OpenGL here: " if no_gl else ""
            raise RuntimeError(f"{kind}the OpenGL listing harness failed: {tail}\n{p.stderr[-4000:]}")
        with np.load(out) as d:
            return {k: d[k] for k in d.files}


def listing_wrong_pixels(gt, gl: dict, rs, name: str) -> dict:
    """Wrong pixels of the GL render `name` against exact visibility, over the ground truth's receivers
    where the rasterized surface is the ray-traced one (within 1e-3 of the view depth + 1e-5 of the
    scene's extent); the receivers where it is not are counted as `other_surface` and left out."""
    sb = gt.screen
    rec = gt.receivers
    pos = sb.position - rs.origin
    gap = np.linalg.norm(np.where(rec[..., None], pos, 0.0) - gl["position"].astype(np.float64), axis=-1)
    tol = 1e-3 * np.where(np.isfinite(sb.depth), sb.depth, 0.0) + 1e-5 * rs.extent
    same = rec & gl["hit"] & (gap <= tol)
    gl_shadowed = gl[f"shadow_{name}"] <= 0.5
    wrong = same & (gl_shadowed != gt.exact_shadowed)
    return {"wrong": int(wrong.sum()), "receivers": int(rec.sum()), "compared": int(same.sum()),
            "other_surface": int((rec & ~same).sum())}


def measure(validate_rig, name: str, path, rig: dict, cascades: int, map_res: int, screen=None,
            languages=LANGUAGES, modes=("solution",), ideal: bool = False, log=None, sources=None,
            conventions=CONVENTIONS, depth_override: dict | None = None, cascade_override=None,
            no_offset: bool = False) -> dict:
    """One scene and cascade count: per depth mode of `modes`, `evaluate --depth <mode>` and the listing's wrong
    pixels per convention and language (all against the exact visibility of one screen), and with `ideal`
    the idealized `--depth ideal` too. `sources`: the shader pieces (default: the document's listings);
    `depth_override`, `cascade_override`: solve_for_listing's. `no_offset`: also the GLSL in the opengl
    convention without the caster offset (without_caster_offset), jobs named <...>_no_offset."""
    t0 = time.perf_counter()
    entry = scene_entry(path)
    solved = solve_for_listing(validate_rig, entry, rig, cascades, map_res, depth_override, cascade_override,
                               conventions)
    resolved = resolve_rig(solved["rig"], entry.loaded)
    light = resolved.lights[0]
    rs = entry.rays
    camera = screen_camera(resolved.camera, screen)
    evals, gt = {}, None
    for depth in (*modes, "ideal") if ideal else modes:
        g = evaluate_buffers(rs, camera, light, solved["maps"], None, depth=depth)
        evals[depth] = g.result["misclassified_pixels"]
        gt = gt or g
    t1 = time.perf_counter()
    verts = np.array(rs.vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.array(rs.faces, dtype=np.uint32).reshape(-1, 3)
    to_light = -np.asarray(light.direction, float)
    jobs = [j for mode in modes for j in listing_jobs(solved, rs.origin, to_light, conventions, languages, mode)]
    src = listings() if sources is None else sources
    cam = camera_matrices(camera, rs, verts.astype(np.float64))
    gl = run_listing(verts, faces, cam, jobs, src)
    listing = {j["name"]: listing_wrong_pixels(gt, gl, rs, j["name"]) for j in jobs}
    if no_offset:
        bare = [dict(j, name=j["name"] + "_no_offset") for mode in modes
                for j in listing_jobs(solved, rs.origin, to_light, ("opengl",), ("glsl",), mode)]
        gl_bare = run_listing(verts, faces, cam, bare, without_caster_offset(src))
        listing.update({j["name"]: listing_wrong_pixels(gt, gl_bare, rs, j["name"]) for j in bare})
    t2 = time.perf_counter()
    sol_modes = [c["depth"]["mode"] for c in solved["solutions"]["opengl"]["lights"][0]["cascades"]]
    if log:
        log(f"{name} K={cascades}: evaluate {evals}, listing {({k: v['wrong'] for k, v in listing.items()})} "
            f"({t1 - t0:.1f} s solve+evaluate, {t2 - t1:.1f} s OpenGL)")
    return {"scene": name, "cascades": cascades, "screen": list(camera.resolution), "map": map_res,
            "modes": sol_modes, "depth": [c["depth"] for c in solved["solutions"]["opengl"]["lights"][0]["cascades"]],
            "evaluate": evals, "listing": listing, "renderer": str(gl["renderer"]),
            "receivers": int(gt.receivers.sum()), "seconds": t2 - t0,
            "resolved": {c: solved["solutions"][c]["resolved"] for c in conventions},
            "light": {"direction": [float(x) for x in light.direction]},
            "camera": {"position": [float(x) for x in camera.position], "forward": [float(x) for x in camera.forward],
                       "fov_y_deg": float(camera.fov_y_deg)}}


def bench_engine(validate_rig, scenes=None, write=True, map_res=2048, screen=None, log=None) -> dict:
    """`shadowopt bench engine`: McUsd at its camera's resolution (1 and 4 cascades) and the corpus scenes
    of CORPUS_SUNS at 1280x720; maps map_res^2."""
    missing = hlsl_tools()
    languages = LANGUAGES if missing is None else ("glsl",)
    pairs, skipped = scene_rigs(scenes, screen)
    rows = []
    for name, path, rig in pairs:
        for k in (1, 4):
            rows.append(measure(validate_rig, name, path, rig, k, map_res, None, languages, ENGINE_MODES, True, log,
                                no_offset=True))
    names = [f"{lang} {conv}" for lang in languages for conv in CONVENTIONS]
    lines = ["| scene | cascades | screen | receivers | left out | solution's modes | depth | evaluate ideal | "
             "**evaluate --depth** | " + " | ".join(f"listing {n}" for n in names) + " | listing glsl opengl, "
             "no caster offset |",
             "|---|---:|---|---:|---:|---|---|---:|---:|" + "---:|" * (len(names) + 1)]
    for r in rows:
        e = r["evaluate"]
        for mode in ENGINE_MODES:
            cells = [f"{r['listing'][f'{lang}_{conv}_{mode}']['wrong']:,}"
                     for lang in languages for conv in CONVENTIONS]
            cells.append(f"{r['listing'][f'glsl_opengl_{mode}_no_offset']['wrong']:,}")
            left_out = max(v["other_surface"] for v in r["listing"].values())
            lines.append(f"| {r['scene']} | {r['cascades']} | {r['screen'][0]}x{r['screen'][1]} | {r['receivers']:,} | "
                         f"{left_out:,} | "
                         f"{','.join(sorted(set(r['modes'])))} | {mode} | {e['ideal']:,} | **{e[mode]:,}** | "
                         + " | ".join(cells) + " |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    table = "\n".join(lines)
    note = ("Wrong pixels (shadow state different from exact ray-traced visibility, over the sun-facing pixels) of "
            "one optimized solution per scene and cascade count. Per depth mode (`solution`: each map's own "
            "`depth.mode`; `hardware` / `linear`: that block for every map): `evaluate --depth <mode>` in the ray "
            "tracer, and docs/engine-integration.md's listings with that mode rendered in Mesa OpenGL "
            f"({rows[0]['renderer'] if rows else 'n/a'}) in the conventions `opengl`, `d3d` (glClipControl upper-left, "
            "depth [0, 1]), `vulkan` (glClipControl lower-left, depth [0, 1]) and `reversed_z` (d3d with "
            "output.reversed_z), GLSL as printed and HLSL through glslang and SPIRV-Cross; each light pass with the "
            "document's rasterizer-state block (its OpenGL calls for the GLSL, its Direct3D 11 fields for the HLSL, its "
            "Vulkan fields in the vulkan convention: the caster-side slope-scaled bias `slope_scaled`, `slope_clamp` "
            "of the map's `depth.hardware`; `linear` adds `depth.linear`'s in the shader). "
            f"Maps {map_res}x{map_res}; suns: McUsd's own, street_canyon {CORPUS_SUNS['street_canyon']}, "
            f"terrain {CORPUS_SUNS['terrain']}. The listing is compared where the rasterized surface is the "
            "ray-traced one; `left out`: the receivers where it is not (silhouettes). The last column: the GLSL "
            "in the opengl convention with the caster offset taken out (no glPolygonOffsetClamp, no slope term in "
            "the linear light pass): what the slope-scaled bias buys.")
    if missing:
        note += f" HLSL not run: {missing}."
    out = {"rows": rows, "skipped": skipped, "table": note + "\n\n" + table}
    if write:
        write_section("engine", out["table"], "shadowopt bench engine")
    return out

