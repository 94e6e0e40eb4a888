#!/usr/bin/env python3
"""The bad-input catalogue (issue 18): every input every tool reads, broken in each of seven
ways, run through the built tool.

    bad_inputs.py [--bin DIR] [--tool TOOL] [--markdown FILE]

An input "slot" is one file a tool reads (the machine of turnfit-track, the bunch file of
turnfit-track --bunch, the profile of turnfit-peakfind, ...), given by a valid base file and the
command that reads it. Each slot is run with its file replaced by:
  truncated  the first 40 % of the base's bytes
  empty      no bytes
  type       a value of the wrong type: in JSON the first number becomes the string "x"; in text
             formats the first number after the first line becomes "x"
  nan        that number becomes nan (JSON has none: the bare word NaN)
  inf        that number becomes inf (JSON: 1e999, which overflows)
  huge       that number becomes 1e400, beyond a double
  binary     4 kB of seeded random bytes with NULs
Each must end with exit status 65 within 20 s, a first stderr line "turnfit-TOOL: ..." that
names the broken file (its path as given), no "internal error", nothing on stdout, and no output
file (the outputs the command names must not exist afterwards); the few cases a tool rightly
accepts (a CSV cut at a row is a shorter valid table) are listed in ACCEPTED with the reason,
and must exit 0. A run that breaks a rule fails the
catalogue; the table (--markdown) lists every case with its message.
"""
import argparse
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
R8 = os.path.join(ROOT, "share", "turnfit", "ring8")
DATA = os.path.join(ROOT, "tests", "cli", "data")
KINDS = ["truncated", "empty", "type", "nan", "inf", "huge", "binary"]

