"""`make mutate`: sampled mutation testing with cosmic-ray's operators (issue 15).

The checkout is shared, so mutants are never written into it: the folders are copied into a scratch
directory (out/mutation/work-<folders>), an import shim there (`_import/shadowopt/<folder>` -> the copies) is put
first on PYTHONPATH so the tests import the mutated copy instead of the editable install, and cosmic-ray's
`mutate_and_test` mutates, runs the mapped tests and restores each file in that copy.

tests/mutation/config.json maps each module to the tests that cover it (files, node IDs, or "@name" for a list in
its test_groups; only those run per mutant) and, for a big module, the definitions to mutate ("only"). The mutants
are sampled per folder with a fixed seed (each folder its own random stream, so `--folders` does not change a
folder's sample, and a larger `--per-folder` extends the smaller sample). Mutations inside annotations of a module with `from __future__ import annotations` that nothing
evaluates (no pydantic / FastAPI / get_type_hints in it) are skipped: they cannot change behaviour. Each module's
tests run unmutated first: a failing set is reported and its mutants skipped; the time it took sets the mutant's
timeout, max(60 s, 4 x baseline), also given to pytest-timeout (a hang counts as killed, as in cosmic-ray).

    python tests/mutation/run.py                            # every folder, the sample in tests/mutation/config.json
    python tests/mutation/run.py --folders solvers --per-folder 70 --resume
    python tests/mutation/run.py --budget 600 --per-folder 5
    python tests/mutation/run.py --only ID [ID ...]         # re-run given mutants (IDs as in results.json)
    python tests/mutation/run.py --list                     # the sample and each mutant's tests; runs nothing

Two runs over different folders can go at the same time (each its own --work copy): every result is merged into
tests/mutation/results.json by mutant ID under an fcntl lock as soon as it is known, and the reports
(tests/mutation/survivors.md, the score table between the markers in TESTING.md) are recomputed from the whole
merged file. A sample run replaces the earlier results of its folders (`--resume` keeps them and skips the mutants
already run); `--only` replaces just the given IDs.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import fcntl
import hashlib
import json
import math
import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

from cosmic_ray.commands.init import _all_work_items
from cosmic_ray.mutating import mutate_and_test
from cosmic_ray.work_item import TestOutcome, WorkerOutcome

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results.json"
CONFIG = HERE / "config.json"  # the sample, the module -> tests map, the budget, the security row
LOCK = ROOT / "out" / "mutation" / "results.lock"
FOLDERS = ("api", "service", "renderers", "solvers", "configs")
BEGIN, END = "<!-- mutation:begin -->", "<!-- mutation:end -->"
MIN_TIMEOUT, TIMEOUT_FACTOR, DEFAULT_TIMEOUT = 60.0, 4.0, 420.0
# a module that evaluates annotations at run time: its annotation mutants are real
EVALUATES_ANNOTATIONS = ("pydantic", "fastapi", "get_type_hints", "get_annotations", "__annotations__")


def make_work(work: Path) -> None:
    """A scratch copy of the package folders and the tests, with an import shim in front of the editable install."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in FOLDERS + ("tests", "docs"):
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, work / name, ignore=ignore)
    for f in ROOT.iterdir():  # pyproject.toml, and the documents some tests read (BENCHMARKS.md, README.md ...)
        if f.is_file() and not f.name.startswith("."):
            shutil.copy2(f, work / f.name)
    shim = work / "_import" / "shadowopt"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("")
    for name in FOLDERS:
        (shim / name).symlink_to(work / name, target_is_directory=True)


def mutation_id(spec) -> str:
    return f"{spec.module_path}:{spec.operator_name}:{spec.occurrence}"


def folder_of(rel: str) -> str:
    return str(rel).split("/")[0]


def module_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


