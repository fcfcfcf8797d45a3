"""Mutation testing of the modules whose bugs the tests must catch; prints kill rates and survivors.

Uses cosmic-ray's operators and its list of mutants (one module file at a time; the set can be
scoped to the functions that matter), but applies and tests each mutant itself: the mutated
source is written into a private copy of the source tree (``--jobs N``: N copies, N mutants at
a time), and the module's tests run in a child forked from this process, which has numpy,
numba, OpenCV, FastAPI, pytest… already imported; uwcam itself is imported afresh by every
child, from the copy (first on ``sys.path``; ``uwcam/drivers`` links to ``drivers/`` as the
installed package maps it). A mutant then costs one pytest run of its module's subset: about a
second when a test fails early, the whole subset when it survives.

Each module is tested with a fast subset of the suite (the tests that exercise it), ``-x`` and
``-p no:randomly``. Operators are a mutmut-like subset of cosmic-ray's (one natural replacement
per operator: + → −, < → ≤, == → !=, and → or, numbers ±1, ``not`` added or removed, …) rather
than every operator into every other one, which would multiply the run time by ten for mutants
that say nothing new. Docstrings, postponed annotations and the functions a target lists in
``exclude`` (speed only, e.g. warm-up) are not mutated.

Usage (slow: minutes per module on a small machine; not part of the CI gate; on a shared
machine run it under ``nice``):

    nice -n 19 .venv/bin/python bench/mutation_test.py --jobs 2                 # every module
    nice -n 19 .venv/bin/python bench/mutation_test.py --jobs 2 ranging lamp    # some of them
    nice -n 19 .venv/bin/python bench/mutation_test.py --jobs 2 --sample 400 calibration
    nice -n 19 .venv/bin/python bench/mutation_test.py --jobs 2 --rerun-survivors ranging
    nice -n 19 .venv/bin/python bench/mutation_test.py --jobs 2 --resume calibration  # + the rest of a sample
    .venv/bin/python bench/mutation_test.py --report     # the table and the survivors, no run
    .venv/bin/python bench/mutation_test.py --list

Results: bench/mutation/results.json (per module: mutants, kills, survivors with their diffs, the
outcome of every mutant run, the hash of the source they were run on); the report prints the
kill rate over all mutants and over the mutants not judged equivalent. Survivors judged
equivalent are named and explained in bench/mutation/SURVIVORS.md (lines ``- eq MODULE
LINE:Operator:occurrence``), which the report reads.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
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
    exclude: tuple[str, ...] = ()
    """Qualified names of functions whose only effect is speed (e.g. compiling ahead of the first
    frame): not mutated. Each is explained in SURVIVORS.md ("Excluded from mutation")."""


RANGING_TESTS = ("tests/test_independent_estimator.py tests/test_independent_geometry.py "
                                          "tests/test_smoothing.py tests/test_window_light.py tests/test_independent_validity.py "
                                          "tests/test_estimator.py tests/test_statistics.py tests/test_calibration_statistics.py "
                                          "tests/test_backscatter_terms.py tests/test_calibration_variance_edges.py "
                                          "tests/test_vehicle_mask.py::test_range_frame_masks_before_smoothing_so_the_vehicle_lends_no_range "
                                          "tests/test_vehicle_mask.py::test_mask_marks_its_boxes_clipped_to_the_image_and_nothing_else "
                                          "tests/test_ranging_contracts.py tests/test_calibration_variance_weights.py "
                                          "tests/test_ranging_block_size.py "
                                          "tests/test_exposure.py::test_a_channel_exposed_m_times_ranges_exactly_as_at_the_calibration_exposure "
                                          "tests/test_exposure.py::test_integer_frames_at_other_exposures_use_the_same_correction_in_the_lookup_path "
                                          "tests/test_exposure.py::test_the_variance_is_that_of_the_raw_counts "
                                          "tests/test_exposure.py::test_gain_scales_the_signal_and_the_noise_in_counts "
                                          "tests/test_exposure.py::test_bad_exposures_are_refused tests/test_exposure_edges.py "
                                          "tests/test_ranging_gaps.py tests/test_attenuation_significance.py")
CALIBRATION_TESTS = ("tests/test_noise_beside_the_plate.py tests/test_calibration_helpers.py tests/test_independent_calibration.py tests/test_calibration_details.py "
                                                  "tests/test_calibration_closed_forms.py "
                                                  "tests/test_calibration.py tests/test_calibration_statistics.py "
                                                  "tests/test_calibration_gaps.py tests/test_calibration_fixed_pattern.py")

TARGETS: dict[str, Target] = {
    "optics.noise": Target("uwcam/optics/noise.py", "tests/test_independent_noise.py tests/test_noise_model_terms.py"),
    "optics.transform": Target("uwcam/optics/transform.py", "tests/test_independent_estimator.py"),
    "optics.fusion": Target("uwcam/optics/fusion.py", "tests/test_independent_estimator.py tests/test_attenuation_significance.py"),
    "optics.reflectance": Target("uwcam/optics/reflectance.py", "tests/test_optics_contracts.py tests/test_independent_estimator.py"),
    "optics.geometry": Target("uwcam/optics/geometry.py", "tests/test_optics_contracts.py tests/test_independent_geometry.py"),
    "optics.validity": Target("uwcam/optics/validity.py", "tests/test_independent_validity.py tests/test_validity.py tests/test_reason_codes.py"),
    "ranging": Target("uwcam/ranging/estimator.py", RANGING_TESTS, exclude=("RangeEstimator.warm_up",)),
    "ranging.smoothing": Target("uwcam/ranging/smoothing.py", RANGING_TESTS),
    # calibration.py was split in four (noise model, line fits, black patch, the whole fit): the
    # figures in bench/mutation/results.json before that are of the one module.
    "calibration": Target("uwcam/calibration/fit.py", CALIBRATION_TESTS),
    "calibration.noise_fit": Target("uwcam/calibration/noise_fit.py", CALIBRATION_TESTS),
    "calibration.line_fit": Target("uwcam/calibration/line_fit.py", CALIBRATION_TESTS),
    "calibration.black_patch": Target("uwcam/calibration/black_patch.py", CALIBRATION_TESTS),
    "api.security": Target("uwcam/api/security.py",
                           "tests/test_security_rules.py tests/test_auth.py "
                           "tests/test_hardening_second.py::test_the_throttle_counts_per_address_and_forgets_the_oldest "
                           "tests/test_hardening_second.py::test_the_throttle_waits_a_quarter_second_more_per_wrong_token_up_to_five_and_remembers_4096_addresses",
                           annotations_inert=False),
    "api.session": Target("uwcam/api/session.py",
                          "tests/test_auth.py "
                          "tests/test_hardening_second.py::test_a_flood_of_wrong_sign_ins_holds_up_neither_the_api_nor_a_right_token_from_elsewhere "
                          "tests/test_hardening_second.py::test_a_right_token_from_a_flooding_address_is_accepted_at_once_and_status_stays_responsive "
                          "tests/test_hardening_second.py::test_the_throttle_counts_per_address_and_forgets_the_oldest",
                          annotations_inert=False),
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
    # kernels.py holds the numpy path (used where numba is missing) and the dispatch; the numba
    # kernels are in kernels_numba.py.
    "optics.kernels": Target("uwcam/optics/kernels.py", "tests/test_numpy_path.py tests/test_optics_contracts.py "
                                                        "tests/test_ranging_contracts.py tests/test_independent_estimator.py "
                                                        "tests/test_independent_geometry.py tests/test_independent_validity.py "
                                                        "tests/test_kernel_edges.py tests/test_attenuation_significance.py "
                                                        "-W ignore::RuntimeWarning",
                             env={"NUMBA_DISABLE_JIT": "1"}),
    "optics.kernels_numba": Target("uwcam/optics/kernels_numba.py", "tests/test_independent_estimator.py tests/test_independent_geometry.py "
                                                                    "tests/test_independent_validity.py tests/test_backscatter_terms.py "
                                                                    "tests/test_kernel_edges.py tests/test_background_kernel_edges.py tests/test_kernel_log.py "
                                                                    "tests/test_attenuation_significance.py -W ignore::RuntimeWarning",
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


def _mutants(name: str, target: Target, tree: Path, env: dict[str, str]) -> tuple[list[dict], int]:
    """Every mutant of the module in scope, as dicts (job_id, operator, args, occurrence, line), and
    how many were left out (other operators, prose, inert annotations, outside ``only``, ``exclude``)."""
    import cosmic_ray.work_db as wdb

    source = (tree / target.path).read_text()
    with tempfile.TemporaryDirectory(prefix="uwcam-cr-") as tmp:
        session = Path(tmp) / f"{name}.sqlite"
        config = Path(tmp) / f"cr-{name}.toml"
        config.write_text(
            "[cosmic-ray]\n"
            f"module-path = {json.dumps(target.path)}\n"
            f"timeout = {target.timeout_s}\n"
            "excluded-modules = []\n"
            f"test-command = {json.dumps(PYTEST)}\n"
            "[cosmic-ray.distributor]\nname = \"local\"\n"
        )
        subprocess.run([COSMIC_RAY, "init", str(config), str(session)], cwd=tree, env=env, check=True,
                       capture_output=True)
        spans = _spans(source, target.only) if target.only else None
        excluded = _spans(source, target.exclude) if target.exclude else []
        prose, annotations = _inert(source)
        mutants, skipped = [], 0
        with wdb.use_db(str(session), wdb.WorkDB.Mode.open) as db:
            for item in db.pending_work_items:
                spec = item.mutations[0]
                line = spec.start_pos[0]
                keep = OPERATORS.match(spec.operator_name) and line not in prose
                if target.annotations_inert:
                    keep = keep and not any(a <= tuple(spec.start_pos) < b for a, b in annotations)
                if keep and spans is not None:
                    keep = any(a <= line <= b for a, b in spans)
                keep = keep and not any(a <= line <= b for a, b in excluded)
                if keep:
                    # cosmic-ray's job ids are random per session; operator and occurrence name a
                    # mutant of the same source in every run.
                    mutants.append({"job_id": f"{spec.operator_name}#{spec.occurrence}", "operator": spec.operator_name,
                                    "args": spec.operator_args or {}, "occurrence": spec.occurrence, "line": line})
                else:
                    skipped += 1
    mutants.sort(key=lambda m: m["job_id"])
    return mutants, skipped


# Imported once by the parent so that every forked test run starts with them loaded; uwcam itself
# is never imported by the parent, so each child imports the mutated module afresh.
PRELOAD = ("numpy", "numba", "cv2", "pydantic", "fastapi", "starlette", "uvicorn", "httpx", "websockets", "yaml",
           "tifffile", "serial", "jerlov", "brping", "genicam", "harvesters", "pytest", "hypothesis",
           "_hypothesis_pytestplugin", "schemathesis", "schemathesis.pytest.plugin")


def _fork_pytest(tree: Path, args: list[str], env: dict[str, str]) -> int:
    """Start pytest with ``args`` in a forked child of this (pre-loaded) process, in ``tree``; its pid."""
    pid = os.fork()
    if pid == 0:  # child: never returns
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops its children itself
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
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
    return pid


def _outcome(status: int) -> str:
    # pytest: 0 passed, 1 tests failed; 2 interrupted, 3 internal error, 4 usage error, 5 none collected.
    return {0: "survived", 1: "killed"}.get(os.waitstatus_to_exitcode(status), "incompetent")


def _test_args(target: Target) -> list[str]:
    import shlex

    # Pre-loaded pytest plugins (anyio, hypothesis, schemathesis) cannot have their own asserts
    # rewritten: harmless, and not a failure of the tests.
    return shlex.split(target.tests) + ["-x", "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
                                        "-W", "ignore::pytest.PytestAssertRewriteWarning"]


def execute(trees: list[Path], target: Target, mutants: list[dict], progress: str = "") -> dict[str, dict]:
    """Run the module's tests against each mutant, one mutant per tree copy at a time (as many in
    parallel as there are trees); returns {job_id: {"outcome", "diff"}}. Outcomes: 'killed' (a test
    failed or the run passed the timeout), 'survived', 'incompetent' (pytest could not run: the
    mutant does not import; counted as killed), 'no-op' (the operator found nothing to mutate).
    Interrupted (SIGINT), it returns the outcomes judged so far."""
    for module in PRELOAD:
        try:
            __import__(module)
        except ImportError:
            pass
    args = _test_args(target)
    # The unmutated tests, once in every copy (this also fills each copy's compilation cache).
    # A copy's first run compiles numba's kernels for it (its cache is keyed by the sources' paths):
    # where a test waits on a request that compiles (a settings change), it may time out that once.
    # A copy that fails then runs again alone (the copies compiling side by side on a small,
    # shared machine is what times a request out), twice at most.
    children = {_fork_pytest(tree, args, target.env): tree for tree in trees}
    failed = [tree for pid, tree in children.items() if _outcome(os.waitpid(pid, 0)[1]) != "survived"]
    for tree in failed:
        for attempt in (2, 3):
            outcome = _outcome(os.waitpid(_fork_pytest(tree, args, target.env), 0)[1])
            if outcome == "survived":
                break
            if attempt == 3:
                raise SystemExit(f"{target.path}: the unmutated tests do not pass in a forked run in {tree} ({outcome})")
    original = (trees[0] / target.path).read_text()
    free = list(trees)
    todo = list(reversed(mutants))
    running: dict[int, tuple[dict, Path, str, float]] = {}
    results: dict[str, dict] = {}
    t0 = time.monotonic()
    try:
        _loop(todo, free, running, results, original, args, target, mutants, progress, t0)
    except KeyboardInterrupt:  # stopped (Ctrl-C, or `timeout -s INT`): keep what was judged
        for pid, (m, tree, _, _) in running.items():
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            (tree / target.path).write_text(original)
        print(f"  {progress}stopped after {len(results)} of {len(mutants)} mutants", flush=True)
    return results


def _loop(todo: list[dict], free: list[Path], running: dict, results: dict[str, dict], original: str,
          args: list[str], target: Target, mutants: list[dict], progress: str, t0: float) -> None:
    """Keep every free tree busy with the next mutant; record each outcome as its child ends."""
    import difflib

    import cosmic_ray.plugins
    from cosmic_ray.mutating import mutate_code

    while todo or running:
        while free and todo:
            m = todo.pop()
            operator = cosmic_ray.plugins.get_operator(m["operator"])(**m["args"])
            mutated = mutate_code(original, operator, m["occurrence"])
            if mutated is None:
                results[m["job_id"]] = {"outcome": "no-op", "diff": ""}
                continue
            tree = free.pop()
            (tree / target.path).write_text(mutated)
            diff = "".join(difflib.unified_diff(original.splitlines(True), mutated.splitlines(True), n=0))
            pid = _fork_pytest(tree, args, target.env)
            running[pid] = (m, tree, diff, time.monotonic() + target.timeout_s)
        for pid in list(running):
            m, tree, diff, deadline = running[pid]
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                outcome = _outcome(status)
            elif time.monotonic() > deadline:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
                outcome = "killed"
            else:
                continue
            del running[pid]
            (tree / target.path).write_text(original)
            free.append(tree)
            results[m["job_id"]] = {"outcome": outcome, "diff": diff}
            if len(results) % 25 == 0:
                rate = (time.monotonic() - t0) / len(results)
                print(f"  {progress}{len(results)}/{len(mutants)} mutants, {rate:.1f} s each", flush=True)
        time.sleep(0.02)


def summarise(name: str, target: Target, source: str, mutants: list[dict], results: dict[str, dict],
              excluded: int) -> dict:
    """Kill rate and survivors of a run."""
    import hashlib

    lines = source.splitlines()
    survivors, killed, incompetent, total = [], 0, 0, 0
    for m in mutants:
        r = results.get(m["job_id"])
        if r is None or r["outcome"] == "no-op":
            continue
        total += 1
        if r["outcome"] == "survived":
            survivors.append({"line": m["line"], "operator": m["operator"].removeprefix("core/"),
                              "occurrence": m["occurrence"], "code": lines[m["line"] - 1].strip(), "diff": r["diff"]})
        else:
            killed += 1
            incompetent += r["outcome"] == "incompetent"
    survivors.sort(key=lambda s: (s["line"], s["operator"], s["occurrence"]))
    not_run = sum(1 for m in mutants if m["job_id"] not in results)
    return {"module": target.path, "source_sha256": hashlib.sha256(source.encode()).hexdigest(),
            "mutants": total, "killed": killed, "incompetent": incompetent, "survived": len(survivors),
            "kill_rate": round(killed / total if total else 1.0, 4), "tests": target.tests,
            "excluded_out_of_scope": excluded, "not_run": not_run, "survivors": survivors}


def _load() -> dict:
    results_file = OUT / "results.json"
    return json.loads(results_file.read_text()) if results_file.exists() else {}


def _save(name: str, summary: dict) -> None:
    """Merge one module's summary into results.json (runs of different modules may overlap)."""
    results = _load()
    results[name] = summary
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps(results, indent=1) + "\n")