# One slot: tool, what the input is, its format (json or text), the base file, the name the
# broken file gets in the work folder, files to place beside it (a machine's map and profiles),
# the command ({in} = the broken file, {dir} = the work folder), and the outputs it names.
RING8_FILES = ["machine.json", "field.map", "main-cavity.dat", "flattop-cavity.dat"]
SLOTS = [
    ("turnfit-orbit", "machine", "json", R8 + "/machine.json", "machine.json", [], ["{in}", "--energies", "100", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-orbit", "field map (turnfit)", "text", R8 + "/field.map", "field.map", [], ["--field-map", "{in}", "--field-format", "turnfit", "--energies", "100", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-orbit", "field map (OPAL RING)", "text", os.path.join(ROOT, "tests", "fuzz", "seeds", "tiny_opal.dat"), "bfield.dat", [], ["--field-map", "{in}", "--energies", "100", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-orbit", "sector-field spec", "json", DATA + "/sector_small.json", "spec.json", [], ["--sector-field", "{in}", "--energies", "100", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-track", "machine", "json", R8 + "/machine.json", "machine.json", RING8_FILES[1:], ["{in}", "--turns", "2", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-track", "machine's field map", "text", R8 + "/field.map", "field.map", ["machine.json", "main-cavity.dat", "flattop-cavity.dat"], ["{dir}/machine.json", "--turns", "2", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-track", "machine's cavity profile", "text", R8 + "/main-cavity.dat", "main-cavity.dat", ["machine.json", "field.map", "flattop-cavity.dat"], ["{dir}/machine.json", "--turns", "2", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-track", "dvars", "json", R8 + "/truth-dvars.json", "dvars.json", [], [R8 + "/machine.json", "--dvars", "{in}", "--turns", "2", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-track", "bunch file", "text", os.path.join(ROOT, "tests", "fuzz", "seeds", "bunch.csv"), "bunch.csv", [], [R8 + "/machine.json", "--bunch", "{in}", "--turns", "2", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-synth", "machine", "json", R8 + "/truth-machine.json", "machine.json", RING8_FILES[1:], ["{in}", "--particles", "50", "-o", "{dir}/out"], ["out"]),
    ("turnfit-peakfind", "profile", "text", R8 + "/measured/RRI2.csv", "RRI2.csv", [], ["{in}", "-o", "{dir}/out.csv"], ["out.csv"]),
    ("turnfit-compare", "measured peaks", "text", DATA + "/compare_peaks.csv", "peaks.csv", [], ["{in}", DATA + "/compare_turns.csv", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-compare", "model turns", "text", DATA + "/compare_turns.csv", "turns.csv", [], [DATA + "/compare_peaks.csv", "{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-compare", "objectives file", "json", DATA + "/compare_problem.json", "problem.json", [], [DATA + "/compare_peaks.csv", DATA + "/compare_turns.csv", "--objectives", "@{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-tc-fit", "phase scan", "text", R8 + "/measured/phase/TC1.csv", "TC1.csv", [], ["{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-plot", "profile", "text", R8 + "/measured/RRI2.csv", "RRI2.csv", [], ["profile", "{in}", "--no-render", "-o", "{dir}/out.png"], ["out.plot.csv", "out.gp"]),
    ("turnfit-nsga", "problem", "json", os.path.join(ROOT, "tests", "fuzz", "seeds", "problem_command.json"), "problem.json", [], ["--problem", "{in}", "--generations", "1", "--population", "4", "-o", "{dir}/out.log"], ["out.log"]),
    ("turnfit-nsga", "population log (--resume)", "text", os.path.join(ROOT, "tests", "fuzz", "seeds", "zdt1.log"), "run.log", [], ["--problem", "ZDT1", "--variables", "2", "--population", "4", "--generations", "3", "--resume", "{in}", "-o", "{dir}/out.log"], ["out.log"]),
    ("turnfit-localsearch", "problem", "json", os.path.join(ROOT, "tests", "fuzz", "seeds", "problem_turns.json"), "problem.json", [], ["{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-localsearch", "start design", "json", R8 + "/truth-dvars.json", "start.json", [], ["{dir}/problem.json", "--start", "{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-diagnose", "problem", "json", os.path.join(ROOT, "tests", "fuzz", "seeds", "problem_turns.json"), "problem.json", [], ["{in}", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-import-opal", "OPAL input", "text", DATA + "/opal_minimal.in", "ring.in", [], ["{in}", "-q", "-o", "{dir}/out.json"], ["out.json"]),
    ("turnfit-export-opal", "machine", "json", R8 + "/machine.json", "machine.json", RING8_FILES[1:], ["{in}", "-q", "--map-out", "{dir}/map.dat", "--dist-out", "{dir}/dist.dat", "-o", "{dir}/out.in"], ["out.in", "map.dat", "dist.dat"]),
    ("turnfit-export-opal", "dvars", "json", R8 + "/truth-dvars.json", "dvars.json", [], [R8 + "/machine.json", "-q", "--dvars", "{in}", "--map-out", "{dir}/map.dat", "--dist-out", "{dir}/dist.dat", "-o", "{dir}/out.in"], ["out.in", "map.dat", "dist.dat"]),
]

# Where the first number to break is looked for in a text format (default: after the first line
# and any comment lines; a map's header has a free-text label, its numbers start after "data").
ANCHORS = {"field.map": b"\ndata\n"}

# Kinds a slot rightly accepts, and why (the run must then exit 0).
ACCEPTED = {
    ("turnfit-peakfind", "profile", "truncated"): "a CSV cut short is a shorter valid table (nothing in a CSV marks its end): the readings it has are used",
    ("turnfit-plot", "profile", "truncated"): "a CSV cut short is a shorter valid table: the readings it has are drawn",
    ("turnfit-nsga", "population log (--resume)", "truncated"): "a log cut short is what a killed run leaves: the torn last record is dropped with a warning and the run continues (turnfit-population(5))",
    ("turnfit-nsga", "population log (--resume)", "empty"): "an empty log is a run killed before its first record: the run starts afresh (turnfit-nsga(1), RESUME)",
}

NUMBER = re.compile(rb"(?<![\w.+-])[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?(?![\w.])")


def replace_json_number(data, repl):
    """The document with its first number value (in document order, not one inside a string)
    replaced by the raw text repl."""
    doc = json.loads(data)
    marker = "\u0000number\u0000"
    def walk(v):
        if isinstance(v, dict):
            for k in v:
                if walk_slot(v, k):
                    return True
        elif isinstance(v, list):
            for i in range(len(v)):
                if walk_slot(v, i):
                    return True
        return False
    def walk_slot(parent, key):
        v = parent[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            parent[key] = marker
            return True
        return walk(v)
    if not walk(doc):
        return None
    return json.dumps(doc, indent=1).encode().replace(json.dumps(marker).encode(), repl, 1)


def replace_number(data, fmt, repl, name):
    """The base with its first number (JSON: its first number value; text formats: the first
    number after the first line) replaced."""
    if fmt == "json":
        return replace_json_number(data, repl)
    if name in ANCHORS:
        start = data.find(ANCHORS[name]) + len(ANCHORS[name])
    else:
        start = data.find(b"\n") + 1
        # skip comment lines and, in CSV, the header
        while start < len(data) and data[start:start + 1] == b"#":
            start = data.find(b"\n", start) + 1
    m = NUMBER.search(data, start)
    if not m:
        return None
    return data[:m.start()] + repl + data[m.end():]


def broken(data, fmt, kind, seed, name):
    if kind == "truncated":
        return data[:len(data) * 2 // 5]
    if kind == "empty":
        return b""
    if kind == "binary":
        rng = random.Random(seed)
        return bytes(rng.choice([0, rng.randrange(256)]) for _ in range(4096))
    repl = {"type": b'"x"' if fmt == "json" else b"x",
            "nan": b"NaN" if fmt == "json" else b"nan",
            "inf": b"1e999" if fmt == "json" else b"inf",
            "huge": b"1e400"}[kind]
    return replace_number(data, fmt, repl, name)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default=os.environ.get("TURNFIT_BIN", os.path.join(ROOT, "build", "tools")))
    ap.add_argument("--tool", action="append", help="only this tool (repeatable)")
    ap.add_argument("--markdown", help="write the table of cases here")
    a = ap.parse_args()
    rows, failures = [], 0
    work = tempfile.mkdtemp(prefix="turnfit-bad-inputs-")
    try:
        for s, (tool, what, fmt, base, name, beside, args, outputs) in enumerate(SLOTS):
            if a.tool and tool not in a.tool and tool.replace("turnfit-", "") not in a.tool:
                continue
            data = open(base, "rb").read()
            for k, kind in enumerate(KINDS):
                d = os.path.join(work, "%02d-%s" % (s, kind))
                os.makedirs(d)
                for f in beside:
                    shutil.copy(os.path.join(R8, f), d)
                os.symlink(R8, os.path.join(d, "ring8"))  # the problem seeds name ring8/machine.json
                if tool == "turnfit-localsearch" and what == "start design":
                    open(os.path.join(d, "problem.json"), "w").write(json.dumps(
                        {"format": "turnfit-problem/1", "machine": R8 + "/machine.json", "peaks": [R8 + "/turns.csv"],
                         "variables": "paper", "bunch": "reference"}))
                path = os.path.join(d, name)
                content = broken(data, fmt, kind, 1000 * s + k, name)
                if content is None:  # a base without a number cannot test this kind: fix the base
                    failures += 1
                    rows.append((tool, what, kind, "-", "no number to break", "FAIL: the base has no number to break"))
                    continue
                open(path, "wb").write(content)
                argv = [os.path.join(a.bin, tool)] + [x.replace("{in}", path).replace("{dir}", d) for x in args]
                try:
                    r = subprocess.run(argv, stdin=subprocess.DEVNULL, capture_output=True, timeout=20)
                    rc, out, err = r.returncode, r.stdout, r.stderr.decode("utf-8", "replace")
                except subprocess.TimeoutExpired:
                    rc, out, err = "timeout", b"", ""
                first = err.splitlines()[0] if err.strip() else ""
                problems = []
                accepted = ACCEPTED.get((tool, what, kind))
                if accepted:
                    if rc != 0:
                        problems.append("exit %s, not 0 (%s)" % (rc, accepted))
                else:
                    if rc != 65:
                        problems.append("exit %s, not 65" % rc)
                    if not first.startswith(tool + ": ") or path not in first:
                        problems.append("the message does not name the file")
                    if out:
                        problems.append("wrote stdout")
                    for o in outputs:
                        if os.path.exists(os.path.join(d, o)):
                            problems.append("left output " + o)
                if "internal error" in err:
                    problems.append("internal error")
                failures += bool(problems)
                msg = first.replace(path, name).replace(d + "/", "")
                verdict = ("accepted: " + accepted if accepted else "ok") if not problems else "FAIL: " + "; ".join(problems)
                rows.append((tool, what, kind, str(rc), msg[:200], verdict))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    for r in rows:
        print(" | ".join(r))
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write("| tool | input | broken | exit | first line of stderr | verdict |\n|---|---|---|---|---|---|\n")
            for r in rows:
                f.write("| " + " | ".join(c.replace("|", "\\|") for c in r) + " |\n")
    print("bad-input catalogue: %d cases, %d failed" % (len(rows), failures))
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
