#!/usr/bin/env python3
"""Run one data-driven CLI case (tests/cli/cases/*.json) against the built turnfit tools.

Like PROJ's test/cli and samtools' test_cmd: a case is data (command, stdin, expected exit code,
expected output with numeric tolerances); this script only runs and compares. The case format
is described in tests/cli/README.md. Python 3 standard library only.

Environment: TURNFIT_BIN (folder of the built tools, default <repo>/build/tools),
TURNFIT_SHARED (the shared data folder, default <repo>/../shared), TURNFIT_BUILD_FEATURES (what
the build has, e.g. "mpi"; CMake sets it) and TURNFIT_TEST_REQUIRE (what may not be missing:
"gnuplot", "mpi"; CMake sets it). Under CI=true, missing shared data fails the case.
Exit codes: 0 ok, 1 the case failed, 2 the case file itself is wrong, 77 skipped (an optional
input or tool absent).
"""
import csv
import io
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))

CASE_KEYS = {
    "description", "labels", "args", "pipeline", "stdin", "stdin_file", "setup", "env",
    "requires_shared", "requires_tools", "requires_build", "exit", "stage_exits", "timeout",
    "stdout_contains", "stdout_not_contains", "stdout_matches", "stdout_empty",
    "stderr_contains", "stderr_not_contains", "stderr_matches", "stderr_empty",
    "csv", "json", "files", "files_absent",
}
CSV_KEYS = {"rows", "header", "columns", "match", "all"}
FILE_KEYS = {"exists", "empty", "contains", "not_contains", "csv", "json"}
SPEC_KEYS = {"approx", "equals", "contains", "not_contains", "matches", "min", "max", "abs_max",
             "non_empty", "empty", "type", "length", "absent", "exists"}
SKIP = 77
SHOW_LINES = 40


class CaseError(Exception):
    """The case file is malformed (exit 2): a typo must not silently disable a check."""


class Skip(Exception):
    pass


# Optional tools and what a build that requires them calls them (TURNFIT_TEST_REQUIRE). Any other
# tool a case names is a plain dependency: missing, the case fails.
OPTIONAL_TOOLS = {"gnuplot": "gnuplot", "mpirun": "mpi"}


def required(what):
    """Whether a missing `what` fails the case instead of skipping it (see the module doc)."""
    if what == "shared" and os.environ.get("CI") == "true":
        return True
    return what in os.environ.get("TURNFIT_TEST_REQUIRE", "").split(",")


def skip_or_fail(what, message):
    if required(what):
        raise OSError("missing %s, which this build requires: %s" % (what, message))
    raise Skip("skipped: " + message)


# ---------------------------------------------------------------------------------------------
# Substitution of $SHARED, $TMP, $DATA (also ${SHARED} ...) in every string of the case.

def make_subst(mapping):
    pattern = re.compile(r"\$(?:\{(SHARED|TMP|DATA|BIN)\}|(SHARED|TMP|DATA|BIN)\b)")

    def subst(value):
        if isinstance(value, str):
            return pattern.sub(lambda m: mapping[m.group(1) or m.group(2)], value)
        if isinstance(value, list):
            return [subst(v) for v in value]
        if isinstance(value, dict):
            return {subst(k): subst(v) for k, v in value.items()}
        return value

    return subst


# ---------------------------------------------------------------------------------------------
# Value checks shared by CSV cells and JSON values.

def is_number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def fmt(x):
    return json.dumps(x) if not isinstance(x, str) else repr(x)


def as_float(actual):
    """A finite float from a CSV cell or a JSON number, else None."""
    if is_number(actual):
        v = float(actual)
    elif isinstance(actual, str):
        try:
            v = float(actual.strip())
        except ValueError:
            return None
    else:
        return None
    return v if math.isfinite(v) else None


def close(a, e, tol):
    return abs(a - e) <= tol + 1e-12 * max(1.0, abs(e))