def _trees(tmp: Path, jobs: int) -> list[Path]:
    trees = []
    for i in range(jobs):
        tree = tmp / f"tree{i}"
        tree.mkdir()
        _copy_tree(tree)
        trees.append(tree)
    return trees


def run(names: list[str], jobs: int, sample: int | None, rerun: bool, resume: bool = False,
        lines: set[int] | None = None) -> None:
    """Run every mutant (or a seeded random ``sample`` of them) of each module; with ``rerun``,
    only the survivors recorded in results.json (and the mutants not run then), keeping the kills."""
    with tempfile.TemporaryDirectory(prefix="uwcam-mutation-") as tmp:
        trees = _trees(Path(tmp), jobs)
        for name in names:
            target = TARGETS[name]
            t0 = time.monotonic()
            source = (ROOT / target.path).read_text()
            mutants, excluded = _mutants(name, target, trees[0], os.environ.copy())
            chosen = mutants
            previous = _load().get(name, {})
            carried: dict[str, dict] = {}
            if rerun:
                if previous.get("module") != target.path or ("runs" not in previous and previous.get("not_run")):
                    print(f"{name}: no complete earlier run of this scope in results.json; running every mutant")
                else:
                    chosen, carried = _to_rerun(source, mutants, previous, resume)
                    if lines and carried:  # survivors elsewhere keep their outcome and diff
                        diffs = {f"core/{s['operator']}#{s['occurrence']}": s["diff"] for s in previous["survivors"]}
                        carried.update({m["job_id"]: {"outcome": "survived", "diff": diffs.get(m["job_id"], "")}
                                        for m in chosen if m["line"] not in lines})
                        chosen = [m for m in chosen if m["line"] in lines]
            if sample is not None and sample < len(chosen):
                if rerun and carried:  # the survivors first, then a seeded sample of those never run
                    known = [m for m in chosen if m["job_id"] in previous.get("runs", {})]
                    fresh = [m for m in chosen if m["job_id"] not in previous.get("runs", {})]
                    chosen = known + random.Random(0).sample(fresh, max(0, min(len(fresh), sample - len(known))))
                else:
                    chosen = random.Random(0).sample(chosen, sample)
            # In a seeded random order: a run stopped early has judged a fair sample of the module.
            chosen = sorted(chosen, key=lambda m: m["job_id"])
            random.Random(1).shuffle(chosen)
            print(f"{name}: {len(mutants)} mutants ({excluded} out of scope or excluded), running {len(chosen)} "
                  f"with {jobs} job(s)", flush=True)
            results = execute(trees, target, chosen, progress=f"{name}: ")
            results = {**carried, **results}
            summary = summarise(name, target, source, mutants, results, excluded)
            summary["runs"] = {k: v["outcome"] for k, v in results.items()}
            summary["minutes"] = round((time.monotonic() - t0) / 60, 1)
            summary["jobs"] = jobs
            if rerun and carried:
                summary["note"] = f"survivors re-run on {time.strftime('%Y-%m-%d')}; kills carried from the earlier full run"
            _save(name, summary)
            print(f"{name}: {summary['killed']}/{summary['mutants']} killed ({100 * summary['kill_rate']:.1f} %), "
                  f"{summary['survived']} survived, {summary['not_run']} not run, {summary['minutes']} min", flush=True)


