"""The `shadowopt` command line. Bad input exits with code 2 and a one-line reason, never a traceback."""
from __future__ import annotations

import argparse
import json
import os
import sys
from importlib.metadata import version
from pathlib import Path

from pydantic import ValidationError

from ..renderers.json_text import dumps  # standard JSON only: every JSON the CLI writes goes through it
from ..service.methods import METHODS  # the one list of methods (no imports: --help stays light)
from .cli_bench import add_bench_parser
from .cli_common import EXIT_USAGE, CliError, parse_wxh
from .progress import progress_bar
from .schemas import ConfigurationError, format_validation_error, validate_configurations
from .schemas import validate_rig  # the rig validation (api.schemas); kept importable from here
from .settings import SettingsError, load_settings

DEMO_SCENE = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"
DEMO_RIG = Path(__file__).resolve().parents[1] / "configs" / "demo_rig.json"


def load_rig(path: str | None, args=None) -> dict:
    """Read a rig JSON file, apply CLI overrides to rig.shadow, validate, return the validated dict."""
    if path is None:
        raise CliError("--rig: a rig JSON file is required (see configs/demo_rig.json)")
    try:
        raw = json.loads(Path(path).read_text())
    except OSError as e:
        raise CliError(f"--rig: cannot read {path!r}: {e.strerror}") from e
    except json.JSONDecodeError as e:
        raise CliError(f"--rig: {path} is not valid JSON: {e.msg} at line {e.lineno} column {e.colno}") from e
    if not isinstance(raw, dict):
        raise CliError(f"--rig: {path} must hold a JSON object")
    shadow = raw.setdefault("shadow", {}) if isinstance(raw.get("shadow", {}), dict) else raw.get("shadow")
    if args is not None and isinstance(shadow, dict):
        if getattr(args, "shadow_resolution", None):
            shadow["resolution"] = args.shadow_resolution
            shadow.pop("texel_budget", None)
        if getattr(args, "texel_budget", None):
            shadow["texel_budget"] = args.texel_budget
            shadow.pop("resolution", None)
        if getattr(args, "cascades", None):
            shadow["cascades"] = args.cascades if args.cascades == "auto" else _int_arg("--cascades", args.cascades)
        if getattr(args, "splits", None):
            shadow["splits"] = args.splits
        if getattr(args, "split_lambda", None) is not None:
            shadow["lambda"] = args.split_lambda
        if getattr(args, "bias", None):
            shadow["bias"] = args.bias
    try:
        return validate_rig(raw)
    except ValidationError as e:
        raise CliError(f"rig {path}: {format_validation_error(e)}") from e


