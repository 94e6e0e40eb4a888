#!/usr/bin/env python3
"""peak_pulls: is turnfit-peakfind's r_err_mm honest? Pulls of its peaks against turnfit-synth truths (issue 15).

For each truth, drawn from a master seed (printed; give it with --master-seed to repeat a run) exactly as
bench/blind_localsearch.py draws them (the same master seed gives the same truths and synth seeds):

1. truth: the nominal ring8 machine with every one of the paper's 48 design variables moved by
   f * (upper - lower), f uniform in [-amplitude, amplitude] (default 0.05); no concealed effects. The
   bounds and nominal values come from turnfit-localsearch's report (one short run on the nominal
   turns, --max-iterations 1), as blind_localsearch.py takes them.
2. measurement: turnfit-synth on the truth at its default noise, wire and drift, synth seed drawn
   from the truth's stream (never 88 nor 1), --no-phase. Kept in --work DIR and reused when there
   (synth is the slow part: about a minute a truth on 2 cores), so peakfind can be re-judged cheaply.
3. peaks: turnfit-peakfind RRI2.csv (first turn 1) and RRL.csv (--first-turn 9), CSV with r_err_mm.
4. matching (blind_localsearch.py's check_numbering): truth.json's true turns that at least a tenth
   of the bunch reaches; each peak against the nearest true turn. A peak whose number differs from
   that turn's is "misnumbered": counted and left out of the pulls (a numbering error is not a
   position error). A wide peak (k turns in one row) is judged against the true turn of its own
   number, which is what a fit compares it with.
5. pulls: (r_peak - r_true) / r_err_mm. Per probe and class (ok, and each flag on its own: a
   merged+edge peak counts in merged and in edge), and over both probes: n, RMS pull, fraction
   within 2 sigma (a Gaussian: 95.4 %), largest |pull|, RMS error and median r_err_mm. Classes with
   fewer than --min-n peaks are printed but marked "few".

--dump FILE writes every matched peak (truth, probe, turn, flag, error, r_err_mm, width, neighbour
distances, and peakfind's JSON fields) as JSON Lines for tuning the model offline.

Usage: peak_pulls.py [--truths N] [--master-seed S] [--work DIR] [--bin DIR] [--threads 2] [--dump FILE]
Python 3 standard library only.
"""
import argparse
import json
import math
import os
import random
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
# The truths, the tools' runs and the files as the blind suite has them: one piece of code for both.
from blind_localsearch import (MACHINE, REPO, ToolError, draw_truth, paper_variables, read_csv,  # noqa: E402
                               run, write_json)

FLAGS = ("merged", "wide", "weak", "gap", "edge", "ambiguous", "cross")


def measure(label, seed, truth, args, tools, work):
    """turnfit-synth on the truth (reused from work when there); returns the measurement folder."""
    d = os.path.join(work, "%s-seed%d" % (label, seed))
    meas = os.path.join(d, "meas")
    if os.path.exists(os.path.join(meas, "truth.json")):
        return d, meas, False
    os.makedirs(d, exist_ok=True)
    truth_path = os.path.join(d, "truth-dvars.json")
    write_json(truth_path, truth)
    cmd = [tools["synth"], MACHINE, "--dvars", truth_path, "--seed", str(seed), "--no-phase",
           "--threads", str(args.threads), "-q", "--out", meas + ".part"]
    if args.particles:
        cmd += ["--particles", str(args.particles)]
    run(cmd, "turnfit-synth")
    os.replace(meas + ".part", meas)
    return d, meas, True