def _to_rerun(source: str, mutants: list[dict], previous: dict, resume: bool = False) -> tuple[list[dict], dict[str, dict]]:
    """Split the mutants into those to run again (the earlier survivors and those never run) and
    the earlier kills, kept. The earlier run must be of the same source: checked by hash, or, for
    a record without one, by every recorded survivor's diff being reproduced exactly."""
    import difflib
    import hashlib

    import cosmic_ray.plugins
    from cosmic_ray.mutating import mutate_code

    if "runs" in previous:
        if previous.get("source_sha256") != hashlib.sha256(source.encode()).hexdigest():
            print("  the module changed since the earlier run: running every mutant")
            return mutants, {}
        runs = previous["runs"]
    else:  # an older record (every mutant run, survivors listed with their diffs)
        by_key = {m["job_id"]: m for m in mutants}
        runs = {key: "killed" for key in by_key}
        for s in previous["survivors"]:
            key = f"core/{s['operator']}#{s['occurrence']}"
            m = by_key.get(key)
            if m is None:
                continue  # out of scope now (an excluded function)
            mutated = mutate_code(source, cosmic_ray.plugins.get_operator(m["operator"])(**m["args"]), m["occurrence"])
            diff = mutated and "".join(difflib.unified_diff(source.splitlines(True), mutated.splitlines(True), n=0))
            if diff != s["diff"]:
                print(f"  survivor {key} of the earlier run is not the same mutant now: running every mutant")
                return mutants, {}
            runs[key] = "survived"
    # Survivors run again; kills are kept; mutants left out of a sampled run stay out of it
    # unless ``resume`` (then they run too, after the survivors, so that --sample takes them last).
    again = [m for m in mutants if runs.get(m["job_id"]) == "survived"]
    if resume:
        again += [m for m in mutants if m["job_id"] not in runs]
    kept = {m["job_id"]: {"outcome": runs[m["job_id"]], "diff": ""} for m in mutants
            if runs.get(m["job_id"], "survived") != "survived"}
    return again, kept