def validate_spec(spec, where):
    """Reject a malformed value spec before running anything (not only when output parses)."""
    if isinstance(spec, dict):
        unknown = set(spec) - SPEC_KEYS
        if unknown:
            raise CaseError("%s: unknown check %s (known: %s)" % (where, sorted(unknown), sorted(SPEC_KEYS)))
        if "approx" in spec:
            validate_spec(spec["approx"], where)
    elif isinstance(spec, list) and (len(spec) != 2 or not all(is_number(v) for v in spec)):
        raise CaseError("%s: a list spec is [expected, tolerance]; use {\"equals\": ...} for lists" % where)


def validate_checks(case):
    def csv_spec(spec, where):
        if not isinstance(spec, dict) or set(spec) - CSV_KEYS:
            raise CaseError("%s: csv keys are %s" % (where, sorted(CSV_KEYS)))
        for m in spec.get("match", []):
            if not isinstance(m, dict) or set(m) - {"key", "values"}:
                raise CaseError("%s: a match is {\"key\": {...}, \"values\": {...}}" % where)
            for col, v in m.get("values", {}).items():
                validate_spec(v, "%s match %s" % (where, col))
        for col, v in spec.get("all", {}).items():
            validate_spec(v, "%s all %s" % (where, col))

    def json_spec(spec, where):
        if not isinstance(spec, dict):
            raise CaseError("%s: json is an object of JSON pointer -> check" % where)
        for ptr, v in spec.items():
            if ptr and not ptr.startswith("/"):
                raise CaseError("%s: JSON pointer %s must start with '/'" % (where, fmt(ptr)))
            validate_spec(v, "%s %s" % (where, ptr))

    if "csv" in case:
        csv_spec(case["csv"], "csv")
    if "json" in case:
        json_spec(case["json"], "json")
    for path, spec in case.get("files", {}).items():
        if not isinstance(spec, dict) or set(spec) - FILE_KEYS:
            raise CaseError("files %s: keys are %s" % (path, sorted(FILE_KEYS)))
        if "csv" in spec:
            csv_spec(spec["csv"], "files %s csv" % path)
        if "json" in spec:
            json_spec(spec["json"], "files %s json" % path)


def check_value(actual, spec, where, problems, missing=False):
    """Compare one value with its spec: [expected, tol], a number, a string, a literal, or a
    dict of operators. missing: the value does not exist (JSON pointer unresolved)."""
    if isinstance(spec, dict):
        unknown = set(spec) - SPEC_KEYS
        if unknown:
            raise CaseError("%s: unknown check %s (known: %s)" % (where, sorted(unknown), sorted(SPEC_KEYS)))
        if spec.get("absent"):
            if not missing:
                problems.append("%s: expected to be absent, got %s" % (where, fmt(actual)))
            return
        if missing:
            problems.append("%s: does not exist" % where)
            return
        for op, arg in spec.items():
            check_op(actual, op, arg, where, problems)
        return
    if missing:
        problems.append("%s: does not exist (expected %s)" % (where, fmt(spec)))
        return
    if isinstance(spec, list):
        if len(spec) != 2 or not all(is_number(v) for v in spec):
            raise CaseError("%s: a list spec is [expected, tolerance]; use {\"equals\": ...} for lists" % where)
        check_op(actual, "approx", spec, where, problems)
    elif is_number(spec):
        check_op(actual, "approx", [spec, 0], where, problems)
    elif isinstance(spec, str):
        if actual != spec:
            problems.append("%s: expected %s, got %s" % (where, fmt(spec), fmt(actual)))
    else:
        check_op(actual, "equals", spec, where, problems)


