#!/usr/bin/env python3
"""bench_diagnose: the time one ring8 diagnosis takes, against one fit in the same run (issue 16).

On the shipped measurement (share/turnfit/ring8/measured, six concealed effects): turnfit-peakfind
on both probes, then the reference, turnfit-localsearch's fit of the paper's 48 variables from
the machine's values (what a user runs before a diagnosis), then turnfit-diagnose from that fit's
design. Prints wall and CPU times, designs simulated, the ratio diagnosis / fit, and where the
diagnosis's time goes (base fit, each round's screen and refits, from its report). The goal of
issue 16: one diagnosis in under 5 minutes on 2 cores. Wall times are only meaningful on an
otherwise quiet machine; the design counts are not affected by load.

Usage: bench_diagnose.py [--bin build/tools] [--threads 2] [--work DIR] [--from-nominal]
--from-nominal: the diagnosis also runs its own base fit from the machine's values (no --start).
Python 3 standard library only.
"""
import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
RING8 = os.path.join(REPO, "share", "turnfit", "ring8")


def timed(cmd):
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.time() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit("%s failed (%d): %s" % (" ".join(cmd), p.returncode, p.stderr[-2000:]))
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default=os.path.join(REPO, "build", "tools"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work")
    ap.add_argument("--from-nominal", action="store_true")
    a = ap.parse_args()
    work = a.work or tempfile.mkdtemp(prefix="bench_diagnose.")
    os.makedirs(work, exist_ok=True)
    tool = lambda n: os.path.join(a.bin, "turnfit-" + n)
    try:
        for probe, first in (("RRI2", []), ("RRL", ["--first-turn", "9"])):
            timed([tool("peakfind"), os.path.join(RING8, "measured", probe + ".csv"), "-o",
                   os.path.join(work, "peaks-%s.csv" % probe)] + first)
        prob = os.path.join(work, "problem.json")
        with open(prob, "w") as f:
            json.dump({"format": "turnfit-problem/1", "machine": os.path.join(RING8, "machine.json"),
                       "peaks": ["peaks-RRI2.csv", "peaks-RRL.csv"], "variables": "paper"}, f)
        best = os.path.join(work, "best.json")
        fit_wall, fit_cpu = timed([tool("localsearch"), prob, "-q", "--threads", str(a.threads), "--report",
                                   os.path.join(work, "fit.json"), "-o", best])
        fit = json.load(open(os.path.join(work, "fit.json")))
        print("machine: %s, %d cores; threads %d" % (os.uname().nodename, os.cpu_count(), a.threads))
        print("reference, turnfit-localsearch (48 variables, from nominal): %.1f s wall, %.1f s CPU, %d designs"
              % (fit_wall, fit_cpu, fit["evaluations"]))
        runs = [("from the fit (--start best.json)", ["--start", best])]
        if a.from_nominal:
            runs.append(("from nominal (its own base fit)", []))
        for label, extra in runs:
            rep = os.path.join(work, "diagnosis.json")
            wall, cpu = timed([tool("diagnose"), prob, "-q", "--threads", str(a.threads), "-o", rep] + extra)
            r = json.load(open(rep))
            print("turnfit-diagnose %s: %.1f s wall (%.2f x the fit), %.1f s CPU, %d designs (%.2f x); verdict %s%s"
                  % (label, wall, wall / fit_wall, cpu, r["evaluations"], r["evaluations"] / fit["evaluations"],
                     r["verdict"], "".join("; " + e["label"] for e in r["effects"])))
            print("  base fit: %d designs, %.1f s" % (r["base_fit"]["evaluations"], r["base_fit"]["wall_s"]))
            for rd in r["rounds"]:
                print("  round %d: screen %d designs %.1f s; refits %s" % (
                    rd["round"], rd["screen_evaluations"], rd["screen_wall_s"],
                    ", ".join("%d designs %.1f s" % (x.get("evaluations", 0), x.get("wall_s", 0)) for x in rd["refits"])))
            if r.get("eliminations"):
                print("  backward elimination: %s" % ", ".join(
                    "%d designs%s" % (x["evaluations"], " (taken out)" if x.get("dropped") else "")
                    for x in r["eliminations"]))
            print("  goal: under 300 s on 2 cores: %s" % ("met" if wall < 300 else "NOT met"))
    finally:
        if not a.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
