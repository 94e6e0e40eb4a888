#!/usr/bin/env python3
"""synth_repeatability: how much repeated turnfit-synth runs of one machine scatter (issue 16).

The paper (Frey et al., repeatability at 58/88/108 uA) measured the RRL profile of the PSI Ring
three times "with the same machine condition" and found the peak positions of the 58 and 108 uA
runs moved against the 88 uA run by sigma 0.51 and 0.58 mm (means -0.09 and +0.003 mm), mean
absolute error 0.40 mm over both. This script repeats that on synthetic data:

1. runs: turnfit-synth MACHINE --scan-errors PRESET --seed S --no-phase for --seeds seeds
   (S = --first-seed, +1, ...), the beam current cycling through --currents (the paper's 88, 58,
   108 uA), --particles particles, one thread each, --jobs runs at a time.
2. peaks: turnfit-peakfind on RRL.csv with --first-turn (9: the paper's RRL turns start at 9, and
   so do ring8's and the PSI example's, see their machine files). Each peak is matched to the
   nearest true turn of truth.json (the bunch centres synth tracked); a peak whose number is not
   that turn's is "misnumbered" and left out (a misnumbered peak would compare two different
   turns), as are turns outside --turns (default: the PSI example 9-182, the paper's; ring8 all)
   and turns the probe's end cuts (fewer particles than the bunch: their centre is that of the
   particles inside).
3. pairs: for every pair of runs (a, b), over the turns both have, d = r_b - r_a per turn:
   - total: d of the peaks, what the paper measured: sigma (standard deviation, mean removed, as
     the paper's histogram), MAE (mean |d|) and |mean|;
   - coherent: d of truth.json's true bunch centres: the run-to-run drift (and the bunch's
     sampling), which moves all turns of a run together and which a fit absorbs;
   - per-turn: d of (peak - true centre): the scan errors, the wire noise and peakfind's own
     error, which no design variable absorbs. total^2 ~ coherent^2 + per-turn^2 (the two are
     independent draws; their cross term averages out over pairs, not in one pair).
   Figures are averaged over pairs as turnfit-synth(1) does: sigma = sqrt(mean of the pairs'
   variances), MAE and |mean| the mean over pairs; the range of the pairs' sigmas is printed
   too (a single pair varies a lot: the drift's betatron amplitude is random).
   Per run: rms of (peak - true centre), the error of one measurement a fit sees.

Machines: "psi" (examples/psi-ring/aeo.json with the bunch of turnfit-synth(1)'s EXAMPLES, its
data files from --shared, default ../shared beside the project or $TURNFIT_SHARED; skipped with a
note when missing) and "ring8" (share/turnfit/ring8/machine.json --dvars truth-dvars.json, the
truth behind the shipped measurement without its concealed effects). Extra turnfit-synth options
go after "--" (e.g. -- --drive-mm 0.2 to try a value).

Usage: synth_repeatability.py [--machines psi,ring8] [--presets none,paper] [--seeds 4]
       [--first-seed 101] [--particles 2000] [--jobs 2] [--bin DIR] [--shared DIR] [--work DIR]
       [--json FILE] [-- SYNTH OPTIONS]
Python 3 standard library only. Exit 0, or 2 on a usage or tool error.
"""
import argparse
import concurrent.futures
import csv
import datetime
import itertools
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PSI_EXAMPLE = os.path.join(ROOT, "examples", "psi-ring", "aeo.json")
RING8 = os.path.join(ROOT, "share", "turnfit", "ring8")
# turnfit-synth(1) EXAMPLES: the bunch the PSI example is measured with.
PSI_BUNCH = {"emittance_r_mm_mrad": 2, "beta_r_m": 1.8, "emittance_z_mm_mrad": 2, "beta_z_m": 2.3,
             "sigma_E_MeV": 0.05, "sigma_phase_deg": 2}
# The paper's figures (Frey et al., repeatability of the RRL probe).
PAPER = {"sigma": (0.51, 0.58), "mae": 0.40, "mean": (-0.09, 0.003)}


class ToolError(Exception):
    pass


def run(args, what):
    p = subprocess.run(args, capture_output=True, text=True)
    if p.returncode != 0:
        raise ToolError("%s failed (exit %d): %s\n%s" % (what, p.returncode, " ".join(args), p.stderr.strip()))
    return p


def read_csv(path):
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(l for l in f if l.strip() and not l.startswith("#")))