def unevaluated_annotation_spans(source: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) positions, as parso counts them (line from 1, column in characters), of every annotation in a
    module whose annotations are never evaluated: postponed (`from __future__ import annotations`) and no
    run-time reader of annotations in the module. Empty otherwise."""
    tree = ast.parse(source)
    postponed = any(isinstance(n, ast.ImportFrom) and n.module == "__future__"
                    and any(a.name == "annotations" for a in n.names) for n in tree.body)
    if not postponed or any(word in source for word in EVALUATES_ANNOTATIONS):
        return []
    lines = source.splitlines()

    def pos(line: int, byte_col: int) -> tuple[int, int]:  # ast counts UTF-8 bytes, parso characters
        return line, len(lines[line - 1].encode()[:byte_col].decode(errors="ignore"))

    spans = []
    for n in ast.walk(tree):
        anns = []
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.returns is not None:
            anns.append(n.returns)
        elif isinstance(n, ast.arg) and n.annotation is not None:
            anns.append(n.annotation)
        elif isinstance(n, ast.AnnAssign):
            anns.append(n.annotation)
        spans += [(pos(a.lineno, a.col_offset), pos(a.end_lineno, a.end_col_offset)) for a in anns]
    return spans


def enumerate_mutants(work: Path, modules: dict) -> tuple[dict[str, list], dict[str, int]]:
    """Every mutation cosmic-ray's `init` would make in the given modules, per module, and per module how many
    were skipped as inside unevaluated annotations."""
    by_module: dict[str, list] = {}
    skipped: dict[str, int] = {}
    old = os.getcwd()
    os.chdir(work)
    try:
        for rel, entry in modules.items():
            only = set(entry.get("only", ()))
            spans = unevaluated_annotation_spans(Path(rel).read_text())
            by_module[rel], skipped[rel] = [], 0
            for item in _all_work_items([Path(rel)], {}):
                spec = item.mutations[0]
                if only and spec.definition_name not in only:
                    continue
                if any(a <= tuple(spec.start_pos) and tuple(spec.end_pos) <= b for a, b in spans):
                    skipped[rel] += 1
                    continue
                by_module[rel].append(spec)
    finally:
        os.chdir(old)
    return by_module, skipped


def load_config(path: Path) -> dict:
    """The config with each module's "@group" test entries replaced by the group's list (test_groups)."""
    cfg = json.loads(path.read_text())
    groups = cfg.get("test_groups", {})
    for entry in cfg["modules"].values():
        entry["tests"] = [t for item in entry["tests"]
                          for t in (groups[item[1:]] if item.startswith("@") else [item])]
    return cfg


def test_command(entry: dict, timeout: float | None = None) -> list[str]:
    t = ["--timeout", str(int(math.ceil(timeout)))] if timeout else ["--timeout", "300"]
    return [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *t, *entry["tests"]]


def mutant_timeout(baseline_s: float | None) -> float:
    """max(60 s, 4 x the unmutated tests' time); 420 s when no baseline time is known."""
    return DEFAULT_TIMEOUT if baseline_s is None else max(MIN_TIMEOUT, TIMEOUT_FACTOR * baseline_s)


def run_one(work: Path, spec, entry: dict, timeout: float) -> dict:
    old = os.getcwd()
    os.chdir(work)
    t0 = time.monotonic()
    try:
        # pytest-timeout a little under cosmic-ray's, so a hung test fails in pytest (killed) before the group kill
        res = mutate_and_test([spec], " ".join(test_command(entry, max(MIN_TIMEOUT - 10, timeout - 10))), timeout)
    finally:
        os.chdir(old)
    if res.worker_outcome == WorkerOutcome.NO_TEST:
        outcome = "no-mutation"
    elif res.worker_outcome != WorkerOutcome.NORMAL or res.test_outcome == TestOutcome.INCOMPETENT:
        outcome = "incompetent"
    else:
        outcome = "killed" if res.test_outcome == TestOutcome.KILLED else "survived"
    secs = time.monotonic() - t0
    line = spec.start_pos[0]
    return {"id": mutation_id(spec), "file": str(spec.module_path), "line": line, "operator": spec.operator_name,
            "definition": spec.definition_name, "outcome": outcome, "seconds": round(secs, 1),
            "timeout": (res.output or "") == "timeout" or "Timeout" in (res.output or "")[-4000:],
            "timeout_s": round(timeout), "diff": res.diff or "", "tests": entry["tests"],
            "module_sha": module_digest(work / spec.module_path),
            "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def baseline(work: Path, cfg: dict, modules: set[str]) -> tuple[set[str], dict[str, float]]:
    """The modules whose mapped tests fail on the unmutated copy (a mutant there would count as killed for
    nothing, so they are reported and skipped), and each module's unmutated test time in seconds."""
    failing, seconds, seen = set(), {}, {}
    for rel in sorted(modules):
        cmd = test_command(cfg["modules"][rel])
        key = " ".join(cmd)
        if key not in seen:
            t0 = time.monotonic()
            ok = subprocess.run(cmd, cwd=work, capture_output=True).returncode == 0
            seen[key] = (ok, time.monotonic() - t0)
        ok, secs = seen[key]
        seconds[rel] = round(secs, 1)
        if not ok:
            failing.add(rel)
    return failing, seconds


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval for k of n (the sample's uncertainty on the score)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def table(results: list[dict], population: dict[str, int], header: str) -> str:
    rows = ["| folder | mutants in population | run | killed | survived | equivalent | score | 95% interval |",
            "|---|---|---|---|---|---|---|---|"]
    tot = [0, 0, 0, 0, 0]
    for folder in sorted(set(population) | {folder_of(r["file"]) for r in results}):
        rs = [r for r in results if folder_of(r["file"]) == folder and r["outcome"] in ("killed", "survived")]
        k = sum(r["outcome"] == "killed" for r in rs)
        eq = sum(r["outcome"] == "survived" and bool(r.get("equivalent")) for r in rs)
        s = len(rs) - k - eq
        n = len(rs) - eq  # equivalent mutants leave the denominator
        lo, hi = wilson(k, n)
        pop = population.get(folder, 0)
        rows.append(f"| {folder}/ | {pop} | {len(rs)} | {k} | {s} | {eq} | "
                    f"{(k / n if n else 0):.0%} | {lo:.0%}-{hi:.0%} |")
        for i, v in enumerate((pop, len(rs), k, s, eq)):
            tot[i] += v
    security = json.loads(CONFIG.read_text()).get("security_modules", [])
    rs = [r for r in results if r["file"] in security and r["outcome"] in ("killed", "survived")]
    if rs:  # the second bar: the resolver, auth, tenant checks and rate limits on their own
        k = sum(r["outcome"] == "killed" for r in rs)
        eq = sum(r["outcome"] == "survived" and bool(r.get("equivalent")) for r in rs)
        lo, hi = wilson(k, len(rs) - eq)
        rows.append(f"| of them resolver/auth/tenant/rate limit ({len(security)} modules) | | {len(rs)} | {k} | "
                    f"{len(rs) - k - eq} | {eq} | {(k / (len(rs) - eq) if len(rs) > eq else 0):.0%} | {lo:.0%}-{hi:.0%} |")
    n = tot[1] - tot[4]
    lo, hi = wilson(tot[2], n)
    rows.append(f"| **all** | {tot[0]} | {tot[1]} | {tot[2]} | {tot[3]} | {tot[4]} | "
                f"{(tot[2] / n if n else 0):.0%} | {lo:.0%}-{hi:.0%} |")
    return header + "\n\n" + "\n".join(rows) + "\n"


@contextlib.contextmanager
def locked():
    """An exclusive fcntl lock around a read-modify-write of results.json and the reports (several runs at once)."""
    LOCK.parent.mkdir(parents=True, exist_ok=True)
    with open(LOCK, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def load_results() -> dict:
    if RESULTS.exists():
        data = json.loads(RESULTS.read_text())
        data.setdefault("meta", {})
        return data
    return {"meta": {}, "results": []}


def merge(new: list[dict], drop=lambda r: False, run: dict | None = None, population=None, skipped=None) -> dict:
    """Under the lock: results.json's results, minus those `drop` selects, updated with `new` by ID; the run's
    record and the folders' population merged into meta; then every report recomputed from the merged file."""
    with locked():
        data = load_results()
        by_id = {r["id"]: r for r in data["results"] if not drop(r)}
        by_id.update({r["id"]: r for r in new})
        meta = data["meta"]
        for key, new_counts in (("population", population), ("annotation_skipped", skipped)):
            counts = {m: n for m, n in meta.get(key, {}).items() if "/" in m}  # per module: folders sum them
            counts.update(new_counts or {})
            meta[key] = counts
        if run is not None:
            runs = [x for x in meta.get("runs", []) if x.get("key") != run["key"]]
            meta["runs"] = (runs + [run])[-8:]
        for k in ("when", "seed", "run", "seconds", "load"):  # the one-run meta of earlier versions
            meta.pop(k, None)
        data = {"meta": meta, "results": sorted(by_id.values(), key=lambda r: r["id"])}
        write_reports(data)
    return data


def write_reports(data: dict) -> None:
    equivalent = json.loads((HERE / "equivalent.json").read_text()) if (HERE / "equivalent.json").exists() else {}
    results, meta = data["results"], data["meta"]
    population = {}
    mapped = json.loads(CONFIG.read_text())["modules"]
    for rel, n in meta.get("population", {}).items():
        if rel in mapped:
            population[folder_of(rel)] = population.get(folder_of(rel), 0) + n
    stale = 0
    for r in results:
        r["equivalent"] = r["outcome"] == "survived" and r["id"] in equivalent
        src = ROOT / r["file"]
        r["stale"] = bool(r.get("module_sha")) and (not src.exists() or module_digest(src) != r["module_sha"])
        stale += r["stale"]
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(RESULTS)
    out = ["# Surviving mutants", "",
           "Written by `make mutate` from the merged tests/mutation/results.json. Each is killed by a test (re-run "
           "with `--only ID`; tests/mutation/config.json's test_groups list those written for survivors) or listed "
           "in tests/mutation/equivalent.json with the reason it is equivalent. \"stale\": the module changed since the mutant ran (re-run it).", ""]
    for r in results:
        if r["outcome"] != "survived":
            continue
        out += [f"## `{r['id']}` ({r['file']}:{r['line']}, in `{r['definition']}`)"
                + (f" - equivalent: {equivalent[r['id']]}" if r["equivalent"] else "")
                + (" - stale" if r["stale"] else ""),
                "", "```diff", "\n".join(l for l in r["diff"].splitlines() if not l.startswith("--- mutation")),
                "```", ""]
    (HERE / "survivors.md").write_text("\n".join(out))
    runs = meta.get("runs", [])
    counted = sum(r["outcome"] in ("killed", "survived") for r in results)
    desc = "; ".join(f"{x['when']} {x['kind']} {','.join(x['folders'])} (seed {x['seed']}, {x['ran']} run, "
                     f"{x['seconds']:.0f} s, load {x['load']})" for x in runs[-4:])
    skipped = sum(n for rel, n in meta.get("annotation_skipped", {}).items() if rel in mapped)
    hdr = (f"`make mutate` results ({counted} mutants run of {sum(population.values())} in the mapped modules; "
           f"{skipped} more inside never-evaluated annotations skipped"
           + (f"; stale, their module changed since they ran: {stale}" if stale else "")
           + f"). Latest runs: {desc}.")
    testing = ROOT / "TESTING.md"
    text = testing.read_text() if testing.exists() else f"# Testing\n\n{BEGIN}\n{END}\n"
    if BEGIN in text and END in text:
        a, b = text.index(BEGIN) + len(BEGIN), text.index(END)
        text = text[:a] + "\n" + table(results, population, hdr) + text[b:]
        testing.write_text(text)


def sample(by_folder: dict[str, list], folders, per_folder: dict[str, int], seed: int) -> list:
    """Per folder, the first n of the folder's mutants in an order shuffled by (seed, folder): independent of the
    other folders, and a larger n extends a smaller one."""
    chosen = []
    for folder in sorted(folders):
        specs = sorted(by_folder.get(folder, []), key=mutation_id)
        random.Random(f"{seed}:{folder}").shuffle(specs)
        chosen += specs[:per_folder.get(folder, 0)]
    random.Random(seed).shuffle(chosen)  # a budget cut then leaves every folder sampled
    return chosen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--folders", nargs="+", choices=FOLDERS, help="only these top folders (default: all mapped)")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--per-folder", type=int, help="mutants sampled per folder (overrides the config)")
    ap.add_argument("--budget", type=float, help="wall-clock seconds; stops starting new mutants after it")
    ap.add_argument("--timeout", type=float, help="seconds per mutant's tests (default: max(60, 4 x the "
                    "module's unmutated test time); a timeout kills")
    ap.add_argument("--only", nargs="*", help="mutant IDs to (re-)run; merged into results.json")
    ap.add_argument("--resume", action="store_true", help="keep the folders' earlier results and skip the mutants "
                    "already run (extends a sample)")
    ap.add_argument("--prune", action="store_true", help="with --resume: drop the folders' results that are not "
                    "in this sample (e.g. --only re-runs of another sample's mutants), so the table scores this sample")
    ap.add_argument("--reverse", action="store_true", help="run the sample from its end (a second process on "
                    "the same folders with --resume: each skips what the other has written)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of each module's tests "
                    "(the timeouts then come from the last recorded baseline times)")
    ap.add_argument("--work", help="scratch copy (default out/mutation/work-<folders>)")
    ap.add_argument("--report", action="store_true", help="only recompute the reports from results.json")
    ap.add_argument("--list", action="store_true", help="only list the sampled mutants (ID, line, definition) "
                    "and the test files each would run; runs nothing and writes no result")
    args = ap.parse_args(argv)
    if args.report:
        merge([])
        return 0
    cfg = load_config(Path(args.config))
    seed = cfg["seed"] if args.seed is None else args.seed
    budget = cfg["budget_s"] if args.budget is None else args.budget
    mapped = sorted({folder_of(m) for m in cfg["modules"]})
    folders = sorted(args.folders) if args.folders else mapped
    if args.only:
        folders = sorted({folder_of(i.split(":")[0]) for i in args.only})
    tag = f"only-{os.getpid()}" if args.only else "-".join(folders)  # --only runs may overlap any other run
    work = (Path(args.work) if args.work else ROOT / "out" / "mutation" / f"work-{tag}").resolve()  # absolute:
    # PYTHONPATH below must hold from inside it
    make_work(work)
    os.environ["PYTHONPATH"] = str(work / "_import")  # the tests import the mutated copy
    probe = subprocess.run([sys.executable, "-c", "import shadowopt.solvers as m; print(m.__path__[0])"],
                           cwd=work, capture_output=True, text=True)
    if not probe.stdout.strip().startswith(str(work)):
        print(f"the scratch copy is not what the tests import ({probe.stdout.strip() or probe.stderr[-300:]})",
              file=sys.stderr)
        return 2
    wanted = ({i.split(":")[0] for i in args.only} if args.only
              else {m for m in cfg["modules"] if folder_of(m) in folders})
    unknown = sorted(m for m in wanted if m not in cfg["modules"])
    if unknown:
        print(f"not mapped in {args.config}: {unknown}", file=sys.stderr)
        return 2
    by_module, skipped = enumerate_mutants(work, {m: cfg["modules"][m] for m in sorted(wanted)})
    population = {m: len(v) for m, v in by_module.items()}
    by_folder: dict[str, list] = {}
    for m, v in by_module.items():
        by_folder.setdefault(folder_of(m), []).extend(v)
    index = {mutation_id(s): s for v in by_module.values() for s in v}
    previous = load_results()
    done = {r["id"] for r in previous["results"] if r["outcome"] in ("killed", "survived")}
    if args.only is not None:
        missing = [i for i in args.only if i not in index]
        if missing:
            print(f"unknown mutant id(s): {missing}", file=sys.stderr)
            return 2
        chosen = [index[i] for i in args.only]
        drop = lambda r: False  # noqa: E731
    else:
        per = {f: (args.per_folder if args.per_folder is not None else cfg["per_folder"].get(f, 0)) for f in folders}
        chosen = sample(by_folder, folders, per, seed)
        in_sample = {mutation_id(s) for s in chosen}
        if args.resume:
            chosen = [s for s in chosen if mutation_id(s) not in done]
            drop = ((lambda r: folder_of(r["file"]) in folders and r["id"] not in in_sample) if args.prune  # noqa: E731
                    else (lambda r: False))
        else:
            drop = lambda r: folder_of(r["file"]) in folders  # noqa: E731
    if args.list:
        for spec in chosen:
            rel = str(spec.module_path)
            print(f"{mutation_id(spec)} (line {spec.start_pos[0]}, {spec.definition_name}): "
                  f"{' '.join(cfg['modules'][rel]['tests'])}")
        print(f"{len(chosen)} mutants (seed {seed}; folders {','.join(folders)})")
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
        return 0
    t0 = time.monotonic()
    run = {"key": f"{os.getpid()}@{time.time():.0f}", "kind": "only" if args.only else "sample",
           "folders": folders, "seed": seed, "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "ran": 0, "seconds": 0.0, "load": " ".join(f"{x:.1f}" for x in os.getloadavg())}
    base_s = dict(previous["meta"].get("baseline_s", {}))
    if args.no_baseline:
        broken = set()
    else:
        broken, secs = baseline(work, cfg, {str(s.module_path) for s in chosen})
        base_s.update(secs)
    for rel in sorted(broken):
        print(f"baseline: the tests mapped to {rel} fail without any mutant: its mutants are not run", flush=True)
    chosen = [s for s in chosen if str(s.module_path) not in broken]
    if args.reverse:
        chosen.reverse()
    with locked():
        data = load_results()
        data["meta"].setdefault("baseline_s", {}).update(base_s)
        RESULTS.write_text(json.dumps(data, indent=1) + "\n")
    merge([], drop=drop, run=run, population=population, skipped=skipped)
    results = []
    for i, spec in enumerate(chosen):
        if time.monotonic() - t0 > budget:
            print(f"budget of {budget:.0f} s reached: {len(chosen) - i} mutants not run", flush=True)
            break
        if args.resume:
            with locked():
                now_done = {r["id"] for r in load_results()["results"] if r["outcome"] in ("killed", "survived")}
            if mutation_id(spec) in now_done:  # another process on the same sample ran it meanwhile
                continue
        rel = str(spec.module_path)
        timeout = args.timeout or mutant_timeout(base_s.get(rel))
        r = run_one(work, spec, cfg["modules"][rel], timeout)
        results.append(r)
        run.update(ran=len(results), seconds=round(time.monotonic() - t0),
                   load=" ".join(f"{x:.1f}" for x in os.getloadavg()))
        merge([r], run=run)
        print(f"[{i + 1}/{len(chosen)}] {r['outcome']:11s} {r['seconds']:6.1f}s {r['id']} "
              f"(line {r['line']}, {r['definition']})" + (" TIMEOUT" if r["timeout"] else ""), flush=True)
    run.update(seconds=round(time.monotonic() - t0), load=" ".join(f"{x:.1f}" for x in os.getloadavg()))
    merge([], run=run)
    for r in results:
        if r["outcome"] == "survived":
            print(f"SURVIVED {r['id']}\n{r['diff']}")
    if args.only and not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
