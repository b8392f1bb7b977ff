"""`shadowopt bench NAME`: run a benchmark (service/bench/), print its table and write it into BENCHMARKS.md."""
from __future__ import annotations

import sys

from ..renderers.json_text import dumps  # standard JSON only
from .cli_common import CliError, parse_wxh
from .schemas import validate_rig


def cmd_bench(args) -> int:
    if args.bench == "coarse":
        from ..service.bench.coarse import bench_coarse  # lazy: the server stack loads only for the command that runs

        result = bench_coarse(validate_rig, runs=args.runs or 20, scenes=args.scenes, write=not args.no_write)
    elif args.bench == "solvers":
        from ..service.bench.solvers import bench_solvers, bench_solvers_corpus  # lazy: the server stack loads only for the command that runs

        if args.corpus:
            result = bench_solvers_corpus(validate_rig, lights=args.lights or 3, scenes=args.scenes,
                                          write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
        else:
            result = bench_solvers(validate_rig, lights=args.lights or 5, write=not args.no_write)
    elif args.bench == "trust":
        from ..service.bench.trust import bench_trust  # lazy: the server stack loads only for the command that runs

        result = bench_trust(validate_rig, rigs=args.lights, write=not args.no_write)
    elif args.bench == "quality":
        parts = ("single", "cascades") if args.part == "all" else (args.part,)
        if args.corpus:
            from ..service.bench.quality_corpus import bench_quality_corpus  # lazy: the server stack loads only for the command that runs

            result = bench_quality_corpus(validate_rig, lights=args.lights, scenes=args.scenes, parts=parts,
                                          write=not args.no_write, reuse=args.reuse or False,
                                          screen=args.screen, cascade_lights=args.cascade_lights,
                                          hd_lights=args.hd_lights, log=lambda m: print(m, file=sys.stderr))
        else:
            from ..service.bench.quality import bench_quality  # lazy: the server stack loads only for the command that runs

            result = bench_quality(validate_rig, lights=args.lights, write=not args.no_write, parts=parts)
    elif args.bench == "engine-truth":  # the engine's depth test with the fitted and the fixed-rule bias
        from ..service.bench.engine_truth import bench_engine_truth  # lazy: the server stack loads only for the command that runs

        result = bench_engine_truth(validate_rig, lights=args.lights, scenes=args.scenes, screen=args.screen,
                                    write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "engines":  # tune's settings, the defaults and a hand grid in real three.js or Babylon.js
        from ..service.bench.engines import bench_engines  # lazy: the server stack loads only for the command that runs

        result = bench_engines(validate_rig, lights=args.lights, scenes=args.scenes, screen=args.screen,
                               write=not args.no_write, log=lambda m: print(m, file=sys.stderr),
                               engine=args.engine, part={"single": "all", "cascades": "all"}.get(args.part, args.part))
    elif args.bench == "solve-time":  # optimize's time per light, fitted bias against the rule
        from ..service.bench.solve_time import bench_solve_time  # lazy: the server stack loads only for the command that runs

        result = bench_solve_time(validate_rig, runs=args.runs or 3, write=not args.no_write)
    elif args.bench == "heldout":  # the corpus protocol on the held-out scenes (configs/heldout.json)
        from ..service.bench.heldout import bench_heldout  # lazy: the server stack loads only for the command that runs

        result = bench_heldout(validate_rig, lights=args.lights, scenes=args.scenes, screen=args.screen,
                               cascade_lights=args.cascade_lights, cascades=args.part != "single",
                               reuse=bool(args.reuse), write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "batch":
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.batches import bench_batch

        result = bench_batch(validate_rig, configurations=args.lights or 20, write=not args.no_write)
    elif args.bench == "security":
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.security import bench_security

        result = bench_security(write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "load":
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.load import bench_load

        result = bench_load(seconds=args.seconds, write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "engine":  # docs/engine-integration.md's listings in Mesa OpenGL vs evaluate --depth
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.engine import bench_engine

        result = bench_engine(validate_rig, scenes=args.scenes.split(",") if args.scenes else None,
                              write=not args.no_write, screen=args.screen, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "path":  # temporal stability along configs/paths.json (renderers.stability)
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.path import bench_path

        result = bench_path(validate_rig, frames=args.frames, screen=args.screen or (320, 180), map_side=args.map,
                            paths=args.paths.split(",") if args.paths else None,
                            methods=args.methods.split(",") if args.methods else None,
                            write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "inspect":  # the browser inspector: slider to new shadows on screen (headless chromium)
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.inspect import bench_inspect

        result = bench_inspect(write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "throughput":  # path jobs' frames/s per method, local pool and Ray (service.bench.throughput)
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.throughput import bench_throughput

        result = bench_throughput(validate_rig, frames=args.frames or 1000, screen=args.screen or (320, 180),
                                  map_side=args.map, methods=args.methods.split(",") if args.methods else None,
                                  write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "budget":  # what a rig's lights need: rig budget split vs per-light (service.bench.budget)
        # lazy: the server stack (an extra) loads only for the command that runs, not for --help
        from ..service.bench.budget import bench_budget

        result = bench_budget(validate_rig, scenes=args.scenes, screen=args.screen or (320, 180), map_side=args.map,
                              write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    elif args.bench == "limits":  # solve time of the largest rigs the request-cost limits admit (service.bench.limits)
        from ..service.bench.limits import bench_limits  # lazy: the server stack loads only for the command that runs

        result = bench_limits(validate_rig, runs=args.runs or 3, write=not args.no_write)
    elif args.bench == "hostile":  # the whole seeded corpus of damaged uploads against a real server
        from ..service.bench.hostile import bench_hostile  # lazy: the server stack loads only for the command that runs

        result = bench_hostile(write=not args.no_write, log=lambda m: print(m, file=sys.stderr))
    else:  # argparse restricts choices
        raise CliError(f"unknown benchmark {args.bench!r}")
    if args.json:
        print(dumps(result, indent=2))
    else:
        print(result["table"])
    return 0


def add_bench_parser(sub) -> None:
    """The `bench` subcommand of the CLI's parser."""
    sp = sub.add_parser("bench", help="run a benchmark, print its table and write it to BENCHMARKS.md")
    sp.add_argument("bench", choices=["coarse", "quality", "solvers", "trust", "load", "batch", "security", "engine", "path",
                                       "throughput", "inspect", "budget", "heldout", "limits", "hostile",
                                       "engine-truth", "solve-time", "engines"])
    sp.add_argument("--frames", type=int, default=None, help="path: frames per path (default: configs/paths.json's samples); "
                    "throughput: frames of the long path (default 1000)")
    sp.add_argument("--paths", default=None, help="path: comma-separated path names from configs/paths.json")
    sp.add_argument("--methods", default=None, help="path: comma-separated methods (default: stable_csm, focused, "
                    "lispsm, optimized, optimized_hysteresis and path where available)")
    sp.add_argument("--map", type=int, default=1024, help="path: texels per side of one map (4 cascades share its budget)")
    sp.add_argument("--seconds", type=float, default=60.0, help="load: seconds of concurrent load per workload")
    sp.add_argument("--lights", type=int, default=None, help="quality, solvers, trust: number of light directions (rigs)")
    sp.add_argument("--part", choices=["single", "cascades", "all", "tune", "matrix"], default="all",
                    help="quality: one map per method, 4 cascades under one budget, or both; engines: tune in three.js, "
                    "the custom-matrix modules in three.js and Babylon.js (matrix), or both")
    sp.add_argument("--runs", type=int, default=None, help="coarse: warm runs per scene (default 20); limits: runs per rig (default 3); the median is reported")
    sp.add_argument("--scenes", default=None, help="comma-separated scene names from configs/benchmarks.json "
                    "(quality --corpus: from configs/corpus.json)")
    sp.add_argument("--corpus", action="store_true", help="quality, solvers: every scene of configs/corpus.json")
    sp.add_argument("--screen", type=parse_wxh, default=None, metavar="WxH",
                    help="quality --corpus: the rig's resolution (default: configs/benchmarks.json quality_corpus.screen)")
    sp.add_argument("--cascade-lights", type=int, default=None, metavar="N",
                    help="quality --corpus: 4 cascades on the first N suns (default: quality_corpus.cascade_lights)")
    sp.add_argument("--hd-lights", type=int, default=None, metavar="N",
                    help="quality --corpus: outside pixels at 1920x1080 on the first N suns (0: off; default: "
                    "quality_corpus.outside_check.lights)")
    sp.add_argument("--reuse", nargs="?", const="same", choices=["same", "any"], default=None,
                    help="quality --corpus: take a scene's stored result (out/bench/quality-corpus/) when scene, rig, "
                    "settings and code are unchanged; `any`: whatever code measured it (named in the section)")
    sp.add_argument("--engine", choices=["three", "babylon"], default="three",
                    help="engines: the real engine tune's settings are rendered in (default three)")
    sp.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    sp.add_argument("--json", action="store_true", help="print the results as one JSON object")
    sp.set_defaults(func=cmd_bench)