def check_op(actual, op, arg, where, problems):
    def bad(expect):
        problems.append("%s: expected %s, got %s" % (where, expect, fmt(actual)))

    if op in ("approx", "min", "max", "abs_max"):
        v = as_float(actual)
        if v is None:
            return bad("a finite number (%s %s)" % (op, fmt(arg)))
        if op == "approx":
            e, tol = arg
            if not close(v, e, tol):
                bad("%s within %s (off by %.6g)" % (fmt(e), fmt(tol), v - e))
        elif op == "min" and v < arg:
            bad(">= %s" % fmt(arg))
        elif op == "max" and v > arg:
            bad("<= %s" % fmt(arg))
        elif op == "abs_max" and abs(v) > arg:
            bad("|value| <= %s" % fmt(arg))
    elif op == "equals":
        if actual != arg or type(actual) is bool and not isinstance(arg, bool):
            bad(fmt(arg))
    elif op in ("contains", "not_contains", "matches"):
        text = actual if isinstance(actual, str) else json.dumps(actual)
        for s in arg if isinstance(arg, list) else [arg]:
            if op == "contains" and s not in text:
                bad("text containing %s" % fmt(s))
            elif op == "not_contains" and s in text:
                bad("text without %s" % fmt(s))
            elif op == "matches" and not re.search(s, text):
                bad("text matching /%s/" % s)
    elif op == "non_empty":
        empty = actual is None or actual == "" or actual == [] or actual == {}
        if empty == bool(arg):
            bad("a non-empty value" if arg else "an empty value")
    elif op == "empty":
        empty = actual is None or actual == "" or actual == [] or actual == {}
        if empty != bool(arg):
            bad("an empty value" if arg else "a non-empty value")
    elif op == "type":
        names = {"array": list, "object": dict, "string": str, "bool": bool}
        if arg == "number":
            ok = is_number(actual)
        elif arg == "null":
            ok = actual is None
        elif arg in names:
            ok = isinstance(actual, names[arg]) and not (arg != "bool" and isinstance(actual, bool))
        else:
            raise CaseError("%s: unknown type %s" % (where, fmt(arg)))
        if not ok:
            bad("a JSON %s" % arg)
    elif op == "length":
        if not hasattr(actual, "__len__") or len(actual) != arg:
            problems.append("%s: expected length %d, got %s" % (
                where, arg, len(actual) if hasattr(actual, "__len__") else fmt(actual)))
    elif op == "exists":
        pass  # reaching here means the value exists


# ---------------------------------------------------------------------------------------------
# CSV and JSON documents.

def parse_csv(text):
    lines = [l for l in text.splitlines() if l.strip() and not l.startswith("#")]
    if not lines:
        return None, []
    reader = csv.reader(io.StringIO("\n".join(lines)))
    header = next(reader)
    rows = []
    for n, rec in enumerate(reader, start=2):
        if len(rec) != len(header):
            rows.append({"__bad__": "data line %d has %d fields, the header %d" % (n, len(rec), len(header))})
            continue
        rows.append(dict(zip(header, rec)))
    return header, rows


def key_matches(row, key):
    for col, want in key.items():
        have = row.get(col)
        if have is None:
            return False
        if is_number(want):
            v = as_float(have)
            if v is None or not close(v, float(want), 1e-9 * max(1.0, abs(want))):
                return False
        elif have != want:
            return False
    return True


def check_csv(text, spec, what, problems):
    unknown = set(spec) - CSV_KEYS
    if unknown:
        raise CaseError("%s csv: unknown key %s (known: %s)" % (what, sorted(unknown), sorted(CSV_KEYS)))
    header, rows = parse_csv(text)
    if header is None:
        problems.append("%s: expected CSV, got no header line" % what)
        return
    for r in rows:
        if "__bad__" in r:
            problems.append("%s: %s" % (what, r["__bad__"]))
    rows = [r for r in rows if "__bad__" not in r]
    if "header" in spec and header != spec["header"]:
        problems.append("%s: expected header %s, got %s" % (what, ",".join(spec["header"]), ",".join(header)))
    for col in spec.get("columns", []):
        if col not in header:
            problems.append("%s: expected a column %s, header is %s" % (what, fmt(col), ",".join(header)))
    if "rows" in spec and len(rows) != spec["rows"]:
        problems.append("%s: expected %d data rows, got %d" % (what, spec["rows"], len(rows)))
    for m in spec.get("match", []):
        if set(m) - {"key", "values"}:
            raise CaseError("%s csv match: keys are 'key' and 'values'" % what)
        key = m.get("key", {})
        found = [r for r in rows if key_matches(r, key)]
        label = ",".join("%s=%s" % kv for kv in key.items())
        if len(found) != 1:
            problems.append("%s: expected one row with %s, found %d" % (what, label, len(found)))
            continue
        for col, want in m.get("values", {}).items():
            where = "%s row %s, column %s" % (what, label, col)
            check_value(found[0].get(col), want, where, problems, missing=col not in found[0])
    for col, want in spec.get("all", {}).items():
        if col not in header:
            problems.append("%s: expected a column %s for 'all', header is %s" % (what, fmt(col), ",".join(header)))
            continue
        before = len(problems)
        for i, r in enumerate(rows, start=1):
            key = "%s=%s" % (header[0], r.get(header[0]))
            check_value(r[col], want, "%s data row %d (%s), column %s" % (what, i, key, col), problems)
            if len(problems) - before >= 5:
                problems.append("%s: ... (more rows fail on column %s)" % (what, col))
                break