def match(label, probe, peaks, extra, true_turns):
    """Each peak against the nearest true turn (blind_localsearch.py's check_numbering); rows and misnumbered count."""
    full = max(t["particles"] for t in true_turns)
    tl = sorted((t["r_mm"], t["turn"], t) for t in true_turns if t["particles"] >= 0.1 * full)
    by_turn = {t["turn"]: t for _, _, t in tl}
    rows, wrong = [], 0
    for i, p in enumerate(peaks):
        r, n = float(p["r_mm"]), int(p["turn"])
        r_t, n_t, t = min(tl, key=lambda q: abs(q[0] - r))
        flags = [] if p["flag"] == "ok" else p["flag"].split("+")
        if "wide" in flags and n in by_turn:  # a row for k turns: the fit compares it with turn n
            n_t, t = n, by_turn[n]
            r_t = t["r_mm"]
        if n != n_t:
            wrong += 1
            continue
        err = float(p["r_err_mm"])
        left = r - float(peaks[i - 1]["r_mm"]) if i > 0 else float("inf")
        right = float(peaks[i + 1]["r_mm"]) - r if i + 1 < len(peaks) else float("inf")
        row = {"truth": label, "probe": probe, "turn": n, "flag": p["flag"], "flags": flags, "r_mm": r,
               "true_r_mm": r_t, "error_mm": r - r_t, "r_err_mm": err, "pull": (r - r_t) / err if err > 0 else float("inf"),
               "width_mm": float(p["width_mm"]), "left_mm": left, "right_mm": right, "true_rms_mm": t["r_rms_mm"]}
        if extra is not None:
            row.update({k: v for k, v in extra[i].items() if k not in row and k != "flag"})
        rows.append(row)
    return rows, wrong


