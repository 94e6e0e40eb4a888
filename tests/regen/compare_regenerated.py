#!/usr/bin/env python3
"""Regenerates committed data with its committed command and compares it with the committed copy.

usage: compare_regenerated.py --committed DIR --files F1,F2,... -- COMMAND ... {out} ...

Runs COMMAND with {out} replaced by a fresh temporary folder, then compares each named file in
that folder with the one in DIR: the same text except numbers, which may differ by two units of
their last printed digit or a relative 1e-12, whichever is larger (the last bits of transcendental
functions can differ between CPUs and libm builds, and a value rounded to 6 decimals may then flip
its last digit; a real change of the data moves numbers far more). Exit 0 when all match, 1 with a report otherwise.
"""
import os
import re
import subprocess
import sys
import tempfile

NUM = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def last_digit(text):
    """The value of one unit in the last printed digit of a number: 1e-8 for 0.85672104."""
    mant, _, exp = text.lower().partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 10.0 ** (int(exp or 0) - decimals)


def compare(a, b, name):
    ta, tb = NUM.split(a), NUM.split(b)
    na, nb = NUM.findall(a), NUM.findall(b)
    if ta != tb or len(na) != len(nb):
        la, lb = a.splitlines(), b.splitlines()
        for i, (x, y) in enumerate(zip(la, lb)):
            if NUM.sub("#", x) != NUM.sub("#", y):
                return "%s:%d: text differs:\n  committed:   %s\n  regenerated: %s" % (name, i + 1, x[:200], y[:200])
        return "%s: %d lines committed, %d regenerated" % (name, len(la), len(lb))
    worst, where = 0.0, None
    for i, (x, y) in enumerate(zip(na, nb)):
        fx, fy = float(x), float(y)
        d = abs(fx - fy) / max(2 * last_digit(x), 2 * last_digit(y), 1e-12 * max(abs(fx), abs(fy)), 1e-300)
        if d > worst:
            worst, where = d, (i, x, y)
    if worst > 1:
        i, x, y = where
        line = a[: a.find(x, sum(len(t) for t in ta[: i + 1]) + sum(len(t) for t in na[:i]))].count("\n") + 1
        return "%s:%d: number %s committed, %s regenerated (%.1f times the tolerance)" % (name, line, x, y, worst)
    return None


def main():
    argv = sys.argv[1:]
    sep = argv.index("--")
    opts, cmd = argv[:sep], argv[sep + 1:]
    committed = opts[opts.index("--committed") + 1]
    files = opts[opts.index("--files") + 1].split(",")
    with tempfile.TemporaryDirectory() as out:
        r = subprocess.run([c.replace("{out}", out) for c in cmd], stderr=subprocess.PIPE, text=True)
        if r.returncode != 0:
            print("regeneration failed (exit %d):\n%s" % (r.returncode, r.stderr))
            return 1
        bad = 0
        for f in files:
            with open(os.path.join(committed, f)) as fa, open(os.path.join(out, f)) as fb:
                msg = compare(fa.read(), fb.read(), f)
            print(msg if msg else "%s: same" % f)
            bad += msg is not None
    print("%d passed, %d failed" % (len(files) - bad, bad))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