def _int_arg(name: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise CliError(f"{name}: expected an integer or 'auto', got {text!r}") from None


def _scene_options(args) -> dict:
    opts = {"time_code": args.time, "asset_root": args.asset_root}
    if args.asset_root and not Path(args.asset_root).is_dir():
        raise CliError(f"--asset-root: {args.asset_root!r} is not a directory")
    return opts


def cmd_scene_info(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.pipeline import scene_entry

    entry = scene_entry(args.scene, **_scene_options(args))
    info = entry.loaded.info()
    info["build_s"] = round(entry.build_s, 4)
    if args.json:
        print(dumps(info, indent=2))
    else:
        lo, hi = info["bounds"]["min"], info["bounds"]["max"]
        print(f"{info['source']}: {info['triangles']} triangles in {info['prims']} prims, "
              f"loaded in {info['load_s']:.2f} s")
        print(f"  stage: upAxis {info['frame']['stage_up_axis']}, metersPerUnit "
              f"{info['frame']['stage_meters_per_unit']} -> world: {info['frame']['world']}")
        print(f"  bounds (m): min {[round(v, 3) for v in lo]} max {[round(v, 3) for v in hi]}")
        for c in info["cameras"]:
            print(f"  camera {c['usd_path']}: fov_y {c['fov_y_deg']:.1f} deg, clip [{c['near']:.3g}, {c['far']:.3g}] m")
        for lt in info["lights"]:
            print(f"  light  {lt['usd_path']}: {lt['usd_type']} -> {lt['type']}" + (f" ({lt['note']})" if lt.get("note") else ""))
        for w in info["warnings"]:
            print(f"  warning: {w}")
    return 0


def cmd_coarse(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.pipeline import coarse_pass, scene_entry

    rig = load_rig(args.rig, args)
    if args.long_side:
        rig["coarse_long_side"] = args.long_side
    entry = scene_entry(args.scene, **_scene_options(args))
    resolved, buffers = coarse_pass(entry, rig, boundary_radius=args.boundary_radius)
    files = buffers.save(args.out)
    summary = {"out": str(args.out), "width": buffers.width, "height": buffers.height,
               "hit_pixels": int(buffers.hit.sum()),
               "lights": [{"lit_pixels": int(lb.lit.sum()), "boundary_pixels": int(lb.boundary.sum()),
                           "facing_pixels": int(lb.facing.sum())} for lb in buffers.lights],
               "timings_ms": {k: round(v, 3) for k, v in buffers.timings_ms.items()}, "files": sorted(files)}
    if args.json:
        print(dumps(summary, indent=2))
    else:
        print(f"wrote {len(files)} files to {args.out} ({buffers.width}x{buffers.height}, "
              f"{summary['hit_pixels']} hit pixels, {buffers.timings_ms['total']:.1f} ms)")
    return 0


def _write_or_print(obj: dict, out: str | None, as_json: bool, summary: str) -> None:
    text = dumps(obj, indent=2)
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(text)
    if as_json:
        print(text)
    else:
        print(summary + (f" (written to {out})" if out else ""))


def cmd_optimize(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.pipeline import scene_entry
    from ..service.request import SolveRequest
    from ..service.solve import solve

    rig = load_rig(args.rig, args)
    _check_options(args.method, rig["shadow"], solver=args.solver, time_budget_ms=args.time_budget_ms,
                   previous=args.previous, hysteresis=args.hysteresis)
    if args.emit:
        _emit(rig, None, args.emit)  # refuse an engine or rig --emit cannot serve before solving
    entry = scene_entry(args.scene, **_scene_options(args))
    previous = _read_json(args.previous, "--previous") if args.previous else None
    sol = solve(entry, rig, SolveRequest(method=args.method, solver=args.solver, time_budget_ms=args.time_budget_ms,
                                         previous=previous,
                                         hysteresis=0.8 if args.hysteresis is None else args.hysteresis))
    errs = [l["predicted_error"] for l in sol["lights"]]
    summary = "; ".join(f"light {k}: {len(l['cascades'])} map(s), predicted p95 m {e['p95_m']:.3g}, "
                        f"median m {e['median_m']:.3g} over {e['samples']} samples"
                        for k, (l, e) in enumerate(zip(sol["lights"], errs)))
    _write_or_print(sol, args.out, args.json, f"{args.method}: {summary}; {sol['timings_ms']['total']:.1f} ms")
    if args.emit:
        print(f"{_emit(rig, sol, args.emit)} module written to {args.emit}", file=sys.stderr)
    return 0


def _emit(rig: dict, sol: dict | None, path: str) -> str:
    """--emit: service.emit's checks as exit 2 (sol None: the rig's only, before solving), else the module written;
    returns the engine's name."""
    from ..service.emit import ENGINE_NAMES, EmitError, check_rig, module  # lazy: only with --emit

    try:
        engine = check_rig(rig)
        if sol is None:
            return ENGINE_NAMES[engine]
        text = module(sol)
    except EmitError as e:
        raise CliError(str(e)) from None
    try:
        Path(path).write_text(text)
    except OSError as e:
        raise CliError(f"--emit: cannot write {path!r}: {e.strerror}") from e
    return ENGINE_NAMES[engine]


def cmd_tune(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.pipeline import scene_entry
    from ..service.tune import TuneError, tune
    from ..solvers.engine_fits import engine_module

    fixed = dict(_knob_arg(t) for t in args.set or [])
    try:  # an unknown engine or knob, a value out of range: exit 2 naming it, before any work
        engine_module(args.engine).validate(fixed)
    except ValueError as e:
        raise CliError(str(e)) from None
    rig = load_rig(args.rig, args)
    poses = _tune_poses(rig, args.poses) if args.poses else None
    entry = scene_entry(args.scene, **_scene_options(args))
    try:
        res = tune(entry, rig, args.engine, poses=poses, fixed=fixed,
                   camera_path=_read_json(args.camera_path, "--camera-path") if args.camera_path else None,
                   sun_arc=_read_json(args.sun_arc, "--sun-arc") if args.sun_arc else None,
                   time_budget_ms=args.time_budget_ms)
    except TuneError as e:
        raise CliError(str(e)) from None
    s, p, d = res["settings"], res["predicted"], res["defaults"]["predicted"]
    _write_or_print(res, args.out, args.json,
                    f"{res['engine']} {res['engine_version']}: " + ", ".join(f"{k}={v}" for k, v in s.items())
                    + f"; predicted {p['misclassified_pixels']:.0f} wrong pixels (defaults: "
                    f"{d['misclassified_pixels']:.0f}); {res['timings_ms']['total']:.0f} ms\n{res['snippet']}")
    if args.emit:
        from ..service import emit_tune_babylon, emit_tune_three  # lazy: only with --emit

        emitter = {"three": emit_tune_three, "babylon": emit_tune_babylon}[res["engine"]]
        try:
            Path(args.emit).write_text(emitter.tune_module(res))
        except OSError as e:
            raise CliError(f"--emit: cannot write {args.emit!r}: {e.strerror}") from e
        print(f"{'three.js' if res['engine'] == 'three' else 'Babylon.js'} module written to {args.emit}",
              file=sys.stderr)
    return 0


def _knob_arg(text: str) -> tuple[str, object]:
    """--set KNOB=VALUE: VALUE read as JSON (numbers, true, false), else as a string."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise CliError(f"--set: expected KNOB=VALUE, got {text!r}")
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


def _tune_poses(rig: dict, path: str) -> list[dict]:
    """--poses FILE.json: a list of camera objects (as the rig's camera), each validated in the rig."""
    poses = _read_json(path, "--poses")
    if not isinstance(poses, list) or not poses:
        raise CliError(f"--poses: {path} must hold a non-empty JSON list of camera objects")
    out = []
    for k, cam in enumerate(poses):
        try:
            out.append(validate_rig({**rig, "camera": cam})["camera"])
        except ValidationError as e:
            raise CliError(f"--poses: pose {k}: {format_validation_error(e)}") from e
    return out


# the CLI's flag for each field service.method_options names (a rig field without a flag is named as in the rig)
OPTION_FLAGS = {"solver": "--solver", "time_budget_ms": "--time-budget-ms", "previous": "--previous",
                "hysteresis": "--hysteresis", "rig.shadow.lambda": "--lambda (rig shadow.lambda)",
                "rig.shadow.splits": "--splits (rig shadow.splits)"}


def _check_options(method: str, shadow: dict | None, **given) -> None:
    """service.method_options.check_options as a CLI error: exit 2 naming the flag and why it would be ignored."""
    from ..service.method_options import OptionError, check_options  # lazy: the server stack loads per command

    try:
        check_options(method, shadow, **given)
    except OptionError as e:
        flag = OPTION_FLAGS.get(e.field) or ("rig " + e.field.removeprefix("rig.") if e.field.startswith("rig.")
                                              else e.field)
        raise CliError(f"{flag}: not used by --method {method}: {e.message}") from None


def _read_json(path: str, flag: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except OSError as e:
        raise CliError(f"{flag}: cannot read {path!r}: {e.strerror}") from e
    except json.JSONDecodeError as e:
        raise CliError(f"{flag}: {path} is not valid JSON: {e.msg} at line {e.lineno}") from e


DEPTH_FLAG_CHOICES = ("solution", "hardware", "linear", "ideal")
DEPTH_FLAG_HELP = ("the depth test emulated: solution (default: what an engine does with each map's depth block, in "
                   "the mode it names), hardware (window z of the projection) or linear (light-space distance) for every "
                   "map, or ideal (the idealized per-texel bias rule of depth_bias)")


def cmd_evaluate(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.evaluation import evaluate_solution
    from ..service.pipeline import scene_entry

    rig = load_rig(args.rig, args)
    solution = _read_json(args.solution, "--solution")
    entry = scene_entry(args.scene, **_scene_options(args))
    res = evaluate_solution(entry, rig, solution, screen=args.screen, heatmap_path=args.heatmap,
                            grid_every=args.grid, heatmap_mode=args.heatmap_mode, depth=args.depth)
    if args.json:
        print(dumps(res, indent=2))
    else:
        print(f"depth test: {args.depth}" + (" (each map's depth block, in the mode it names)"
                                            if args.depth == "solution" else ""))
        for k, r in enumerate(res["lights"] if "lights" in res else [res]):
            print(_evaluation_summary(r, f"light {k}: " if "lights" in res else ""))
        if args.heatmap:
            print(f"{args.heatmap_mode} heatmap with its legend: {args.heatmap}"
                  + (" (one file per light)" if "lights" in res else ""))
    return 0


def _evaluation_summary(r: dict, prefix: str = "") -> str:
    """One line per evaluation; counts and measured m name the screen they were measured at."""
    w, h = r.get("screen") or ("?", "?")
    rw, rh = r.get("rig_resolution") or (w, h)
    p95 = r.get("measured_error", {}).get("p95_m", float("nan"))
    line = (f"{prefix}at the {w}x{h} screen: misclassified {r.get('misclassified_pixels')} of "
            f"{r.get('receiver_pixels')} receiver pixels ({100 * (r.get('misclassified_fraction') or 0):.3f}%; "
            f"wrongly shadowed {r.get('wrongly_shadowed_pixels')}, wrongly lit {r.get('wrongly_lit_pixels')}), "
            f"outside {r.get('outside_pixels')}, measured p95 m {p95:.3g} in {w}x{h} pixels")
    if "measured_error_rig_pixels" in r:
        line += f", {r['measured_error_rig_pixels'].get('p95_m', float('nan')):.3g} in the rig's {rw}x{rh} pixels"
    return line


def cmd_analyze(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..solvers.analysis import analyze

    for name, v, lo, hi in (("--f-over-n", args.f_over_n, 1.0, 1e9), ("--theta-deg", args.theta_deg, 0.0, 90.0),
                            ("--gamma-deg", args.gamma_deg, 0.0, 180.0)):
        if not (lo <= v <= hi) or (name != "--gamma-deg" and v == lo):
            raise CliError(f"{name}: {v} is outside ({lo:g}, {hi:g}]" if name != "--gamma-deg"
                           else f"{name}: {v} is outside [0, 180]")
    if args.partitions < 1:
        raise CliError(f"--partitions: must be at least 1, got {args.partitions}")
    res = analyze(args.f_over_n, args.theta_deg, args.gamma_deg, args.method, partitions=args.partitions)
    res = {k: float(v) for k, v in res.items()}
    if args.json:
        print(dumps(res, indent=2))
    else:
        print(f"R_s = {res['R_s']:.4g}, R_t = {res['R_t']:.4g}, S = {res['S']:.4g}"
              + (f", maps = {res['maps']:g}" if "maps" in res else ""))
    return 0


def cmd_compare(args) -> int:
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.compare import compare, markdown_table
    from ..service.pipeline import scene_entry

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise CliError(f"--methods: unknown {', '.join(bad) or '(none given)'} (known: {', '.join(METHODS)})")
    rig = load_rig(args.rig, args)
    for m in methods:
        _check_options(m, rig["shadow"])
    entry = scene_entry(args.scene, **_scene_options(args))
    res = compare(entry, rig, methods, screen=args.screen, report_dir=args.report, grid_every=args.grid,
                  depth=args.depth)
    if args.json:
        print(dumps(res, indent=2))
    else:
        print(markdown_table(res), end="")
        if args.report:
            print(f"report: {res['report']['heatmaps']} (m), {res['report']['errors']} (misclassified pixels), "
                  f"{res['report']['table']}")
    return 0


def cli_bar(total: int, desc: str, unit: str):
    """The batch and path commands' progress: a tqdm bar on a terminal, a line every few seconds in a log file."""
    return progress_bar(total, desc, unit=unit)


def cmd_batch(args) -> int:
    """Precompute many configurations (explicit, or a camera path crossed with light directions)."""
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.batch_request import expand_configurations
    from ..service.local_jobs import run_batch
    from ..service.request_fields import BatchError

    raw = _read_json(args.configs, "--configs")
    request = {"configurations": raw} if isinstance(raw, list) else raw
    if not isinstance(request, dict):
        raise CliError(f"--configs: {args.configs} must hold a JSON object or a list of configurations")
    try:
        configs = expand_configurations(request)
    except BatchError as e:
        raise CliError(f"--configs {args.configs}: {e.field}: {e.message}") from e
    try:
        configs = validate_configurations(configs)
    except ConfigurationError as e:
        raise CliError(f"--configs {args.configs}: {e.message}") from e
    method = args.method or request.get("method") or "optimized"
    if method not in METHODS:
        raise CliError(f"--configs {args.configs}: method: unknown {method!r} (known: {', '.join(METHODS)})")
    for c in configs:  # the batch's settings against each configuration's rig
        _check_options(method, (c.get("rig") or {}).get("shadow"), solver=args.solver or request.get("solver"),
                       time_budget_ms=args.time_budget_ms or request.get("time_budget_ms"))
    if args.workers < 1:
        raise CliError(f"--workers: must be at least 1, got {args.workers}")
    if args.backend == "ray":
        try:
            import ray  # noqa: F401  # lazy: optional (the ray extra), checked only for --backend ray
        except ImportError:
            raise CliError("--backend ray: ray is not installed (pip install 'shadowopt[ray]')") from None
    s = run_batch(args.scene, configs, backend=args.backend, workers=args.workers, out_path=args.out,
                  method=method, progress=None if args.no_progress else cli_bar, solver=args.solver or request.get("solver"),
                  time_budget_ms=args.time_budget_ms or request.get("time_budget_ms"), ray_address=args.ray_address)
    print(f"batch: {s['total']} configurations, {s['done']} done, {s['failed']} failed in {s['seconds']:.1f} s "
          f"({s['total'] / max(s['seconds'], 1e-9):.2f} configurations/s); results in {args.out}")
    if s["failed"]:
        first = s["errors"][0]
        print(f"shadowopt: error: {s['failed']} configuration(s) failed; first: index {first['index']}: "
              f"{first['code']}: {first['message']}", file=sys.stderr)
        # Nothing succeeded because of the input (the scene or the rigs): a usage error, like a bad file.
        internal = ("internal_error", "worker_crashed", "runner_error")
        return EXIT_USAGE if s["done"] == 0 and first["code"] not in internal else 1
    return 0


def cmd_path(args) -> int:
    """Solve a camera path frame by frame (service.paths): poses/keyframes, or a USD camera at time codes."""
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.local_jobs import run_path
    from ..service.paths import PathError, expand_path_with_notes, line_json

    raw = _read_json(args.rig, "--rig")
    if not isinstance(raw, dict):
        raise CliError(f"--rig: {args.rig} must hold a JSON object")
    if (args.path is None) == (args.camera is None):
        raise CliError("--path: give exactly one of --path PATH.json and --camera /USD/Camera with --time")
    if args.camera is not None:
        if args.time is None:
            raise CliError("--time: --camera needs --time START:END[:STEP] (time codes)")
        raw.setdefault("camera", {"usd_path": args.camera})
        request, source = {"rig": raw, "usd_camera": args.camera, "time": _parse_time(args.time)}, "--camera"
    else:
        path = _read_json(args.path, "--path")
        if not isinstance(path, dict):
            raise CliError(f"--path: {args.path} must hold a JSON object (the camera_path form)")
        request = {"rig": raw, **path} if "camera_path" in path else {"rig": raw, "camera_path": path}
        source = f"--path {args.path}"
    try:
        frames, notes = expand_path_with_notes(request, scene_path=args.scene)
    except PathError as e:
        raise CliError(f"{source}: {e.field}: {e.message}") from e
    try:
        rigs = validate_configurations([{"rig": f["rig"]} for f in frames])
    except ConfigurationError as e:
        raise CliError(f"{source}: {e.message.replace('configurations.', 'frames.')}") from e
    frames = [{**f, "rig": r["rig"]} for f, r in zip(frames, rigs)]
    method = args.method or "optimized"
    if method not in METHODS:
        raise CliError(f"--method: unknown {method!r} (known: {', '.join(METHODS)})")
    _check_options(method, None, solver=args.solver, time_budget_ms=args.time_budget_ms)
    if args.workers < 1:
        raise CliError(f"--workers: must be at least 1, got {args.workers}")
    for n in notes:
        print(f"shadowopt: note: {n}", file=sys.stderr)
    out = open(args.out, "w") if args.out else None

    def on_line(line):
        text = line_json(line)
        if out is not None:
            out.write(text + "\n")
            out.flush()
        if args.json:
            print(text, flush=True)

    try:
        s = run_path(args.scene, frames, method=method, coherent=args.coherent, workers=args.workers,
                     on_line=on_line, progress=None if args.no_progress else cli_bar, solver=args.solver,
                     time_budget_ms=args.time_budget_ms)
    finally:
        if out is not None:
            out.close()
    print(f"path: {s['total']} frames, {s['done']} done, {s['failed']} failed in {s['seconds']:.1f} s "
          f"({s['total'] / max(s['seconds'], 1e-9):.2f} frames/s)" + (f"; results in {args.out}" if args.out else ""),
          file=sys.stderr if args.json else sys.stdout)
    if s["failed"]:
        first = s["errors"][0]
        print(f"shadowopt: error: {s['failed']} frame(s) failed; first: frame {first['index']}: "
              f"{first['code']}: {first['message']}", file=sys.stderr)
        internal = ("internal_error", "worker_crashed", "runner_error")
        return EXIT_USAGE if s["done"] == 0 and first["code"] not in internal else 1
    return 0


def _parse_time(text: str) -> dict:
    """--time START:END[:STEP] -> {"start", "end", "step"} (step 1 by default)."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        vals = [float(p) for p in parts]
    except ValueError:
        raise CliError(f"--time: expected START:END[:STEP] in time codes, got {text!r}") from None
    return {"start": vals[0], "end": vals[1], "step": vals[2] if len(vals) == 3 else 1.0}


def cmd_pack(args) -> int:
    """A local stage with its references, sublayers and payloads as one .usdz to upload."""
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..service.packing import pack_stage

    res = pack_stage(args.scene, args.out, allow_outside=args.allow_outside)
    if args.json:
        print(dumps(res, indent=2))
    else:
        print(f"{args.out}: {res['entries']} entries ({res['layers']} layers), {res['bytes']} bytes")
        other = [a for a in res["assets"] if not a.lower().endswith((".usd", ".usda", ".usdc", ".usdz"))]
        if other:
            print(f"  note: {len(other)} non-USD file(s) packed (e.g. {other[0]}); the service does not read them")
        for u in res["unresolved"]:
            print(f"  warning: {u} is named by the stage but does not exist; left out", file=sys.stderr)
    return 0


def cmd_serve(args) -> int:
    from .server import check_host, serve  # lazy: FastAPI, uvicorn and the server stack: only to serve

    try:
        settings = load_settings(args.config, host=args.host, port=args.port, data_dir=args.data_dir,
                                 warm_scenes=args.scene)
    except SettingsError as e:
        raise CliError(str(e)) from e
    refusal = check_host(settings)
    if refusal:
        raise CliError(refusal)
    return serve(settings)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="shadowopt", description="Scene-optimized shadow-map parameters.")

    p.add_argument("--version", action="version", version=f"shadowopt {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def scene_args(sp):
        sp.add_argument("scene", help="a .usd, .usda, .usdc or .usdz file")
        sp.add_argument("--time", type=float, default=None, help="time code to read attributes at (default: the stage's default)")
        sp.add_argument("--asset-root", default=None, help="refuse assets that resolve outside this folder")

    sp = sub.add_parser("scene-info", help="print what the loader found in a scene")
    scene_args(sp)
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_scene_info)

    def rig_args(sp):
        sp.add_argument("--rig", required=True, help="rig JSON file (see configs/demo_rig.json)")
        sp.add_argument("--shadow-resolution", type=parse_wxh, default=None, metavar="WxH", help="overrides rig.shadow.resolution")
        sp.add_argument("--texel-budget", type=int, default=None, help="overrides rig.shadow.texel_budget")
        sp.add_argument("--cascades", default=None, help="overrides rig.shadow.cascades (K or auto)")
        sp.add_argument("--splits", choices=["practical", "log", "uniform", "optimized"], default=None)
        sp.add_argument("--lambda", dest="split_lambda", type=float, default=None, help="practical split weight")
        sp.add_argument("--bias", choices=["fitted", "rule"], default=None,
                        help="overrides rig.shadow.bias: fitted (default: chosen against the engine's depth test) or "
                             "rule (a fixed rule, what an engine user sets by hand)")

    sp = sub.add_parser("coarse", help="render the coarse buffers for a rig and write them to a folder")
    scene_args(sp)
    rig_args(sp)
    sp.add_argument("--out", required=True, help="output folder for .npy buffers and PNG previews")
    sp.add_argument("--long-side", type=int, default=None, help="coarse buffer's long side in px (default 180)")
    sp.add_argument("--boundary-radius", type=int, default=1, help="dilation of the shadow-boundary mask, px")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_coarse)

    sp = sub.add_parser("optimize", help="compute a shadow setup (matrices, warp, splits) and its predicted error")
    scene_args(sp)
    rig_args(sp)
    sp.add_argument("--method", choices=METHODS, default="optimized")
    sp.add_argument("--solver", default=None, help="optimizer for --method optimized (default nlopt:LN_BOBYQA; "
                    "gradient:linesearch, gradient:lbfgs, gradient:adam, nlopt:LN_COBYLA, nlopt:LN_SBPLX, "
                    "nlopt:GN_DIRECT_L, nlopt:LD_MMA, nlopt:LD_LBFGS)")
    sp.add_argument("--time-budget-ms", type=float, default=None, help="return the best so far after this long")
    sp.add_argument("--previous", default=None, metavar="FILE", help="the previous frame's solution: kept (refit) "
                    "unless the new one's median h is below --hysteresis times its own (temporal stability)")
    sp.add_argument("--hysteresis", type=float, default=None, help="with --previous and --method optimized (default 0.8)")
    sp.add_argument("--out", default=None, help="also write the solution JSON to this file")
    sp.add_argument("--emit", default=None, metavar="FILE.js", help="also write an ES module that installs the "
                    "solution in the engine as it is (the rig's output.engine \"three\": three.js r187, one "
                    "directional light, one map or cascades through three's CSM addon; \"babylon\": Babylon.js "
                    "9.35, one directional light, one map; \"filament\": the light's ShadowOptions for Filament's "
                    "web build, which takes no matrix; docs/engines.md)")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_optimize)

    sp = sub.add_parser("tune", help="an engine's own cascade settings (three.js CSM, Babylon.js) that predict the fewest wrong "
                        "pixels, against the engine's defaults (docs/tune.md)")
    scene_args(sp)
    rig_args(sp)
    sp.add_argument("--engine", default="three", help="the engine whose cascades to tune (accepted: three, "
                    "babylon)")
    sp.add_argument("--poses", default=None, metavar="FILE.json", help="more camera poses (a JSON list of camera "
                    "objects like the rig's): one setting for all of them")
    sp.add_argument("--camera-path", default=None, metavar="FILE.json", help="more poses along a camera path "
                    "({\"poses\": [...]} or {\"keyframes\": [...], \"samples\": N}, over the rig's camera)")
    sp.add_argument("--sun-arc", default=None, metavar="FILE.json", help="every camera under each sun of an arc "
                    "({\"azimuth_deg\": [a, b], \"elevation_deg\": [a, b], \"samples\": N}); at most 16 poses in all")
    sp.add_argument("--time-budget-ms", type=float, default=None, help="the search's time (default 1600 per pose "
                    "less the coarse passes); past it no new candidate is scored (the answer's search.complete)")
    sp.add_argument("--set", action="append", metavar="KNOB=VALUE", help="pin a knob (the engine's own name, e.g. "
                    "cascades=4); repeatable")
    sp.add_argument("--out", default=None, help="also write the result JSON to this file")
    sp.add_argument("--emit", default=None, metavar="FILE.js", help="also write an ES module that builds the tuned "
                    "cascades (three: a CSM instance from ctx.CSM, export default function apply(THREE, ctx); babylon: a "
                    "CascadedShadowGenerator, apply(BABYLON, ctx))")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_tune)

    sp = sub.add_parser("evaluate", help="measure a solution against exact ray-traced shadows")
    scene_args(sp)
    rig_args(sp)
    sp.add_argument("--solution", required=True, help="a solution JSON written by `optimize`")
    sp.add_argument("--screen", type=parse_wxh, default=None, metavar="WxH", help="measure at this screen "
                    "resolution (default: the rig's; predicted error stays in the rig's pixels)")
    sp.add_argument("--heatmap", default=None, metavar="FILE.png", help="write a heatmap with its legend")
    sp.add_argument("--heatmap-mode", choices=["m", "errors"], default="m", help="m: the per-pixel m in the colour key of "
                    "Lloyd et al. (2007); errors: wrongly shadowed and wrongly lit pixels in two colours over the exact "
                    "shading (default m)")
    sp.add_argument("--grid", type=int, default=None, metavar="N", help="overlay the texel grid every N texels")
    sp.add_argument("--depth", choices=DEPTH_FLAG_CHOICES, default="solution", help=DEPTH_FLAG_HELP)
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_evaluate)

    sp = sub.add_parser("compare", help="methods side by side: predicted and measured error, time, heatmaps")
    scene_args(sp)
    rig_args(sp)
    sp.add_argument("--methods", default="uniform,focused,lispsm,logpsm", help="comma-separated methods")
    sp.add_argument("--screen", type=parse_wxh, default=None, metavar="WxH", help="measure at this screen "
                    "resolution (default: the rig's); every method is still solved at the rig's resolution")
    sp.add_argument("--report", default=None, metavar="DIR", help="write the m heatmaps and the misclassified "
                    "pixels per method side by side (PNG) and the table (Markdown)")
    sp.add_argument("--grid", type=int, default=None, metavar="N", help="overlay the texel grid every N texels")
    sp.add_argument("--depth", choices=DEPTH_FLAG_CHOICES, default="solution", help=DEPTH_FLAG_HELP)
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_compare)

    sp = sub.add_parser("analyze", help="Lloyd et al. (2007): scene-independent critical resolution and storage factors")
    sp.add_argument("--f-over-n", type=float, required=True)
    sp.add_argument("--theta-deg", type=float, required=True, help="half field of view of the view frustum")
    sp.add_argument("--gamma-deg", type=float, required=True, help="angle between light and view direction (90 = overhead)")
    sp.add_argument("--method", choices=["uniform", "perspective", "log", "fp", "fp+p", "fp+log"], required=True,
                    help="a warp per z-partition, or face partitioning (fp, fp+p, fp+log; Lloyd et al. 2007)")
    sp.add_argument("--partitions", type=int, default=1, help="equal-ratio z-partitions (1 with face partitioning)")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_analyze)

    add_bench_parser(sub)

    sp = sub.add_parser("batch", help="precompute shadow setups for many camera/light configurations")
    sp.add_argument("scene", help="a .usd, .usda, .usdc or .usdz file")
    sp.add_argument("--configs", required=True, help='JSON: {"configurations": [{"rig": ...}, ...]} or a base '
                    '"rig" with "camera_path" and/or "light_directions" / "sun_arc"')
    sp.add_argument("--out", required=True, help="JSON lines, one per configuration in index order")
    sp.add_argument("--backend", choices=["local", "ray"], default="local")
    sp.add_argument("--workers", type=int, default=2, help="worker processes (local) or Ray actors")
    sp.add_argument("--ray-address", default=None, help="a Ray cluster (default: a local Ray instance)")
    sp.add_argument("--method", choices=METHODS, default=None,
                    help="default: the file's \"method\", else optimized")
    sp.add_argument("--solver", default=None, help="optimizer for --method optimized")
    sp.add_argument("--time-budget-ms", type=float, default=None, help="per configuration")
    sp.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    sp.set_defaults(func=cmd_batch)

    sp = sub.add_parser("path", help="solve a camera path frame by frame (poses, keyframes or a USD camera's "
                        "time samples); results in frame order")
    sp.add_argument("scene", help="a .usd, .usda, .usdc or .usdz file")
    sp.add_argument("--rig", required=True, help="the base rig JSON (shadow, output, lights; the path sets the camera)")
    sp.add_argument("--path", default=None, metavar="PATH.json", help='the camera path: {"poses": [...]} or '
                    '{"keyframes": [...], "samples": N} (as a batch\'s camera_path)')
    sp.add_argument("--camera", default=None, metavar="/USD/Camera", help="a camera animated by time samples")
    sp.add_argument("--time", default=None, metavar="START:END[:STEP]", help="time codes for --camera")
    sp.add_argument("--method", default=None, help="default optimized")
    sp.add_argument("--coherent", action="store_true", help="solve frames in order, each given the previous "
                    "frame's solution (as optimize --previous)")
    sp.add_argument("--json", action="store_true", help="one JSON line per frame on stdout, in frame order")
    sp.add_argument("--out", default=None, metavar="FILE", help="also write the JSON lines to FILE")
    sp.add_argument("--workers", type=int, default=2, help="worker processes (a coherent path runs in as many "
                    "coherent chunks, each starting fresh, when it has 16 frames per worker)")
    sp.add_argument("--solver", default=None, help="optimizer for --method optimized")
    sp.add_argument("--time-budget-ms", type=float, default=None, help="per frame")
    sp.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    sp.set_defaults(func=cmd_path)

    sp = sub.add_parser("pack", help="package a stage and the files it references as one .usdz to upload")
    sp.add_argument("scene", help="a .usd, .usda or .usdc stage")
    sp.add_argument("--out", required=True, metavar="FILE.usdz", help="the package to write")
    sp.add_argument("--allow-outside", action="store_true", help="also pack files outside the stage's folder "
                    "(absolute paths, '..', links leading out; refused by default: they would be uploaded)")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_pack)

    sp = sub.add_parser("serve", help="start the REST service")
    sp.add_argument("--host", default=None, help="default 127.0.0.1; another address needs tokens configured "
                    "(or, without them, allowed_hosts)")
    sp.add_argument("--port", type=int, default=None, help="default 8000")
    sp.add_argument("--data-dir", default=None, help="scene files and the SQLite database (default ./data)")
    sp.add_argument("--config", default=None, help="settings file (TOML or JSON): tokens, limits, batch backend")
    sp.add_argument("--scene", action="append", default=None, help="scene to warm up with before /healthz is 200 "
                    "(repeatable; default: the demo)")
    sp.set_defaults(func=cmd_serve)
    return p


def _version() -> str:
    try:
        return version("shadowopt")
    except Exception:
        return "0+unknown"


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # lazy: the server stack (an extra) loads only for the command that runs, not for --help
    from ..renderers.mitsuba_setup import RendererUnavailable
    from ..renderers.scene_data import SceneError
    from ..service.rigs import RigError, SolutionError

    try:
        return int(args.func(args) or 0)
    except CliError as e:
        print(f"shadowopt: error: {e}", file=sys.stderr)
        return e.code
    except SceneError as e:
        print(f"shadowopt: error: scene: {e.message} [{e.code}]", file=sys.stderr)
        return EXIT_USAGE
    except SolutionError as e:
        print(f"shadowopt: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except RigError as e:
        print(f"shadowopt: error: rig: {e}", file=sys.stderr)
        return EXIT_USAGE
    except RendererUnavailable as e:
        print(f"shadowopt: error: renderer unavailable: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # an internal error: say what, keep the traceback for debugging on request
        if os.environ.get("SHADOWOPT_DEBUG"):
            raise
        print(f"shadowopt: internal error: {type(e).__name__}: {e} (set SHADOWOPT_DEBUG=1 for a traceback)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
