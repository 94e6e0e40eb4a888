#!/usr/bin/env python3
"""The suite's guard: what ctest registered is exactly what the test sources define.

- Every Catch2 case of each test binary is one ctest entry (prefix + name), and every ctest
  entry with that prefix is a Catch2 case. catch_discover_tests splits a name at ';' into
  entries that match no case; such an entry would run nothing and report Passed.
- Every CLI case file is one ctest entry "cli: NAME", and no "cli:" entry lacks its file.
- A Catch2 name that cannot survive the round trip (';', a leading or trailing space) is named.

Usage: check_registered.py --ctest CTEST --build-dir DIR --catch "unit: =BIN" ... --cli-cases DIR
Exit 0 when the lists agree, 1 with every difference listed.
"""
import argparse
import glob
import json
import os
import subprocess
import sys


def catch_names(binary):
    p = subprocess.run([binary, "--list-test-names-only"], capture_output=True, text=True, timeout=120)
    # Catch2 2.13 exits with the number of cases listed; a negative status is a crash.
    if p.returncode < 0:
        sys.exit("%s --list-test-names-only died (%d): %s" % (binary, p.returncode, p.stderr))
    return [line for line in p.stdout.split("\n") if line.strip()]


def ctest_names(ctest, build_dir):
    p = subprocess.run([ctest, "--show-only=json-v1"], cwd=build_dir, capture_output=True, text=True,
                       timeout=120)
    if p.returncode != 0:
        sys.exit("ctest --show-only=json-v1 failed (%d): %s" % (p.returncode, p.stderr))
    return [t["name"] for t in json.loads(p.stdout)["tests"]]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ctest", required=True)
    ap.add_argument("--build-dir", required=True)
    ap.add_argument("--catch", action="append", default=[], help="PREFIX=BINARY")
    ap.add_argument("--cli-cases", required=True)
    a = ap.parse_args()

    registered = ctest_names(a.ctest, a.build_dir)
    problems = []
    total = 0
    for spec in a.catch:
        prefix, binary = spec.split("=", 1)
        cases = catch_names(binary)
        total += len(cases)
        for c in cases:
            if ";" in c or c != c.strip():
                problems.append("%s%r: ';' or an outer space in a test name (catch_discover_tests splits or "
                                "trims it; the pieces would match no case)" % (prefix, c))
        want = {prefix + c for c in cases}
        have = {n for n in registered if n.startswith(prefix)}
        for n in sorted(want - have):
            problems.append("Catch2 case not registered with ctest: %r" % n)
        for n in sorted(have - want):
            problems.append("ctest entry that is no Catch2 case (it would run nothing): %r" % n)
        dup = len([n for n in registered if n.startswith(prefix)]) - len(have)
        if dup:
            problems.append("%d duplicate ctest entries with prefix %r" % (dup, prefix))
        print("%s%d Catch2 cases, %d ctest entries" % (prefix, len(cases), len(have)))

    files = {"cli: " + os.path.splitext(os.path.basename(f))[0]
             for f in glob.glob(os.path.join(a.cli_cases, "*.json"))}
    have = {n for n in registered if n.startswith("cli: ")}
    for n in sorted(files - have):
        problems.append("CLI case file not registered (re-run cmake): %r" % n)
    for n in sorted(have - files):
        problems.append("ctest CLI entry without a case file: %r" % n)
    print("cli: %d case files, %d ctest entries" % (len(files), len(have)))

    if problems:
        print("\n".join(problems))
        return 1
    print("registered: %d Catch2 cases and %d CLI cases, one ctest entry each" % (total, len(files)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
