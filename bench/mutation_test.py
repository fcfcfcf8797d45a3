"""Mutation testing of the modules whose bugs the tests must catch; prints kill rates and survivors.

Uses cosmic-ray (works on Python 3.11, mutates one module file at a time, and the set of mutants
can be scoped to the functions that matter). Runs in a copy of the source tree, never in the
working tree: cosmic-ray edits the file under test in place. The copy is put first on
``PYTHONPATH`` (``uwcam/drivers`` becomes a link to ``drivers/``, as the installed package
maps it), so the tests import the mutated copy and not the editable install.

Each module is tested with a fast subset of the suite (the tests that exercise it), ``-x`` and
``-p no:randomly``. Operators are a mutmut-like subset of cosmic-ray's (one natural replacement
per operator: + → −, < → ≤, == → !=, and → or, numbers ±1, ``not`` added or removed, …) rather
than every operator into every other one, which would multiply the run time by ten for mutants
that say nothing new.

Usage (slow: minutes per module on a small machine; not part of the CI gate):

    .venv/bin/python bench/mutation_test.py                 # every module
    .venv/bin/python bench/mutation_test.py rangefinder lamp # some of them
    .venv/bin/python bench/mutation_test.py --list

Results: bench/mutation/<name>.sqlite (cosmic-ray session), a summary printed per module and
written to bench/mutation/results.json. Survivors judged equivalent are explained in
bench/mutation/SURVIVORS.md.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "mutation"
COSMIC_RAY = str(Path(sys.executable).with_name("cosmic-ray"))
PYTEST = f"{sys.executable} -m pytest -x -q -p no:randomly -p no:cacheprovider"

# One natural replacement per operator, as mutmut does.
OPERATORS = re.compile(
    r"core/(ReplaceBinaryOperator_(Add_Sub|Sub_Add|Mul_Div|Div_Mul|Pow_Mul|FloorDiv_Div|Mod_FloorDiv"
    r"|BitOr_BitAnd|BitAnd_BitOr|BitXor_BitOr|LShift_RShift|RShift_LShift)"
    r"|ReplaceComparisonOperator_(Eq_NotEq|NotEq_Eq|Lt_LtE|LtE_Lt|Gt_GtE|GtE_Gt|Is_IsNot|IsNot_Is)"
    r"|ReplaceUnaryOperator_(USub_UAdd|Delete_Not|Delete_Invert|Delete_USub)"
    r"|AddNot|ReplaceTrueWithFalse|ReplaceFalseWithTrue|ReplaceAndWithOr|ReplaceOrWithAnd"
    r"|ReplaceBreakWithContinue|ReplaceContinueWithBreak|NumberReplacer|ZeroIterationForLoop)$"
)


@dataclass
class Target:
    path: str
    """Module file, relative to the repository root."""
    tests: str
    """pytest arguments: the fast subset that exercises the module."""
    only: tuple[str, ...] = ()
    """Qualified names of the functions/classes to mutate (all of the module when empty)."""
    env: dict[str, str] = field(default_factory=dict)
    timeout_s: float = 120.0
    annotations_inert: bool = True
    """False where FastAPI reads handler signatures (request models, dependencies)."""


TARGETS: dict[str, Target] = {
    "optics.noise": Target("uwcam/optics/noise.py", "tests/test_independent_noise.py"),
    "optics.transform": Target("uwcam/optics/transform.py", "tests/test_independent_estimator.py"),
    "optics.fusion": Target("uwcam/optics/fusion.py", "tests/test_independent_estimator.py"),
    "optics.reflectance": Target("uwcam/optics/reflectance.py", "tests/test_independent_estimator.py"),
    "optics.geometry": Target("uwcam/optics/geometry.py", "tests/test_independent_geometry.py"),
    "optics.validity": Target("uwcam/optics/validity.py", "tests/test_independent_validity.py tests/test_validity.py"),
    "ranging": Target("uwcam/ranging.py", "tests/test_independent_estimator.py tests/test_independent_geometry.py "
                                          "tests/test_smoothing.py tests/test_independent_validity.py "
                                          "tests/test_estimator.py tests/test_statistics.py tests/test_calibration_statistics.py "
                                          "tests/test_backscatter_terms.py tests/test_calibration_variance_edges.py "
                                          "tests/test_vehicle_mask.py::test_range_frame_masks_before_smoothing_so_the_vehicle_lends_no_range"),
    "calibration": Target("uwcam/calibration.py", "tests/test_independent_calibration.py tests/test_calibration_closed_forms.py "
                                                  "tests/test_calibration.py tests/test_calibration_statistics.py"),
    "api.security": Target("uwcam/api/security.py", "tests/test_auth.py", annotations_inert=False),
    "api.session": Target("uwcam/api/session.py", "tests/test_auth.py", annotations_inert=False),
    "api.models": Target("uwcam/api/settings.py", "tests/test_api_validation.py",
                         only=("ProcessingPatch", "patch_config"), annotations_inert=False),
    "api.lamp": Target("uwcam/api/lamp.py", "tests/test_api_validation.py", only=("LampCommand", "put_lamp"),
                       annotations_inert=False),
    "rangefinder": Target("drivers/rangefinder.py", "tests/test_nmea.py",
                          only=("nmea_checksum_ok", "_finite", "parse_ascii_range", "AsciiRangefinder._poll")),
    "lamp": Target("drivers/lamp.py", "tests/test_lamp_protocol.py",
                   only=("LampReplies", "load_protocol", "SerialLamp._transaction", "SerialLamp.status",
                         "SerialLamp.set_intensity", "SerialLamp._remember", "SerialLamp.on", "SerialLamp.off")),
    # The compiled kernels run as plain Python here (NUMBA_DISABLE_JIT): each mutant would
    # otherwise need a fresh compilation, and the arithmetic being mutated is the same. Compiled,
    # a float32 division by zero is silent (error_model="numpy"); as Python it warns: ignored.
    "optics.kernels": Target("uwcam/optics/kernels.py", "tests/test_independent_estimator.py tests/test_independent_geometry.py "
                                                        "tests/test_independent_validity.py -W ignore::RuntimeWarning",
                             env={"NUMBA_DISABLE_JIT": "1"}),
}


def _spans(source: str, names: tuple[str, ...]) -> list[tuple[int, int]]:
    """Line ranges (first, last) of the named top-level functions/classes or Class.method."""
    tree = ast.parse(source)
    spans = []

    def visit(body, prefix):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{node.name}"
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if name in names:
                    spans.append((first, node.end_lineno))
                if isinstance(node, ast.ClassDef):
                    visit(node.body, f"{name}.")

    visit(tree.body, "")
    if len(spans) < len(names):
        raise SystemExit(f"some of {names} are not in the module any more; update TARGETS")
    return spans


def _inert(source: str) -> tuple[set[int], list[tuple[tuple[int, int], tuple[int, int]]]]:
    """Where a mutant cannot change behaviour: docstring lines, and function annotations (never
    evaluated under ``from __future__ import annotations``) as ((line, col), (end_line, end_col)).
    Annotations of fields are kept: pydantic evaluates them, bounds and all."""
    lines: set[int] = set()
    spans = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            lines.update(range(node.lineno, node.end_lineno + 1))
        annotations = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.returns is not None:
            annotations.append(node.returns)
        if isinstance(node, ast.arg) and node.annotation is not None:
            annotations.append(node.annotation)
        spans += [((a.lineno, a.col_offset), (a.end_lineno, a.end_col_offset)) for a in annotations]
    return lines, spans


def _copy_tree(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, check=True,
                           capture_output=True, text=True).stdout.split("\n")
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    (dest / "uwcam" / "drivers").symlink_to("../drivers")  # the package-dir mapping of pyproject.toml
    (dest / "uwcam" / "calibration_rigs").symlink_to("../calibration_rigs")


def run_target(name: str, target: Target, tree: Path, env: dict[str, str]) -> dict:
    import cosmic_ray.work_db as wdb
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    OUT.mkdir(parents=True, exist_ok=True)
    session = OUT / f"{name}.sqlite"
    session.unlink(missing_ok=True)
    module = tree / target.path
    source = module.read_text()
    cmd_env = {**env, **target.env}
    config = tree / f"cr-{name}.toml"
    test_command = f"{PYTEST} {target.tests}"
    config.write_text(
        "[cosmic-ray]\n"
        f"module-path = {json.dumps(target.path)}\n"
        f"timeout = {target.timeout_s}\n"
        "excluded-modules = []\n"
        f"test-command = {json.dumps(test_command)}\n"
        "[cosmic-ray.distributor]\nname = \"local\"\n"
    )
    t0 = time.monotonic()
    base = subprocess.run(test_command, shell=True, cwd=tree, env=cmd_env, capture_output=True, text=True)
    if base.returncode != 0:
        print(f"{name}: the unmutated tests fail; fix them first\n{base.stdout[-2000:]}{base.stderr[-2000:]}")
        return {"module": target.path, "error": "baseline failed"}
    baseline_s = time.monotonic() - t0
    subprocess.run([COSMIC_RAY, "init", str(config), str(session)], cwd=tree, env=cmd_env,
                   check=True, capture_output=True)
    spans = _spans(source, target.only) if target.only else None
    prose, annotations = _inert(source)
    skipped = 0
    with wdb.use_db(str(session), wdb.WorkDB.Mode.open) as db:
        for item in list(db.pending_work_items):
            spec = item.mutations[0]
            line = spec.start_pos[0]
            keep = OPERATORS.match(spec.operator_name) and line not in prose
            if target.annotations_inert:
                keep = keep and not any(a <= tuple(spec.start_pos) < b for a, b in annotations)
            if keep and spans is not None:
                keep = any(a <= line <= b for a, b in spans)
            if not keep:
                db.set_result(item.job_id, WorkResult(worker_outcome=WorkerOutcome.SKIPPED))
                skipped += 1
        total = db.num_work_items - skipped
    print(f"{name}: {total} mutants ({skipped} out of scope), tests take {baseline_s:.1f} s unmutated", flush=True)
    execute(session, tree, target)
    summary = summarise(name, target, source)
    summary["minutes"] = round((time.monotonic() - t0) / 60, 1)
    print(f"{name}: {summary['killed']}/{summary['mutants']} killed ({100 * summary['kill_rate']:.1f} %), "
          f"{summary['survived']} survived, {summary['minutes']} min", flush=True)
    for s in summary["survivors"]:
        print(f"    line {s['line']:4d} {s['operator']:<40s} #{s['occurrence']}: {s['code'][:90]}")
    return summary


# Imported once by the parent so that every forked test run starts with them loaded; uwcam itself
# is never imported by the parent, so each child imports the mutated module afresh.
PRELOAD = ("numpy", "numba", "cv2", "pydantic", "fastapi", "starlette", "uvicorn", "httpx", "websockets", "yaml",
           "tifffile", "serial", "jerlov", "brping", "genicam", "harvesters", "pytest", "hypothesis",
           "_hypothesis_pytestplugin", "schemathesis", "schemathesis.pytest.plugin")


def _run_forked(tree: Path, args: list[str], env: dict[str, str], timeout_s: float) -> str:
    """Run pytest with ``args`` in a forked child of this (pre-loaded) process: 'survived' when it
    passes, 'killed' when it fails or runs past ``timeout_s``, 'incompetent' when it cannot run."""
    pid = os.fork()
    if pid == 0:  # child: never returns
        code = 4
        saved_stderr = os.dup(2)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            os.chdir(tree)
            os.environ.update(env)
            sys.dont_write_bytecode = True
            sys.path.insert(0, str(tree))
            import numba

            numba.config.reload_config()  # NUMBA_DISABLE_JIT may be set for this module
            import pytest

            code = int(pytest.main(args))
        except BaseException:  # report why the run could not start, on the parent's stderr
            import traceback

            os.write(saved_stderr, traceback.format_exc().encode())
        finally:
            os._exit(code)
    deadline = time.monotonic() + timeout_s
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            code = os.waitstatus_to_exitcode(status)
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            return "killed"
        time.sleep(0.05)
    # pytest: 0 passed, 1 tests failed; 2 interrupted, 3 internal error, 4 usage error, 5 none collected.
    return {0: "survived", 1: "killed"}.get(code, "incompetent")


def execute(session: Path, tree: Path, target: Target, only: set[str] | None = None) -> None:
    """Apply each pending mutant in the copy, run the module's tests in a forked child, record the outcome."""
    import shlex

    import cosmic_ray.plugins
    import cosmic_ray.work_db as wdb
    from cosmic_ray.mutating import use_mutation
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome, WorkResult

    for module in PRELOAD:
        try:
            __import__(module)
        except ImportError:
            pass
    # Pre-loaded pytest plugins (anyio, hypothesis, schemathesis) cannot have their own asserts
    # rewritten: harmless, and not a failure of the tests.
    args = shlex.split(target.tests) + ["-x", "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
                                        "-W", "ignore::pytest.PytestAssertRewriteWarning"]
    unmutated = _run_forked(tree, args, target.env, target.timeout_s)
    if unmutated != "survived":
        raise SystemExit(f"{target.path}: the unmutated tests do not pass in a forked run ({unmutated}); cannot judge mutants")
    with wdb.use_db(str(session), wdb.WorkDB.Mode.open) as db:
        # In a random (seeded) order: a run stopped early has then judged a fair sample of the module.
        pending = sorted((i for i in db.pending_work_items if only is None or i.job_id in only), key=lambda item: item.job_id)
        random.Random(0).shuffle(pending)
        for item in pending:
            spec = item.mutations[0]
            operator = cosmic_ray.plugins.get_operator(spec.operator_name)(**(spec.operator_args or {}))
            with use_mutation(tree / spec.module_path, operator, spec.occurrence) as (original, mutated):
                if mutated is None:
                    db.set_result(item.job_id, WorkResult(worker_outcome=WorkerOutcome.NO_TEST))
                    continue
                outcome = _run_forked(tree, args, target.env, target.timeout_s)
            import difflib

            diff = "".join(difflib.unified_diff(original.splitlines(True), mutated.splitlines(True), n=0))
            db.set_result(item.job_id, WorkResult(worker_outcome=WorkerOutcome.NORMAL, test_outcome=TestOutcome(outcome),
                                                  diff=diff))


