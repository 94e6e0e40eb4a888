#!/usr/bin/env python3
"""Blind cases for turnfit-diagnose's space-charge candidate (issue 20).

    blind_space_charge.py [--bin DIR] [--master-seed S] [--cases N] [--out DIR] [--particles N]

Each case draws its run seeds from the master seed, makes two measurements of ring8 with
turnfit-synth (the paper's scan errors and drift; each run its own seed, so its own drift), finds
their turns with turnfit-peakfind, and runs turnfit-diagnose on the first with --measured-at for
both. Three kinds of case, in turn:

  positive   the truth has space charge, measured at 88 and 1000 uA: it should be named
  low        the truth has space charge, measured at 10 and 20 uA: too weak to name
  absent     the truth has none, measured at 88 and 1000 uA: it must not be named

The tuning cases (looked at while the candidate was written) used run seeds 21 to 26; the master
seed here draws others. Prints one line per case and a summary; exit 0 when every positive is
named and no negative is, 1 otherwise.
"""
import argparse
import json
import os
import random
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, ".."))
RING8 = os.path.join(ROOT, "share", "turnfit", "ring8", "machine.json")
KINDS = [("positive", 88, 1000, True), ("low", 10, 20, True), ("absent", 88, 1000, False)]


def run(cmd, cwd):
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit("failed (%d): %s\n%s" % (p.returncode, " ".join(cmd), p.stderr))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "tools"))
    ap.add_argument("--master-seed", type=int, default=2026)
    ap.add_argument("--cases", type=int, default=3, help="cases in all, the kinds in turn")
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--out", default=os.path.join(ROOT, "build", "blind-space-charge"))
    a = ap.parse_args()
    rng = random.Random(a.master_seed)
    b = lambda t: os.path.join(a.bin, "turnfit-" + t)
    ok = True
    for c in range(a.cases):
        kind, i1, i2, sc = KINDS[c % len(KINDS)]
        work = os.path.join(a.out, "case%d-%s" % (c, kind))
        os.makedirs(work, exist_ok=True)
        seeds = [rng.randrange(100, 10**6) for _ in range(2)]
        peaks = {}
        for cur, seed, name in ((i1, seeds[0], "a"), (i2, seeds[1], "b")):
            d = os.path.join(work, name)
            cmd = [b("synth"), RING8, "--current-uA", str(cur), "--seed", str(seed), "--particles", str(a.particles),
                   "--no-phase", "--scan-errors", "paper", "-q", "-o", d]
            if sc:
                cmd += ["--space-charge", "--sc-grid", "16"]
            run(cmd, work)
            run([b("peakfind"), os.path.join(d, "RRI2.csv"), "-q", "-o", os.path.join(d, "p-RRI2.csv")], work)
            run([b("peakfind"), os.path.join(d, "RRL.csv"), "--first-turn", "9", "-q", "-o",
                 os.path.join(d, "p-RRL.csv")], work)
            peaks[cur] = os.path.join(d, "p-RRI2.csv") + "," + os.path.join(d, "p-RRL.csv")
        problem = os.path.join(work, "problem.json")
        with open(problem, "w") as f:
            json.dump({"format": "turnfit-problem/1", "machine": RING8,
                       "peaks": [os.path.join(work, "a", "p-RRI2.csv"), os.path.join(work, "a", "p-RRL.csv")],
                       "variables": ["rinit", "prinit", "vchange"]}, f)
        report = os.path.join(work, "report.json")
        run([b("diagnose"), problem, "--effects", "probe-offset", "--measured-at", "%g=%s" % (i1, peaks[i1]),
             "--measured-at", "%g=%s" % (i2, peaks[i2]), "-q", "-o", report], work)
        r = json.load(open(report))["space_charge"]
        named = r["verdict"] == "named"
        right = named == (kind == "positive")
        ok = ok and right
        print("case %d %-8s seeds %s: %-9s alpha %.3g +- %.2g, gain %.3g against %.3g (the model's own %.3g), %d turns: %s"
              % (c, kind, seeds, r["verdict"], r["alpha"], r["alpha_sigma"], r["gain"], r["threshold"],
                 r["gain_at_model"], r["points"], "right" if right else "WRONG"))
    print("all right" if ok else "some wrong")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