def resolve_pointer(doc, pointer):
    """RFC 6901 JSON pointer; returns (value, found)."""
    if pointer == "":
        return doc, True
    if not pointer.startswith("/"):
        raise CaseError("JSON pointer %s must start with '/'" % fmt(pointer))
    cur = doc
    for tok in pointer[1:].split("/"):
        tok = tok.replace("~1", "/").replace("~0", "~")
        if isinstance(cur, dict):
            if tok not in cur:
                return None, False
            cur = cur[tok]
        elif isinstance(cur, list):
            if not re.fullmatch(r"0|[1-9][0-9]*", tok) or int(tok) >= len(cur):
                return None, False
            cur = cur[int(tok)]
        else:
            return None, False
    return cur, True


def check_json(text, spec, what, problems):
    try:
        doc = json.loads(text)
    except ValueError as e:
        problems.append("%s: expected a JSON document, it does not parse: %s" % (what, e))
        return
    for pointer, want in spec.items():
        value, found = resolve_pointer(doc, pointer)
        check_value(value, want, "%s JSON %s" % (what, pointer or "(root)"), problems, missing=not found)


def check_text(text, spec, name, what, problems):
    for s in spec.get(name + "_contains", []):
        if s not in text:
            problems.append("%s: expected to contain %s" % (what, fmt(s)))
    for s in spec.get(name + "_not_contains", []):
        if s in text:
            problems.append("%s: expected not to contain %s" % (what, fmt(s)))
    for s in spec.get(name + "_matches", []):
        if not re.search(s, text, re.MULTILINE):
            problems.append("%s: expected to match /%s/" % (what, s))
    if name + "_empty" in spec and (text == "") != bool(spec[name + "_empty"]):
        problems.append("%s: expected %s" % (what, "nothing" if spec[name + "_empty"] else "some output"))


# ---------------------------------------------------------------------------------------------
# Running commands.

def resolve_tool(argv, bin_dir):
    """turnfit tools come from TURNFIT_BIN (never from PATH: an installed copy would hide a
    missing build); anything else (cat, head, sh) from PATH."""
    if not argv or not all(isinstance(a, str) for a in argv):
        raise CaseError("a command is a non-empty list of strings, got %s" % fmt(argv))
    name = argv[0]
    if name.startswith("turnfit") and "/" not in name:
        path = os.path.join(bin_dir, name)
        if not os.access(path, os.X_OK):
            raise FileNotFoundError("tool %s not found in TURNFIT_BIN=%s (not built?)" % (name, bin_dir))
        return [path] + argv[1:]
    return argv


def signal_name(rc):
    if rc < 0:
        try:
            return signal.Signals(-rc).name
        except ValueError:
            return "signal %d" % -rc
    return rc


def exit_ok(rc, allowed):
    allowed = allowed if isinstance(allowed, list) else [allowed]
    got = signal_name(rc)
    for a in allowed:
        if a == got:
            return True
        # Shell convention: 128+N is death by signal N.
        if is_number(a) and a > 128 and rc < 0 and -rc == a - 128:
            return True
    return False