def summarise(name: str, target: Target, source: str) -> dict:
    """Kill rate and survivors of a finished session (bench/mutation/<name>.sqlite)."""
    import cosmic_ray.work_db as wdb
    from cosmic_ray.work_item import WorkerOutcome

    session = OUT / f"{name}.sqlite"
    survivors, killed, incompetent, total, pending = [], 0, 0, 0, 0
    lines = source.splitlines()
    with wdb.use_db(str(session), wdb.WorkDB.Mode.open) as db:
        done = {item.job_id for item, _ in db.completed_work_items}
        pending = sum(1 for item in db.work_items if item.job_id not in done)
        for item, result in db.completed_work_items:
            if result.worker_outcome == WorkerOutcome.SKIPPED:
                continue
            total += 1
            if result.test_outcome is not None and result.test_outcome.value == "survived":
                spec = item.mutations[0]
                line = spec.start_pos[0]
                survivors.append({"line": line, "operator": spec.operator_name.removeprefix("core/"),
                                  "occurrence": spec.occurrence, "code": lines[line - 1].strip(), "diff": result.diff})
            elif result.test_outcome is not None and result.test_outcome.value == "incompetent":
                incompetent += 1  # the mutant does not even import or run: counted as killed
                killed += 1
            else:
                killed += 1
    survivors.sort(key=lambda s: (s["line"], s["operator"]))
    rate = killed / total if total else 1.0
    return {"module": target.path, "mutants": total, "killed": killed, "incompetent": incompetent,
            "survived": len(survivors), "kill_rate": round(rate, 4), "tests": target.tests, "not_run": pending,
            "survivors": survivors}