def report(names: list[str]) -> None:
    """Print the table of results.json and each module's survivors, with the equivalents counted
    from SURVIVORS.md's table of equivalent mutants."""
    results = _load()
    equivalent = _equivalents()
    print("module               mutants  killed  survived  equivalent  killed/mutants  killed/(mutants-equivalent)")
    for name in names:
        r = results.get(name)
        if r is None:
            print(f"{name:20s} not run")
            continue
        eq = sum(1 for s in r["survivors"] if _key(s) in equivalent.get(name, set()))
        rest = r["mutants"] - eq
        # Figures of an earlier version of the module are shown, and said to be: run it again.
        source = (ROOT / TARGETS[name].path).read_text() if name in TARGETS else ""
        older = r.get("source_sha256") != hashlib.sha256(source.encode()).hexdigest()
        print(f"{name:20s} {r['mutants']:7d} {r['killed']:7d} {r['survived']:9d} {eq:11d}  "
              f"{100 * r['kill_rate']:12.1f} %  {100 * (r['killed'] / rest if rest else 1):12.1f} %"
              + (f"  ({r['not_run']} not run)" if r.get("not_run") else "")
              + ("  (of an earlier source: run again)" if older else ""))
    for name in names:
        r = results.get(name)
        if not r or not r["survivors"]:
            continue
        print(f"\n{name} survivors (E = explained as equivalent in SURVIVORS.md):")
        for s in r["survivors"]:
            mark = "E" if _key(s) in equivalent.get(name, set()) else " "
            print(f"  {mark} line {s['line']:4d} {s['operator']:<36s} #{s['occurrence']:<3d} {s['code'][:80]}")