def run_pipeline(stages, stdin_path, env, timeout, out_dir):
    """Run the stages joined by pipes; returns (exit codes, stdout, [stderr per stage], timed_out)."""
    procs, errs = [], []
    out_path = os.path.join(out_dir, "stdout")
    stdin = open(stdin_path, "rb") if stdin_path else subprocess.DEVNULL
    out = open(out_path, "wb")
    prev = stdin
    try:
        for i, argv in enumerate(stages):
            err = open(os.path.join(out_dir, "stderr.%d" % i), "wb")
            errs.append(err)
            last = i == len(stages) - 1
            try:
                p = subprocess.Popen(argv, stdin=prev, stdout=out if last else subprocess.PIPE,
                                     stderr=err, env=env, start_new_session=True)
            except OSError:
                for q in procs:  # do not leave the earlier stages running
                    os.killpg(q.pid, signal.SIGKILL)
                    q.wait()
                raise
            if prev not in (stdin, subprocess.DEVNULL) and hasattr(prev, "close"):
                prev.close()  # the child holds it now; a reader exiting must give the writer EPIPE
            prev = p.stdout
            procs.append(p)
        timed_out = False
        for p in procs:
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                timed_out = True
                break
        if timed_out:
            for p in procs:
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGKILL)
            for p in procs:
                p.wait()
    finally:
        if hasattr(stdin, "close"):
            stdin.close()
        out.close()
        for e in errs:
            e.close()
    with open(out_path, "rb") as f:
        stdout = f.read().decode("utf-8", "replace")
    stderrs = []
    for i in range(len(stages)):
        with open(os.path.join(out_dir, "stderr.%d" % i), "rb") as f:
            stderrs.append(f.read().decode("utf-8", "replace"))
    return [p.returncode for p in procs], stdout, stderrs, timed_out


def excerpt(text):
    lines = text.splitlines()
    shown = lines[:SHOW_LINES]
    more = len(lines) - len(shown)
    body = "\n".join("    | " + l for l in shown) if shown else "    (empty)"
    return body + ("\n    | ... (%d more lines)" % more if more > 0 else "")


# ---------------------------------------------------------------------------------------------

def run_case(case_path):
    name = os.path.splitext(os.path.basename(case_path))[0]
    try:
        with open(case_path, encoding="utf-8") as f:
            case = json.load(f)
    except (OSError, ValueError) as e:
        raise CaseError("cannot read the case: %s" % e)
    if not isinstance(case, dict):
        raise CaseError("a case is a JSON object")
    unknown = set(case) - CASE_KEYS
    if unknown:
        raise CaseError("unknown key %s (known: %s)" % (sorted(unknown), sorted(CASE_KEYS)))
    if ("args" in case) == ("pipeline" in case):
        raise CaseError("give exactly one of 'args' and 'pipeline'")
    if "stdin" in case and "stdin_file" in case:
        raise CaseError("give at most one of 'stdin' and 'stdin_file'")
    validate_checks(case)

    bin_dir = os.path.abspath(os.environ.get("TURNFIT_BIN") or os.path.join(REPO, "build", "tools"))
    # TURNFIT_SHARED wins; ctest passes the build's default as TURNFIT_SHARED_DEFAULT.
    shared = os.path.abspath(os.environ.get("TURNFIT_SHARED") or os.environ.get("TURNFIT_SHARED_DEFAULT")
                             or os.path.join(REPO, "..", "shared"))
    data = os.path.join(HERE, "data")

    for rel in case.get("requires_shared", []):
        if not os.path.exists(os.path.join(shared, rel)):
            skip_or_fail("shared", "%s: %s not found (TURNFIT_SHARED=%s)" % (name, rel, shared))
    features = [f for f in os.environ.get("TURNFIT_BUILD_FEATURES", "").split(",") if f]
    for feat in case.get("requires_build", []):
        # "mpi": the build has it; "!mpi": the build lacks it (a case of the other branch).
        have = feat.lstrip("!") in features
        if have == feat.startswith("!"):
            raise Skip("skipped: %s: this build %s %s" % (name, "has" if have else "lacks", feat.lstrip("!")))
    for tool in case.get("requires_tools", []):
        if shutil.which(tool) is None:
            if tool not in OPTIONAL_TOOLS:
                raise OSError("%s not on PATH (a dependency of the tests)" % tool)
            skip_or_fail(OPTIONAL_TOOLS[tool], "%s: %s not on PATH" % (name, tool))

    tmp = tempfile.mkdtemp(prefix="turnfit-cli-%s-" % name)
    work = tempfile.mkdtemp(prefix="turnfit-cli-run-")  # runner's own files, outside $TMP
    try:
        subst = make_subst({"SHARED": shared, "TMP": tmp, "DATA": data, "BIN": bin_dir})
        case = subst(case)
        return check_case(name, case, bin_dir, shared, tmp, data, work)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(work, ignore_errors=True)