def _save(name: str, summary: dict) -> None:
    """Merge one module's summary into results.json (runs of different modules may overlap)."""
    results_file = OUT / "results.json"
    results = json.loads(results_file.read_text()) if results_file.exists() else {}
    results[name] = summary
    results_file.write_text(json.dumps(results, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("modules", nargs="*", help=f"subset of: {', '.join(TARGETS)}")
    p.add_argument("--list", action="store_true", help="list the modules and their test subsets")
    p.add_argument("--report", action="store_true", help="only summarise the sessions already in bench/mutation/")
    p.add_argument("--rerun-survivors", action="store_true",
                   help="run the current tests against the survivors (and unrun mutants) of the existing sessions only")
    args = p.parse_args(argv)
    if args.list:
        for name, t in TARGETS.items():
            print(f"{name:20s} {t.path:28s} {t.tests}")
        return 0
    unknown = [m for m in args.modules if m not in TARGETS]
    if unknown:
        p.error(f"unknown module(s) {', '.join(unknown)}; known: {', '.join(TARGETS)}")
    names = args.modules or list(TARGETS)
    if args.report or args.rerun_survivors:
        names = [n for n in names if (OUT / f"{n}.sqlite").exists()]
        if args.rerun_survivors:
            rerun(names)
        for name in names:
            _save(name, summarise(name, TARGETS[name], (ROOT / TARGETS[name].path).read_text()))
    else:
        run(names)
    results = json.loads((OUT / "results.json").read_text())
    print("\nmodule               mutants  killed  survived  kill rate")
    for name in names:
        r = results[name]
        if "error" in r:
            print(f"{name:20s} {r['error']}")
        else:
            print(f"{name:20s} {r['mutants']:7d} {r['killed']:7d} {r['survived']:9d}  {100 * r['kill_rate']:6.1f} %"
                  + (f"  ({r['not_run']} not run)" if r.get("not_run") else ""))
    return 0


def rerun(names: list[str]) -> None:
    """Forget the survivors of each session and run them again with the tests as they are now."""
    import sqlite3

    with tempfile.TemporaryDirectory(prefix="uwcam-mutation-") as tmp:
        tree = Path(tmp)
        _copy_tree(tree)
        for name in names:
            with sqlite3.connect(OUT / f"{name}.sqlite") as db:
                jobs = {row[0] for row in db.execute("SELECT job_id FROM work_results WHERE test_outcome = 'SURVIVED'")}
                db.execute("DELETE FROM work_results WHERE test_outcome = 'SURVIVED'")
            print(f"{name}: running {len(jobs)} survivors again", flush=True)
            execute(OUT / f"{name}.sqlite", tree, TARGETS[name], only=jobs)


def run(names: list[str]) -> None:
    with tempfile.TemporaryDirectory(prefix="uwcam-mutation-") as tmp:
        tree = Path(tmp)
        _copy_tree(tree)
        # No .pyc files: a mutant of the same size written within the same second as the
        # original would otherwise be shadowed by the original's cached bytecode.
        env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
        for name in names:
            _save(name, run_target(name, TARGETS[name], tree, env))


if __name__ == "__main__":
    sys.exit(main())