def stats(rows):
    n = len(rows)
    if n == 0:
        return None
    pulls = [r["pull"] for r in rows]
    errs = [r["error_mm"] for r in rows]
    sig = sorted(r["r_err_mm"] for r in rows)
    return {"n": n, "rms_pull": math.sqrt(sum(p * p for p in pulls) / n),
            "within2": sum(1 for p in pulls if abs(p) <= 2) / n, "max_pull": max(abs(p) for p in pulls),
            "rms_err": math.sqrt(sum(e * e for e in errs) / n), "max_err": max(abs(e) for e in errs),
            "median_sigma": sig[n // 2]}


def classes(rows):
    """(name, rows) per class: ok, each flag, all."""
    out = [("ok", [r for r in rows if not r["flags"]])]
    for f in FLAGS:
        sel = [r for r in rows if f in r["flags"]]
        if sel:
            out.append((f, sel))
    out.append(("all", rows))
    return out


def print_table(rows, min_n, out):
    print("| probe | class | n | RMS pull | within 2 sigma | max pull | RMS error [mm] | max error [mm] | median r_err_mm |",
          file=out)
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |", file=out)
    for probe in ("RRI2", "RRL", "both"):
        sel = rows if probe == "both" else [r for r in rows if r["probe"] == probe]
        for name, cl in classes(sel):
            s = stats(cl)
            if not s:
                continue
            print("| %s | %s | %d%s | %.2f | %.1f %% | %.1f | %.4f | %.3f | %.4f |" % (
                probe, name, s["n"], " (few)" if s["n"] < min_n else "", s["rms_pull"], 100 * s["within2"],
                s["max_pull"], s["rms_err"], s["max_err"], s["median_sigma"]), file=out)


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=4, help="random truths (default 4)")
    ap.add_argument("--master-seed", type=int, help="master seed (default: drawn at random and printed)")
    ap.add_argument("--amplitude", type=float, default=0.05, help="largest move, fraction of each bound range")
    ap.add_argument("--particles", type=int, default=0, help="synth bunch size (default: synth's, 2000 on ring8)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bin", default=os.path.join(REPO, "build", "tools"), help="folder of the turnfit tools")
    ap.add_argument("--work", help="keep (and reuse) synth's measurements here (default: a temporary folder, removed)")
    ap.add_argument("--dump", help="write every matched peak as JSON Lines to this file")
    ap.add_argument("--min-n", type=int, default=10, help="classes with fewer peaks are marked 'few' (default 10)")
    ap.add_argument("--json", help="write the pull statistics per probe and class to this JSON file")
    args = ap.parse_args(argv)
    if args.truths < 1:
        ap.error("--truths must be at least 1")
    tools = {t: os.path.join(os.path.abspath(args.bin), "turnfit-" + t) for t in ("track", "synth", "peakfind", "localsearch")}
    for t, p in tools.items():
        if not os.access(p, os.X_OK):
            print("peak_pulls: %s not found (--bin %s)" % (p, args.bin), file=sys.stderr)
            return 2
    master = args.master_seed if args.master_seed is not None else random.SystemRandom().randrange(1, 2 ** 31)
    work = os.path.abspath(args.work) if args.work else tempfile.mkdtemp(prefix="peak-pulls-")
    os.makedirs(work, exist_ok=True)
    print("# peak_pulls: master seed %d (repeat: --master-seed %d), %d truth(s), amplitude %g of each bound range, "
          "synth particles %s, tools %s, %s" % (master, master, args.truths, args.amplitude, args.particles or "default",
                                                args.bin, time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())))
    sys.stdout.flush()
    rows = []
    dump = open(args.dump, "w", encoding="utf-8") if args.dump else None
    try:
        variables = paper_variables(tools, work, args.threads)
        for k in range(args.truths):
            label = "m%d-truth%d" % (master, k + 1)
            seed, truth = draw_truth(random.Random("%d/%d" % (master, k + 1)), variables, args.amplitude)
            t0 = time.time()
            d, meas, fresh = measure(label, seed, truth, args, tools, work)
            synth_s = time.time() - t0
            tdoc = json.load(open(os.path.join(meas, "truth.json")))
            got, wrong_all, missing = [], 0, 0
            for probe, first in (("RRI2", 1), ("RRL", 9)):
                out = os.path.join(d, probe + "-peaks.csv")
                run([tools["peakfind"], os.path.join(meas, probe + ".csv"), "--first-turn", str(first), "-q", "-o", out],
                    "turnfit-peakfind " + probe)
                peaks = read_csv(out)
                if "r_err_mm" not in peaks[0]:
                    raise ToolError("%s: peakfind wrote no r_err_mm column" % out)
                extra = None
                if dump:
                    js = os.path.join(d, probe + "-peaks.json")
                    run([tools["peakfind"], os.path.join(meas, probe + ".csv"), "--first-turn", str(first), "-q",
                         "--format", "json", "-o", js], "turnfit-peakfind --format json " + probe)
                    extra = json.load(open(js))["peaks"]
                r, wrong = match(label, probe, peaks, extra, tdoc["turns"][probe])
                got += r
                wrong_all += wrong
                full = max(t["particles"] for t in tdoc["turns"][probe])
                missing += sum(1 for t in tdoc["turns"][probe] if t["particles"] >= 0.1 * full) - len(peaks)
            flagged = {}
            for r in got:
                for f in r["flags"]:
                    flagged[f] = flagged.get(f, 0) + 1
            s = stats(got)
            print("# %s: synth seed %d (%s, %.0f s), %d peaks matched, %d misnumbered, %d true turns without a peak; "
                  "flags %s; RMS pull %.2f, within 2 sigma %.1f %%, max |error| %.3f mm" % (
                      label, seed, "synth run" if fresh else "reused", synth_s, len(got), wrong_all, max(missing, 0),
                      flagged or "none", s["rms_pull"], 100 * s["within2"], s["max_err"]))
            sys.stdout.flush()
            rows += got
            if dump:
                for r in got:
                    dump.write(json.dumps(r) + "\n")
    except ToolError as e:
        print("peak_pulls: %s" % e, file=sys.stderr)
        return 2
    finally:
        if dump:
            dump.close()
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    print_table(rows, args.min_n, sys.stdout)
    if args.json:
        doc = {"master_seed": master, "args": vars(args), "classes": {}}
        for probe in ("RRI2", "RRL", "both"):
            sel = rows if probe == "both" else [r for r in rows if r["probe"] == probe]
            doc["classes"][probe] = {name: stats(cl) for name, cl in classes(sel)}
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
