#!/usr/bin/env python3
"""The paper's space-charge check on ring8 (issue 20), and what mA currents do to its turns.

    space_charge_ring8.py [--bin DIR] [--particles N] [--turns N] [--grid G] [--currents 88,1000,2200]
                          [--threads N] [--out DIR]

Tracks one bunch of ring8 (the embedded machine, its bunch block: 2 deg phase, 30 keV, 1 mm mrad)
without space charge, then the same particles (same seed) with it at each current, and prints
per current: the largest change of a turn's centroid (the paper: 0.05 mm at 88 uA on the PSI
Ring), the change at a few turns, the turns' widths (rms) against the run without, and the
turn separation against the width (where neighbouring turns start to overlap). It also compares
the bunch without space charge with the single reference particle (the paper: its 360000-particle
run moved the error by about 0.1 mm). Writes the turn tables and, when gnuplot is on PATH,
figures (centroid change and width against turn) to --out. Times each run: the space-charge
runs' time against the run without is the solver's cost.
"""
import argparse
import csv
import os
import shutil
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, ".."))
RING8 = os.path.join(ROOT, "share", "turnfit", "ring8", "machine.json")


def rows(path):
    with open(path) as f:
        return {(r["probe"], int(r["turn"])): r for r in csv.DictReader(l for l in f if not l.startswith("#"))}


REUSE = False


def run(cmd):
    if REUSE:
        return 0.0, ""
    t0 = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit("failed (%d): %s\n%s" % (p.returncode, " ".join(cmd), p.stderr))
    return time.time() - t0, p.stderr


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "tools"))
    ap.add_argument("--particles", type=int, default=10000)
    ap.add_argument("--turns", type=int, default=182)
    ap.add_argument("--grid", default="32x32x32")
    ap.add_argument("--currents", default="88,1000,2200")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=os.path.join(ROOT, "build", "space-charge"))
    ap.add_argument("--reuse", action="store_true", help="Summarize the runs already in --out instead of running them")
    a = ap.parse_args()
    global REUSE
    REUSE = a.reuse
    os.makedirs(a.out, exist_ok=True)
    track = os.path.join(a.bin, "turnfit-track")
    base = [track, RING8, "--turns", str(a.turns), "--no-provenance", "--threads", str(a.threads), "-q"]
    single = os.path.join(a.out, "single.csv")
    run(base + ["--particles", "0", "-o", single])
    plain = os.path.join(a.out, "plain.csv")
    t_plain, _ = run(base + ["--particles", str(a.particles), "-o", plain])
    print("ring8, %d particles, %d turns, grid %s, %d threads (%s)" %
          (a.particles, a.turns, a.grid, a.threads, time.strftime("%Y-%m-%d")))
    print("run without space charge: %.1f s" % t_plain)
    P, S = rows(plain), rows(single)
    keys = sorted(k for k in P if k in S)
    d = [float(P[k]["r_mm"]) - float(S[k]["r_mm"]) for k in keys]
    print("bunch centroid minus the single particle (no space charge): mean %.4f mm, range %.4f to %.4f mm"
          % (sum(d) / len(d), min(d), max(d)))
    results = {}
    for cur in [float(c) for c in a.currents.split(",")]:
        out = os.path.join(a.out, "sc-%g.csv" % cur)
        t, err = run(base + ["--particles", str(a.particles), "--space-charge", "--current-uA", "%g" % cur,
                             "--sc-grid", a.grid, "--sc-timing", "-o", out])
        results[cur] = (out, t, err.strip())
    print()
    print("| current uA | max abs centroid change mm | at turn | change at turns 50 / 100 / 150 / last mm "
          "| width rms, last complete turn: without / with mm | time s | time / without |")
    print("|---|---|---|---|---|---|---|")
    for cur, (out, t, err) in results.items():
        C = rows(out)
        # Complete crossings only: near the end of the run a wide bunch's outer particles have
        # not reached the probe yet, and a partial turn's mean is another bunch's.
        ks = [k for k in keys if k in C and k[0] == "RRL" and int(C[k]["particles"]) == a.particles
              and int(P[k]["particles"]) == a.particles]
        ch = {k: float(C[k]["r_mm"]) - float(P[k]["r_mm"]) for k in ks}
        worst = max(ks, key=lambda k: abs(ch[k]))
        last = max(ks)
        at = " / ".join("%.4f" % ch[("RRL", t_)] if ("RRL", t_) in ch else "-" for t_ in (50, 100, 150, last[1]))
        w = "%.3f / %.3f" % (float(P[last]["r_rms_mm"]), float(C[last]["r_rms_mm"])) if last in C else "-"
        print("| %g | %.4f | %d | %s | %s | %.0f | %.1f |" % (cur, abs(ch[worst]), worst[1], at, w, t, t / t_plain if t_plain > 0 else 0))
    print()
    for cur, (out, t, err) in results.items():
        print("%g uA: %s" % (cur, err.replace("turnfit-track: ", "")))
    # Turn separation against width (RRL): where 2.35 rms (the FWHM of a Gaussian) reaches it.
    print()
    for cur, (out, t, err) in [(0.0, (plain, t_plain, ""))] + list(results.items()):
        C = rows(out)
        rr = [(k[1], float(C[k]["r_mm"]), float(C[k]["r_rms_mm"])) for k in sorted(C)
              if k[0] == "RRL" and int(C[k]["particles"]) == a.particles]
        over = [t_ for (t_, r, w), (t2, r2, w2) in zip(rr, rr[1:]) if 2.35 * max(w, w2) > abs(r2 - r)]
        print("%g uA: turns whose FWHM reaches the next turn: %s" %
              (cur, "none" if not over else "%d (first at turn %d)" % (len(over), over[0])))
    if shutil.which("gnuplot"):
        data = os.path.join(a.out, "sc.dat")
        with open(data, "w") as f:
            for cur, (out, t, err) in results.items():
                C = rows(out)
                f.write("# %g uA\n" % cur)
                for k in keys:
                    if k in C and k[0] == "RRL" and int(C[k]["particles"]) == a.particles:
                        f.write("%d %.6f %.6f %.6f\n" % (k[1], float(C[k]["r_mm"]) - float(P[k]["r_mm"]),
                                                         float(C[k]["r_rms_mm"]), float(P[k]["r_rms_mm"])))
                f.write("\n\n")
        png = os.path.join(a.out, "space-charge.png")
        curs = list(results)
        plot = ", ".join("'%s' index %d using 1:2 with lines lc %d title '%g uA'" % (data, i, i + 1, c)
                         for i, c in enumerate(curs))
        widths = ", ".join("'%s' index %d using 1:3 with lines lc %d title '%g uA'" % (data, i, i + 1, c)
                           for i, c in enumerate(curs))
        script = ("set terminal pngcairo size 900,800\nset output '%s'\nset multiplot layout 2,1\n"
                  "set xlabel 'turn (RRL)'\nset ylabel 'centroid change [mm]'\nset key left top\nplot %s\n"
                  "set ylabel 'turn width, rms [mm]'\nplot '%s' index 0 using 1:4 with lines dt 2 lc 0 title 'no space charge', %s\n"
                  "unset multiplot\n" % (png, plot, data, widths))
        subprocess.run(["gnuplot"], input=script, text=True, check=True)
        print("\nfigure: %s" % png)


if __name__ == "__main__":
    main()