def psi_machine(shared, work):
    """The PSI example with a bunch and absolute data paths, written into work; None if the
    shared data are missing."""
    if not os.path.exists(os.path.join(shared, "data", "psi-ring", "bfield.dat")):
        return None
    doc = json.load(open(PSI_EXAMPLE, encoding="utf-8"))
    data = os.path.join(shared, "data", "psi-ring")
    # The example names its files relative to itself (../../../shared/data/psi-ring/...): the
    # same names in the shared folder given.
    doc["field"]["map"] = os.path.join(data, os.path.basename(doc["field"]["map"]))
    for c in doc.get("cavities", []):
        if "profile" in c:
            c["profile"] = os.path.join(data, os.path.basename(c["profile"]))
    for t in doc.get("trimcoils", []):
        for k in ("file", "profile"):
            if k in t and not os.path.isabs(t[k]):
                t[k] = os.path.normpath(os.path.join(os.path.dirname(PSI_EXAMPLE), t[k]))
    doc["bunch"] = dict(PSI_BUNCH)
    path = os.path.join(work, "psi-ring.json")
    with open(path, "w", encoding="utf-8") as f:
        json.dump(doc, f, indent=1)
    return path


def one_run(tools, machine, label, seed, current, args, extra, work):
    """synth + peakfind of one run; returns {turn: (peak r, true r)} and a few facts."""
    d = os.path.join(work, "%s-s%d" % (label, seed))
    cmd = [tools["synth"], machine["path"]] + machine["args"] + [
        "--seed", str(seed), "--current-uA", str(current), "--particles", str(args.particles),
        "--no-phase", "--threads", "1", "-q", "--no-provenance", "--out", d] + extra
    t0 = time.time()
    run(cmd, "turnfit-synth")
    wall = time.time() - t0
    peaks_csv = os.path.join(d, "rrl-peaks.csv")
    run([tools["peakfind"], os.path.join(d, "RRL.csv"), "--first-turn", str(machine["first_turn"]), "-q",
         "-o", peaks_csv], "turnfit-peakfind")
    truth = json.load(open(os.path.join(d, "truth.json"), encoding="utf-8"))
    true_turns = {t["turn"]: t for t in truth["turns"]["RRL"]}
    full = truth["particles"] - truth["lost"]
    lo, hi = machine["turns"]
    out, misnumbered, cut = {}, [], 0
    centres = sorted((t["r_mm"], n) for n, t in true_turns.items())
    for row in read_csv(peaks_csv):
        n, r = int(row["turn"]), float(row["r_mm"])
        nearest = min(centres, key=lambda c: abs(c[0] - r))[1]
        if nearest != n:
            misnumbered.append(n)
            continue
        if not (lo <= n <= hi):
            continue
        if true_turns[n]["particles"] < full:
            cut += 1
            continue
        out[n] = (r, true_turns[n]["r_mm"])
    return {"seed": seed, "current_uA": current, "turns": out, "misnumbered": misnumbered, "cut": cut,
            "wall_s": wall, "drift": {k: truth["drift"][k] for k in ("dr_mm", "dpr_mrad", "dvoltage_rel")},
            "scan_errors": truth.get("scan_errors"), "truth_turns": len(true_turns)}


def pair_stats(runs):
    """The three comparisons over every pair of runs (module doc, step 3)."""
    res = {}
    for kind in ("total", "coherent", "per-turn"):
        var, mae, mean, sig = [], [], [], []
        for a, b in itertools.combinations(runs, 2):
            common = sorted(set(a["turns"]) & set(b["turns"]))
            if len(common) < 2:
                continue
            d = []
            for n in common:
                (pa, ta), (pb, tb) = a["turns"][n], b["turns"][n]
                d.append({"total": pb - pa, "coherent": tb - ta, "per-turn": (pb - tb) - (pa - ta)}[kind])
            m = sum(d) / len(d)
            v = sum((x - m) ** 2 for x in d) / len(d)
            var.append(v)
            sig.append(math.sqrt(v))
            mae.append(sum(abs(x) for x in d) / len(d))
            mean.append(abs(m))
        if not var:
            raise ToolError("no pair of runs has turns in common")
        res[kind] = {"sigma": math.sqrt(sum(var) / len(var)), "mae": sum(mae) / len(mae),
                     "mean_abs": sum(mean) / len(mean), "sigma_min": min(sig), "sigma_max": max(sig),
                     "pairs": len(var)}
    errs = [x for r in runs for (p, t) in r["turns"].values() for x in [p - t]]
    res["run_error_rms"] = math.sqrt(sum(e * e for e in errs) / len(errs))
    return res