def _key(s: dict) -> str:
    return f"{s['line']}:{s['operator']}:{s['occurrence']}"


def _equivalents() -> dict[str, set[str]]:
    """SURVIVORS.md names the mutants judged equivalent on lines `- eq MODULE LINE:Operator:occurrence …`
    (one or more per line, under the explanation of why); the rest of the file is prose."""
    found: dict[str, set[str]] = {}
    path = OUT / "SURVIVORS.md"
    if path.exists():
        for m in re.finditer(r"^\s*- eq (\S+) (.*)$", path.read_text(), re.M):
            found.setdefault(m.group(1), set()).update(re.findall(r"\d+:\w+:\d+", m.group(2)))
    return found


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    import signal

    # Stop cleanly, keeping the outcomes judged so far, on Ctrl-C or `timeout` (INT or TERM), even
    # when started in the background by a shell that ignores SIGINT there.
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("modules", nargs="*", help=f"subset of: {', '.join(TARGETS)}")
    p.add_argument("--list", action="store_true", help="list the modules and their test subsets")
    p.add_argument("--report", action="store_true", help="only print the results recorded in bench/mutation/results.json")
    p.add_argument("--rerun-survivors", action="store_true",
                   help="run the current tests against the recorded survivors only; kills (and mutants a sample left out) are kept")
    p.add_argument("--resume", action="store_true",
                   help="with --rerun-survivors: also run the mutants a sampled run left out (--sample: how many in all)")
    p.add_argument("--lines", default="",
                   help="with --rerun-survivors: re-run only the survivors on these lines (comma-separated); the rest keep their outcome")
    p.add_argument("--jobs", type=int, default=1, help="mutants tested in parallel, each in its own copy of the tree")
    p.add_argument("--sample", type=int, default=None, help="run only this many mutants per module (seeded random sample)")
    args = p.parse_args(argv)
    if args.list:
        for name, t in TARGETS.items():
            print(f"{name:20s} {t.path:28s} {t.tests}" + (f"  (not mutated: {', '.join(t.exclude)})" if t.exclude else ""))
        return 0
    unknown = [m for m in args.modules if m not in TARGETS]
    if unknown:
        p.error(f"unknown module(s) {', '.join(unknown)}; known: {', '.join(TARGETS)}")
    names = args.modules or list(TARGETS)
    if not args.report:
        lines = {int(x) for x in args.lines.split(",") if x.strip()}
        run(names, max(1, args.jobs), args.sample, args.rerun_survivors or args.resume, args.resume, lines)
    report(names)
    return 0


if __name__ == "__main__":
    sys.exit(main())