def timeout_scale():
    """TURNFIT_TIMEOUT_SCALE (default 1) multiplies every case's timeout: the timeouts are hang
    guards sized for the Release build, and the sanitizer build (make -f Makefile.wrap check) runs
    the same commands several times slower."""
    try:
        v = float(os.environ.get("TURNFIT_TIMEOUT_SCALE", "1"))
    except ValueError:
        raise CaseError("TURNFIT_TIMEOUT_SCALE: not a number")
    if not (v > 0 and math.isfinite(v)):
        raise CaseError("TURNFIT_TIMEOUT_SCALE: must be a positive number")
    return v


def check_case(name, case, bin_dir, shared, tmp, data, work):
    env = dict(os.environ)
    env.update({"SHARED": shared, "TMP": tmp, "DATA": data, "TURNFIT_BIN": bin_dir, "LC_ALL": "C"})
    env.update({k: str(v) for k, v in case.get("env", {}).items()})
    timeout = case.get("timeout", 60) * timeout_scale()

    for i, argv in enumerate(case.get("setup", [])):
        argv = resolve_tool(argv, bin_dir)
        try:
            p = subprocess.run(argv, stdin=subprocess.DEVNULL, capture_output=True, env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            return fail(name, case, ["setup step %d timed out: %s" % (i + 1, shlex.join(argv))])
        if p.returncode != 0:
            return fail(name, case, ["setup step %d failed (exit %s): %s\n  its stderr:\n%s" % (
                i + 1, signal_name(p.returncode), shlex.join(argv),
                excerpt(p.stderr.decode("utf-8", "replace")))])

    stages = case["pipeline"] if "pipeline" in case else [case["args"]]
    if not isinstance(stages, list) or not stages:
        raise CaseError("'pipeline' is a non-empty list of commands")
    stages = [resolve_tool(a, bin_dir) for a in stages]
    command = " | ".join(shlex.join(a) for a in stages)

    stdin_path = None
    if "stdin" in case:
        stdin_path = os.path.join(work, "stdin")
        with open(stdin_path, "w", encoding="utf-8") as f:
            f.write(case["stdin"])
    elif "stdin_file" in case:
        stdin_path = case["stdin_file"]
        if not os.path.exists(stdin_path):
            return fail(name, case, ["stdin_file %s not found" % stdin_path], command)
        command += " < " + shlex.quote(stdin_path)

    codes, stdout, stderrs, timed_out = run_pipeline(stages, stdin_path, env, timeout, work)
    stderr = "".join(stderrs)
    problems = []
    if timed_out:
        problems.append("timed out after %s s" % timeout)

    expected = case.get("stage_exits")
    if expected is None:
        expected = [0] * (len(stages) - 1) + [case.get("exit", 0)]
    elif "exit" in case:
        raise CaseError("give 'exit' or 'stage_exits', not both")
    if len(expected) != len(stages):
        raise CaseError("'stage_exits' needs one entry per pipeline stage")
    for i, (rc, want) in enumerate(zip(codes, expected)):
        if not exit_ok(rc, want):
            stage = "exit code" if len(stages) == 1 else "exit code of stage %d (%s)" % (i + 1, os.path.basename(stages[i][0]))
            problems.append("%s: expected %s, got %s" % (stage, fmt(want), fmt(signal_name(rc))))

    check_text(stdout, case, "stdout", "stdout", problems)
    check_text(stderr, case, "stderr", "stderr", problems)
    if "csv" in case:
        check_csv(stdout, case["csv"], "stdout", problems)
    if "json" in case:
        check_json(stdout, case["json"], "stdout", problems)

    for path, spec in case.get("files", {}).items():
        unknown = set(spec) - FILE_KEYS
        if unknown:
            raise CaseError("files %s: unknown key %s (known: %s)" % (path, sorted(unknown), sorted(FILE_KEYS)))
        exists = os.path.isfile(path)
        if spec.get("exists", True) != exists:
            problems.append("file %s: expected %s" % (path, "to exist" if spec.get("exists", True) else "not to exist"))
            continue
        if not exists:
            continue
        with open(path, "rb") as f:
            text = f.read().decode("utf-8", "replace")
        check_text(text, {"file_" + k: v for k, v in spec.items()}, "file", "file " + path, problems)
        if "csv" in spec:
            check_csv(text, spec["csv"], "file " + path, problems)
        if "json" in spec:
            check_json(text, spec["json"], "file " + path, problems)
    for path in case.get("files_absent", []):
        if os.path.lexists(path):
            problems.append("%s: expected not to exist (left behind)" % path)
    # Atomic output (style.md): temp files are renamed or removed, whatever the outcome.
    for root, _, files in os.walk(tmp):
        for f in files:
            if ".tmp." in f:
                problems.append("temporary file left behind: %s" % os.path.join(root, f))

    if problems:
        return fail(name, case, problems, command, codes, stdout, stderrs, stages)
    print("ok: %s" % name)
    return 0


def fail(name, case, problems, command=None, codes=None, stdout=None, stderrs=None, stages=None):
    out = ["FAIL: %s" % name]
    if case.get("description"):
        out.append("  what: %s" % case["description"])
    if command:
        out.append("  command: %s" % command)
    if codes is not None:
        out.append("  exit: %s" % ", ".join(str(signal_name(c)) for c in codes))
    out.append("  problems:")
    out.extend("    - " + p for p in problems)
    if stdout is not None:
        out.append("  stdout:")
        out.append(excerpt(stdout))
    if stderrs is not None:
        for i, e in enumerate(stderrs):
            label = "stderr" if len(stderrs) == 1 else "stderr of stage %d (%s)" % (i + 1, os.path.basename(stages[i][0]))
            out.append("  %s:" % label)
            out.append(excerpt(e))
    print("\n".join(out))
    return 1


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print("usage: run_case.py CASE.json [CASE.json ...]\n"
              "Runs data-driven CLI cases (tests/cli/README.md); exit 0 ok, 1 failed, 2 bad case, 77 skipped.")
        return 0 if len(argv) >= 2 else 2
    worst = 0
    paths = [os.path.abspath(p) for p in argv[1:]]
    os.chdir(HERE)  # relative paths in cases are relative to tests/cli, wherever we start
    for path in paths:
        try:
            rc = run_case(path)
        except Skip as s:
            print(s)
            rc = SKIP
        except CaseError as e:
            print("ERROR: %s: bad case file: %s" % (path, e))
            rc = 2
        except OSError as e:
            print("FAIL: %s: %s" % (os.path.splitext(os.path.basename(path))[0], e))
            rc = 1
        # A failure outranks a bad case, which outranks a skip.
        rank = {0: 0, SKIP: 1, 2: 2, 1: 3}
        if rank[rc] > rank[worst]:
            worst = rc
    return worst


if __name__ == "__main__":
    sys.exit(main(sys.argv))