def main(argv):
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    else:
        extra = []
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--machines", default="psi,ring8", help="psi, ring8 or both (default)")
    ap.add_argument("--presets", default="none,paper", help="--scan-errors presets to compare (default none,paper)")
    ap.add_argument("--seeds", type=int, default=4, help="runs per machine and preset (default 4: 6 pairs)")
    ap.add_argument("--first-seed", type=int, default=101, help="seed of the first run (default 101)")
    ap.add_argument("--currents", default="88,58,108", help="beam currents cycled over the runs [uA] (the paper's)")
    ap.add_argument("--particles", type=int, default=2000, help="bunch size (default 2000)")
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time, one thread each (default 2)")
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "tools"), help="folder with the built tools")
    ap.add_argument("--shared", default=os.environ.get("TURNFIT_SHARED", os.path.join(ROOT, "..", "shared")),
                    help="the shared data folder (for the PSI example)")
    ap.add_argument("--psi-turns", default="9-182", help="RRL turns compared on the PSI example (the paper's)")
    ap.add_argument("--work", help="keep the runs in this folder (default: a temporary one, removed)")
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args(argv)
    if args.seeds < 2 or args.particles < 1 or args.jobs < 1:
        ap.error("--seeds must be 2 or more, --particles and --jobs 1 or more")
    tools = {t: os.path.join(os.path.abspath(args.bin), "turnfit-" + t) for t in ("synth", "peakfind")}
    for t in tools.values():
        if not os.access(t, os.X_OK):
            ap.error("%s: not found (build first, or give --bin)" % t)
    currents = [float(c) for c in args.currents.split(",")]
    presets = args.presets.split(",")
    work = os.path.abspath(args.work) if args.work else tempfile.mkdtemp(prefix="synth_repeatability.")
    os.makedirs(work, exist_ok=True)
    lo, hi = (int(x) for x in args.psi_turns.split("-"))

    machines = []
    for name in args.machines.split(","):
        if name == "psi":
            path = psi_machine(os.path.abspath(args.shared), work)
            if path is None:
                print("note: %s has no data/psi-ring/bfield.dat: the PSI example is skipped" % args.shared)
                continue
            machines.append({"name": "psi", "path": path, "args": [], "first_turn": 9, "turns": (lo, hi)})
        elif name == "ring8":
            machines.append({"name": "ring8", "path": os.path.join(RING8, "machine.json"),
                             "args": ["--dvars", os.path.join(RING8, "truth-dvars.json")], "first_turn": 9,
                             "turns": (1, 10 ** 9)})
        else:
            ap.error("unknown machine %r (psi, ring8)" % name)

    started = datetime.datetime.now(datetime.timezone.utc)
    print("# synth_repeatability: %s UTC, %s, %d cores, load %.2f; seeds %d-%d, currents %s uA, %d particles, "
          "%d jobs; extra synth options: %s" % (
              started.strftime("%Y-%m-%d %H:%M"), platform.node(), os.cpu_count() or 0, os.getloadavg()[0],
              args.first_seed, args.first_seed + args.seeds - 1, args.currents, args.particles, args.jobs,
              " ".join(extra) or "none"), flush=True)
    jobs = []
    for m in machines:
        for p in presets:
            for k in range(args.seeds):
                jobs.append((m, p, args.first_seed + k, currents[k % len(currents)]))
    results = {}
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as ex:
            futs = {ex.submit(one_run, tools, m, "%s-%s" % (m["name"], p), s, c, args,
                              ["--scan-errors", p] + extra, work): (m["name"], p) for (m, p, s, c) in jobs}
            for f in concurrent.futures.as_completed(futs):
                key = futs[f]
                r = f.result()
                results.setdefault(key, []).append(r)
                print("# %s %s seed %d (%g uA): %.0f s, %d turns compared, %d misnumbered, %d cut; drift dr %+.3f mm"
                      % (key[0], key[1], r["seed"], r["current_uA"], r["wall_s"], len(r["turns"]),
                         len(r["misnumbered"]), r["cut"], r["drift"]["dr_mm"]), flush=True)
    except ToolError as e:
        print("synth_repeatability: %s" % e, file=sys.stderr)
        return 2
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)

    print()
    print("| machine | preset | runs (pairs) | total: sigma / MAE / mean abs [mm] | pairs' sigma min-max [mm] "
          "| coherent: sigma / MAE [mm] | per-turn: sigma / MAE [mm] | one run vs truth: rms [mm] | misnumbered |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    doc = {"started_utc": started.isoformat(), "host": platform.node(), "args": vars(args), "extra": extra,
           "paper": PAPER, "rows": []}
    for m in machines:
        for p in presets:
            runs = sorted(results[(m["name"], p)], key=lambda r: r["seed"])
            st = pair_stats(runs)
            t, c, q = st["total"], st["coherent"], st["per-turn"]
            mis = sum(len(r["misnumbered"]) for r in runs)
            print("| %s | %s | %d (%d) | %.3f / %.3f / %.3f | %.2f-%.2f | %.3f / %.3f | %.3f / %.3f | %.3f | %d |" % (
                m["name"], p, len(runs), t["pairs"], t["sigma"], t["mae"], t["mean_abs"], t["sigma_min"],
                t["sigma_max"], c["sigma"], c["mae"], q["sigma"], q["mae"], st["run_error_rms"], mis))
            doc["rows"].append({"machine": m["name"], "preset": p, "stats": st,
                                "runs": [{k: v for k, v in r.items() if k != "turns"} for r in runs]})
    print("\nThe paper (PSI Ring RRL, turns 9-182): sigma 0.51 and 0.58 mm, MAE 0.40 mm, means -0.09 and +0.003 mm.")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=1)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
