#!/usr/bin/env python3
"""blind_localsearch: turnfit-localsearch recovering hidden ring8 settings from turnfit-synth data (issue 15).

For each truth, drawn from a master seed (printed; give it with --master-seed to repeat a run):

1. truth: the nominal ring8 machine with every one of the paper's 48 design variables moved by
   f * (upper - lower), f uniform in [-amplitude, amplitude] (default 0.05); no concealed
   effects. The bounds and nominal values come from turnfit-localsearch's own report (one short
   run on the nominal turns, --max-iterations 1), so they are the tool's, not a copy here.
2. measurement: turnfit-synth on the truth at its default noise, wire and drift, with a synth seed
   drawn at random (never 88, the shipped measurement's, nor 1, the man pages'), --no-phase;
   --particles (default: synth's default, the machine's bunch, 2000 on ring8).
3. peaks: turnfit-peakfind on RRI2.csv (first turn 1) and RRL.csv (--first-turn 9). Every peak is
   matched to the nearest true turn of truth.json (the bunch centres synth tracked, numbered as
   turnfit-track numbers them): a peak whose number differs from that turn's is "misnumbered"
   and fails the row (the fit takes peakfind's numbers as they are); a true turn no peak is
   nearest to is "missing", a note (one residual less, not a wrong one).
4. fit: turnfit-localsearch PROBLEM --report R -o best.json from the nominal machine, the problem
   {"machine": ring8, "peaks": [rri2, rrl], "variables": "paper"} (no sigma_mm: estimated, the
   paper's six objectives), as a user would run it.
5. judge (thresholds from issue 15, the SciPy peer's upper figures on such truths):
   - least squares (the report's "after"; its design tracked with turnfit-track --centroid, the
     bunch's centre as the problem predicts it): against truth.json's true bunch centres (of the
     turns the whole bunch reaches inside the probe: a turn cut by the probe's end has the centre of
     the particles inside, which no model of the bunch's centre predicts; a note names it), worst
     turn <= --max-worst (0.12 mm) and RMS <= --max-rms (0.016 mm): how well the fit recovered
     the machine. Against the peaks (what the report says): the same figures, or 1.1 times what
     the effective truth (below) itself reaches there if that is more: a merged pair of turns
     that peakfind splits 0.4 mm wrong is as wrong for a perfect fit. Our noise model is the
     peer's (the issue's peer ran on turnfit-synth at its default noise); peakfind(1)'s ACCURACY
     gives the peak error alone on such profiles, and each row prints it (peaks against
     truth.json's bunch centres). The model predicts the bunch's centre (turnfit-problem(5),
     "bunch"): synth measures a bunch with a 2 deg rms phase spread whose centre runs 0.07 mm
     rms (0.11 max) inside the reference particle; before the problem modelled it (an earlier
     version of this suite, RESULTS) the 48 variables absorbed that offset and moved by up to
     130 of their sigmas.
   - the minimax polish (the report's "minimax", what -o writes): worst turn against the true
     centres <= --max-worst, against the peaks within the limit above and not above the
     least-squares worst turn. Its RMS is printed, not checked: the polish trades RMS for the
     worst turn by design (the paper's rule lets the l2 rise by 0.01 mm a step).
   - uncertainties: every variable the report calls "determined" is compared with its effective
     truth: |value - truth_eff| <= 2 sigma ("value" and "sigma" of the report's variables: the
     least-squares result, where the covariance is computed). Pooled over the random truths at
     least --min-within (90 %) must pass. Why 90 % and not 95 %: a truth has only ~20 determined
     variables; if the sigmas are right, the count outside 2 sigma is Binomial(20, 0.0455): a
     95 % rule allows 1 of 20 and fails a correct fit 23 % of the time per truth, 90 % allows 2
     and fails it 6 % of the time (pooled over 3 truths, ~60 variables, 90 % allows 6: 2 %).
   - the negative control (--control: truth = the nominal machine, only synth's drift and noise):
     the same thresholds, >= 90 % within 2 sigma of nominal + drift and every one within
     3 sigma. ("Every one within 2 sigma" would fail a correct fit with 18 determined variables
     1 - 0.9545^18 = 57 % of the time; every one within 3 sigma fails it 5 %.)
   - --centroid-reference (a diagnostic, not a check): the same fit on the noiseless truth
     (truth.json's bunch centres at the turns peakfind numbered; start, weak prior and sigma as
     the fit's), whose result is where the model puts the measured bunch without peak noise;
     each determined variable's distance from it in sigma tells whether a miss against the
     effective truth comes from the sigma or from the peaks.
   Exit status 0 when every check passes, 1 when one fails, 2 on a usage or tool error.

The effective truth (what synth measured), from lib/turnfit/synth/synth.cpp, apply_drift(): the
run's drift, recorded in truth.json "drift" (dr_mm, dpr_mrad, dvoltage_rel), changes the truth
machine's document before tracking as
   injection.r_mm          += dr_mm                          -> rinit  += dr_mm (same unit, same sign)
   injection.pr_betagamma  += P * dpr_mrad * 1e-3            -> prinit += P * dpr_mrad * 1e-3,
        P = beta*gamma of the truth's injection energy (benergy * 1000 MeV, proton 938.27208816 MeV):
        the drift's "angle" is p_r/p, i.e. prinit, not phiinit (the injection azimuth, untouched)
   every cavity's voltage_MV *= (1 + dvoltage_rel)           -> vmaincav1-4, vftcav and vchange
        all times (1 + dvoltage_rel): main k's document voltage is vmaincavk + vchange/4
        (vchange is additive, turnfit-machine(5)), so scaling both scales their sum exactly
        (the split between vmaincavk and vchange is not unique, but the alternatives differ by
        vchange * dvoltage_rel ~ 1e-6 MV, far below any sigma).
Then the bunch's sample mean, recorded in truth.json "bunch_mean" (synth tracks N particles whose
mean is not the reference particle: 2 deg / sqrt(2000) = 0.045 deg rms of phase at ring8's bunch;
the fit's quadrature is centred on its injection, so the injection variables take up the mean),
from lib/turnfit/track/bunch.cpp, offset_state(): every particle starts at
   r_mm + dr_mm, energy_MeV + dE_MeV, p_r = P_i (pr_betagamma / P + dpr_mrad * 1e-3)
        (P_i = beta*gamma of the particle's energy, P of the injection's), t_ns + dt_ns,
        dt_ns = dphase_deg / (360 f_rf) * 1e3 (positive starts later), at the injection azimuth.
No design variable moves the start time. A particle that starts dt late at azimuth phi follows the
path of one that starts on time at phi + dphi, dphi = -dt / (dt/dphi) < 0 for dt > 0 (the tracker's
azimuth grows with time; dt/dphi = r / (v p_theta/p), physics/azimuth_eom.hpp), with r and p_r/p
moved by their derivatives along that path (dr/dphi = r (p_r/p) / (p_theta/p), d(p_r/p)/dphi =
p_theta/p - r b: at ring8's injection p_r/p = -0.042 and the sector field make both matter). synth
evaluates this in the truth's field at the mean start (synth.cpp, bunch_mean()) and records the
result in "bunch_mean" "at_reference_time" (dr_mm, dpr_mrad, dE_MeV, dphi_deg), so
   rinit   += at.dr_mm;  benergy += at.dE_MeV / 1000;  phiinit += at.dphi_deg
        (about -dphase_deg / h = -dphase_deg / 6 on ring8's isochronous orbit; the injection azimuth)
   prinit   = P' (prinit_drift / P + at.dpr_mrad * 1e-3), P' = beta*gamma at the new benergy:
        the quadrature's nodes sit at p_r/p offsets around the injection's p_r/p, as offset_state puts them
The vertical mean (dz_mm, dpz_mrad) has no design variable and does not move the radial motion to
first order in a median-plane-symmetric field; it is recorded, not mapped.
The truth's dvars are read back from truth.json "dvars" (and checked against what was drawn).

--peer (needs SciPy: Debian's python3-scipy, e.g. /usr/bin/python3): the same truth fitted by
scipy.optimize.least_squares(method="trf", bounds, x_scale = bound ranges), residuals
r_sim - r_meas in mm on the same peaks, r_sim from `turnfit-track --dvars` (one process per
design), from the nominal machine, as a user would. Forward differences with steps of
--peer-step (1e-4) of each bound range (turnfit-track prints radii to 1e-6 mm; SciPy's default
relative step, 1.5e-8 of |x|, leaves some derivatives in the rounding), backward at an upper
bound; the n designs of one Jacobian run on --threads processes at once, as localsearch's do.
--peer-step 0: SciPy's own "2-point" Jacobian at its default step, one design at a time.
A measured turn a design misses counts 10 mm, as in localsearch. Counts every design simulated.

Usage: blind_localsearch.py [--truths N] [--control] [--master-seed S] [--peer [--peer-on K]]
       [--particles N] [--threads 2] [--bin DIR] [--work DIR] [--json FILE]
Python 3 standard library only (SciPy inside --peer only).
"""
import argparse
import concurrent.futures
import importlib
import csv
import json
import math
import os
import random
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
MACHINE = os.path.join(REPO, "share", "turnfit", "ring8", "machine.json")
PROTON_MEV = 938.27208816
SHIPPED_SEEDS = {88, 1}  # share/turnfit/ring8/measured (seed 88), the man pages' runs (seed 1)
VOLTAGE_VARS = ("vmaincav1", "vmaincav2", "vmaincav3", "vmaincav4", "vftcav", "vchange")
MISS_MM = 10.0  # a measured turn the design misses (localsearch's penalty)


class ToolError(Exception):
    pass


def run(args, what, **kw):
    """Run a tool; its stderr is shown when it fails."""
    p = subprocess.run(args, capture_output=True, text=True, **kw)
    if p.returncode != 0:
        raise ToolError("%s failed (exit %d): %s\n%s" % (what, p.returncode, " ".join(args), p.stderr.strip()))
    return p


def read_csv(path_or_text, is_text=False):
    text = path_or_text if is_text else open(path_or_text, encoding="utf-8").read()
    return list(csv.DictReader(l for l in text.splitlines() if l.strip() and not l.startswith("#")))


def turns_of(rows):
    return {(r["probe"], int(r["turn"])): float(r["r_mm"]) for r in rows}


def norms(sim, meas):
    """worst |dr| and RMS over the measured turns the simulation has; and how many it misses."""
    d = [sim[k] - meas[k] for k in meas if k in sim]
    missing = sum(1 for k in meas if k not in sim)
    if not d:
        return float("nan"), float("nan"), missing
    return max(abs(x) for x in d), math.sqrt(sum(x * x for x in d) / len(d)), missing


def write_json(path, doc):
    with open(path, "w", encoding="utf-8") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


# ---------------------------------------------------------------------------------------------

def paper_variables(tools, work, threads):
    """[(name, nominal, lower, upper)] of the paper's 48 variables, from localsearch's report (cached in work)."""
    d = os.path.join(work, "bounds")
    cache = os.path.join(d, "variables.json")
    if os.path.exists(cache):
        return [tuple(v) for v in json.load(open(cache))]
    os.makedirs(d, exist_ok=True)
    turns = os.path.join(d, "nominal-turns.csv")
    run([tools["track"], MACHINE, "-q", "-o", turns], "turnfit-track (nominal)")
    prob = os.path.join(d, "problem.json")
    write_json(prob, {"format": "turnfit-problem/1", "machine": MACHINE, "peaks": turns,
                      "variables": "paper", "sigma_mm": 1})
    rep = os.path.join(d, "report.json")
    run([tools["localsearch"], prob, "--max-iterations", "1", "--no-minimax", "--threads", str(threads),
         "-q", "--report", rep, "-o", os.path.join(d, "best.json")], "turnfit-localsearch (bounds)")
    r = json.load(open(rep))
    out = [(v["name"], v["start"], v["lower"], v["upper"]) for v in r["variables"]]
    if len(out) != 48:
        raise ToolError("the paper's variables: expected 48, the report lists %d" % len(out))
    write_json(cache, out)
    return out


def draw_truth(rng, variables, amplitude, control=False):
    """The synth seed (never a shipped one) and the truth's dvars: each variable moved by a uniform
    fraction of its bound range, up to amplitude (the control: not moved; the stream is the same)."""
    seed = rng.randrange(2, 2 ** 31)
    while seed in SHIPPED_SEEDS:
        seed = rng.randrange(2, 2 ** 31)
    fractions = {n: (0.0 if control else rng.uniform(-amplitude, amplitude)) for n, _, _, _ in variables}
    return seed, {n: v + fractions[n] * (hi - lo) for n, v, lo, hi in variables}


def effective_truth(truth_doc):
    """The truth's dvars with synth's drift and its bunch's sample mean applied (see the module doc).
    A truth.json without "bunch_mean" (synth before it recorded one) gets the drift alone, with a note."""
    dv = dict(truth_doc["dvars"])
    dr = truth_doc["drift"]
    eff = dict(dv)
    eff["rinit"] = dv["rinit"] + dr["dr_mm"]
    gamma = 1 + dv["benergy"] * 1000.0 / PROTON_MEV
    betagamma = math.sqrt(gamma * gamma - 1)
    eff["prinit"] = dv["prinit"] + betagamma * dr["dpr_mrad"] * 1e-3
    for name in VOLTAGE_VARS:
        eff[name] = dv[name] * (1 + dr["dvoltage_rel"])
    mean = truth_doc.get("bunch_mean")
    if mean is None:
        print("note: truth.json (seed %s) has no bunch_mean (an older turnfit-synth): the effective truth "
              "leaves out the bunch's sample mean" % truth_doc.get("seed"), file=sys.stderr)
        return eff
    at = mean["at_reference_time"]
    eff["rinit"] += at["dr_mm"]
    eff["phiinit"] = dv["phiinit"] + at["dphi_deg"]
    eff["benergy"] = dv["benergy"] + at["dE_MeV"] / 1000.0
    gamma1 = 1 + eff["benergy"] * 1000.0 / PROTON_MEV
    eff["prinit"] = math.sqrt(gamma1 * gamma1 - 1) * (eff["prinit"] / betagamma + at["dpr_mrad"] * 1e-3)
    return eff


def check_numbering(peaks, truth_turns):
    """Match the peaks to the true turns in radial order; (misnumbered [(probe, peak#, true#)], missing,
    max/rms error). Peaks and true turns are aligned monotonically (both sorted by radius, each peak to
    its own true turn or to none, true turns may be skipped) at the least total |error|, and a peak
    whose number differs from its true turn's is misnumbered; a peak left without a turn (more peaks
    than turns) is misnumbered too. Nearest-turn matching called the two halves of a merged pair
    misnumbered whenever the pair's decomposition put a half nearer its partner (at the paper's noise:
    turns 1.8 mm apart, the half 1.3 mm off), though their numbers were in order; a real numbering
    slip (a turn skipped, every later number off by one) still lands every later peak on another turn.
    Where the numbers jump after a peak (n, then n + k), peakfind has taken turns n .. n + k - 1 as
    merged into that peak, and a match to any of them is right.
    A true turn that fewer than a tenth of the bunch's particles reach inside the probe's extent
    (the last turn at RRL's outer end, cut by the probe's end) is not a turn a profile shows."""
    wrong, missing, errs = [], [], []
    skip_peak = 1e3  # [mm] the cost of leaving a peak without a turn: only when there are too few turns
    for probe, true in truth_turns.items():
        full = max(t["particles"] for t in true)
        tl = sorted((t["r_mm"], t["turn"]) for t in true if t["particles"] >= 0.1 * full)
        got = sorted((r, n) for (p, n), r in peaks.items() if p == probe)
        P, T = len(got), len(tl)
        inf = float("inf")
        # cost[i][j]: the first i peaks aligned within the first j true turns; move[i][j]: how.
        cost = [[inf] * (T + 1) for _ in range(P + 1)]
        move = [[0] * (T + 1) for _ in range(P + 1)]
        for j in range(T + 1):
            cost[0][j] = 0.0
        for i in range(1, P + 1):
            r = got[i - 1][0]
            cost[i][0] = cost[i - 1][0] + skip_peak
            move[i][0] = 2
            for j in range(1, T + 1):
                best, how = cost[i][j - 1], 0                            # true turn j unseen
                c = cost[i - 1][j - 1] + abs(r - tl[j - 1][0])          # peak i is turn j
                if c < best:
                    best, how = c, 1
                c = cost[i - 1][j] + skip_peak                          # peak i has no turn
                if c < best:
                    best, how = c, 2
                cost[i][j], move[i][j] = best, how
        i, j, used = P, T, set()
        while i > 0:
            how = move[i][j]
            if how == 0:
                j -= 1
                continue
            r, n = got[i - 1]
            if how == 1:
                r_t, n_t = tl[j - 1]
                used.add(n_t)
                errs.append(r - r_t)
                # A gap in the numbers after this peak: peakfind took the turns between as merged
                # into it (a wide peak, or a pair it could not split), and any of them is its own.
                last = max(n, got[i][1] - 1) if i < P else n
                if not n <= n_t <= last:
                    wrong.append((probe, n, n_t))
                j -= 1
            else:
                wrong.append((probe, n, None))
            i -= 1
        missing += [(probe, n) for _, n in tl if n not in used]
    rms = math.sqrt(sum(e * e for e in errs) / len(errs)) if errs else float("nan")
    return wrong, missing, max(abs(e) for e in errs) if errs else float("nan"), rms


def check_truth_dvars(label, tdoc, drawn):
    """truth.json's dvars must be the drawn ones (synth applied what it was given)."""
    for n, v in drawn.items():
        if abs(tdoc["dvars"][n] - v) > 1e-9 * max(1.0, abs(v)):
            raise ToolError("%s: truth.json dvars %s = %r, drawn %r" % (label, n, tdoc["dvars"][n], v))


def measured_peaks(tools, meas, d, tdoc, row):
    """turnfit-peakfind on meas's RRI2.csv and RRL.csv (--first-turn 9) into d, every peak matched to
    truth.json's true turns (check_numbering); fills row's peaks, true_turns, misnumbered, missing
    and its failures (a misnumbered turn) and notes (a missed turn); returns the peaks, the worst and
    rms error of the peaks against the true turns, and the two peak files [RRI2, RRL]."""
    rri2, rrl = os.path.join(d, "rri2.csv"), os.path.join(d, "rrl.csv")
    run([tools["peakfind"], os.path.join(meas, "RRI2.csv"), "-q", "-o", rri2], "turnfit-peakfind RRI2")
    run([tools["peakfind"], os.path.join(meas, "RRL.csv"), "--first-turn", "9", "-q", "-o", rrl],
        "turnfit-peakfind RRL")
    peaks = turns_of(read_csv(rri2) + read_csv(rrl))
    wrong, missing, pmax, prms = check_numbering(peaks, tdoc["turns"])
    row["peaks"] = len(peaks)
    row["true_turns"] = sum(len(v) for v in tdoc["turns"].values())
    row["misnumbered"], row["missing"] = wrong, missing
    if wrong:
        row["failures"].append("peakfind misnumbered %d turns (probe, peak's number, true number): %s" % (
            len(wrong), wrong[:8]))
    if missing:  # a note: a missed turn is one residual less, not a wrong one
        row["notes"].append("peakfind missed %d true turn(s): %s" % (len(missing), missing[:8]))
    return peaks, pmax, prms, [rri2, rrl]


def track_turns(tools, dvars_path, centroid=False):
    """turnfit-track's turns of the machine with these dvars: the reference particle's, or with
    centroid the bunch's centre as a turn-pattern problem predicts it (turnfit-track --centroid)."""
    p = run([tools["track"], MACHINE, "--dvars", dvars_path, "-q", "--no-provenance", "-o", "-"] +
            (["--centroid"] if centroid else []), "turnfit-track")
    return turns_of(read_csv(p.stdout, is_text=True))


def true_centres(tdoc, peaks, partial=None):
    """truth.json's bunch centres at the measured (probe, turn) (the numbering is checked separately).
    A turn that part of the bunch does not reach inside the probe's extent (fewer than 99 % of the
    probe's fullest turn: the last RRL turn, cut by the probe's end) is left out and its key added to
    `partial`: its true centre is the mean of the particles inside, not the bunch's centre the model
    predicts (on one truth 1648 of 2000 particles, 0.46 mm apart), so neither a perfect model nor a
    perfect fit meets it. The fit still sees its peak (flagged edge by peakfind, with its r_err)."""
    t = {}
    for probe, true in tdoc["turns"].items():
        full = max(x["particles"] for x in true)
        for x in true:
            if x["particles"] >= 0.99 * full:
                t[(probe, x["turn"])] = x["r_mm"]
            elif partial is not None and (probe, x["turn"]) in peaks:
                partial.append((probe, x["turn"], x["particles"], full))
    return {k: t[k] for k in peaks if k in t}


def design_of(report):
    return {v["name"]: v["value"] for v in report["variables"]}


def one_truth(label, rng, variables, args, tools, work, control):
    """Draw, measure, find peaks, fit, judge one truth; returns the row (a dict)."""
    d = os.path.join(work, label)
    os.makedirs(d, exist_ok=True)
    seed, truth = draw_truth(rng, variables, args.amplitude, control)
    truth_path = os.path.join(d, "truth-dvars.json")
    write_json(truth_path, truth)
    row = {"label": label, "synth_seed": seed, "control": control, "failures": [], "notes": []}

    meas = os.path.join(d, "meas")
    cmd = [tools["synth"], MACHINE, "--dvars", truth_path, "--seed", str(seed), "--no-phase",
           "--threads", str(args.threads), "-q", "--out", meas]
    if args.particles:
        cmd += ["--particles", str(args.particles)]
    t0 = time.time()
    run(cmd, "turnfit-synth")
    row["synth_wall_s"] = time.time() - t0
    tdoc = json.load(open(os.path.join(meas, "truth.json")))
    row["particles"], row["lost"], row["drift"] = tdoc["particles"], tdoc["lost"], {
        k: tdoc["drift"][k] for k in ("dr_mm", "dpr_mrad", "dvoltage_rel")}
    check_truth_dvars(label, tdoc, truth)
    eff = effective_truth(tdoc)
    eff_path = os.path.join(d, "effective-truth-dvars.json")
    write_json(eff_path, eff)

    peaks, pmax, prms, peak_files = measured_peaks(tools, meas, d, tdoc, row)
    row["peak_err_max_mm"], row["peak_err_rms_mm"] = pmax, prms

    # The truth with and without the drift, the bunch's centre as the fit predicts it, against the
    # peaks: with the drift, the floor a perfect fit reaches (the peaks' own errors and the model's).
    row["truth_nodrift"] = norms(track_turns(tools, truth_path, True), peaks)[:2]
    eff_turns = track_turns(tools, eff_path, True)
    row["truth_drift"] = norms(eff_turns, peaks)[:2]
    partial = []
    centres = true_centres(tdoc, peaks, partial)
    if partial:
        row["notes"].append("true centres of %d partial turn(s) not judged (particles inside the probe / the "
                            "bunch): %s" % (len(partial), ", ".join("%s %d %d/%d" % p for p in partial)))
    row["truth_drift_vs_centres"] = norms(eff_turns, centres)[:2]

    prob = os.path.join(d, "problem.json")
    write_json(prob, {"format": "turnfit-problem/1", "machine": MACHINE, "peaks": peak_files, "variables": "paper"})
    rep, best = os.path.join(d, "report.json"), os.path.join(d, "best.json")
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.time()
    run([tools["localsearch"], prob, "--report", rep, "--residuals", os.path.join(d, "residuals.csv"),
         "-o", best, "--threads", str(args.threads), "-q"], "turnfit-localsearch")
    row["wall_s"] = time.time() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    row["cpu_s"] = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    r = json.load(open(rep))
    row["report_wall_s"], row["report_cpu_s"] = r["wall_s"], r["cpu_s"]
    row["before"] = (r["before"]["linf_mm"], r["before"]["rms_mm"])
    row["after"] = (r["after"]["linf_mm"], r["after"]["rms_mm"])
    mm = r.get("minimax") or {}
    row["minimax"] = (mm.get("linf_mm", float("nan")), mm.get("rms_mm", float("nan")))
    row["evaluations"] = r["evaluations"]
    row["polish_evaluations"] = mm.get("evaluations", 0)
    row["ls_evaluations"] = r["evaluations"] - row["polish_evaluations"]
    row["termination"] = r["termination"]
    row["chi2_dof"] = r["after"]["chi2_dof"]
    row["sigma_mm"] = r["sigma_mm"]
    row["matched"] = (r["after"]["matched"], len(peaks))

    # The fitted machines' bunch centres against the true ones: how well the fit recovered the
    # machine, whatever the peaks' errors.
    ls_path = os.path.join(d, "ls-dvars.json")
    write_json(ls_path, design_of(r))
    row["ls_vs_centres"] = norms(track_turns(tools, ls_path, True), centres)[:2]
    row["polish_vs_centres"] = norms(track_turns(tools, best, True), centres)[:2]

    checks = []
    # Against the true centres: the issue's figures. Against the peaks: those figures, or the floor
    # the effective truth itself reaches there (a merged pair peakfind splits 0.4 mm wrong is as
    # wrong for a perfect fit), with 10 % to spare.
    worst_lim = max(args.max_worst, 1.1 * row["truth_drift"][0])
    rms_lim = max(args.max_rms, 1.1 * row["truth_drift"][1])
    for what, (w, rms) in (("least squares against the true centres", row["ls_vs_centres"]),
                           ("least squares against the peaks", row["after"])):
        wl, rl = (args.max_worst, args.max_rms) if "centres" in what else (worst_lim, rms_lim)
        if not w <= wl:
            row["failures"].append("%s: worst turn %.4f mm > %.3f mm" % (what, w, wl))
        if not rms <= rl:
            row["failures"].append("%s: RMS %.4f mm > %.4f mm" % (what, rms, rl))
    if not row["polish_vs_centres"][0] <= args.max_worst:
        row["failures"].append("minimax polish against the true centres: worst turn %.4f mm > %.3f mm" % (
            row["polish_vs_centres"][0], args.max_worst))
    if not row["minimax"][0] <= worst_lim:
        row["failures"].append("minimax polish against the peaks: worst turn %.4f mm > %.3f mm" % (
            row["minimax"][0], worst_lim))
    if not row["minimax"][0] <= row["after"][0] + 1e-9:
        row["failures"].append("minimax polish: worst turn %.4f mm above least squares' %.4f mm" % (
            row["minimax"][0], row["after"][0]))

    for v in r["variables"]:
        if not v["determined"]:
            continue
        t = eff[v["name"]]
        z = (v["value"] - t) / v["sigma"] if v["sigma"] > 0 else float("inf")
        checks.append({"name": v["name"], "value": v["value"], "truth_eff": t, "truth": tdoc["dvars"][v["name"]],
                       "sigma": v["sigma"], "z": z})
    row["determined"] = checks
    if args.centroid_reference:
        centroid_reference(row, r, peaks, tdoc, args, tools, d)
    row["within2"] = sum(1 for c in checks if abs(c["z"]) <= 2)
    row["within3"] = sum(1 for c in checks if abs(c["z"]) <= 3)
    if control:
        n = len(checks)
        if n and row["within2"] < args.min_within * n:
            row["failures"].append("control: %d of %d determined variables within 2 sigma of nominal + drift (< %.0f %%)"
                                   % (row["within2"], n, 100 * args.min_within))
        if row["within3"] < n:
            row["failures"].append("control: %s beyond 3 sigma of nominal + drift" % ", ".join(
                "%s (%.1f sigma)" % (c["name"], c["z"]) for c in checks if abs(c["z"]) > 3))
    if args.max_evaluations and row["evaluations"] > args.max_evaluations:
        row["failures"].append("%d evaluations > %d" % (row["evaluations"], args.max_evaluations))
    return row


def centroid_reference(row, report, peaks, tdoc, args, tools, d):
    """Diagnostic (--centroid-reference): the same fit on the noiseless truth, i.e. on truth.json's
    bunch centres of the turns peakfind numbered, same start (nominal), same weak prior, sigma
    fixed at the fit's estimate. Its result is where the model (one reference particle) puts the
    measured bunch without peak noise: the fitted values should lie within 2 sigma of it if the
    sigmas are right, whatever the bunch's own offset from the reference particle does. Tracked
    and compared with the peaks, it also says what the peaks' own errors leave to any fit."""
    cpath = os.path.join(d, "centroids.csv")
    true = {(p, t["turn"]): t["r_mm"] for p, turns in tdoc["turns"].items() for t in turns}
    with open(cpath, "w", encoding="utf-8") as f:
        f.write("probe,turn,r_mm\n")
        for k in sorted(peaks):
            if k in true:
                f.write("%s,%d,%.9f\n" % (k[0], k[1], true[k]))
    sig = report["sigma_mm"].get("per_probe")
    if not sig:  # older reports: one value per probe in order
        sig = {"RRI2": row["after"][1], "RRL": row["after"][1]}
    prob = os.path.join(d, "problem-centroids.json")
    write_json(prob, {"format": "turnfit-problem/1", "machine": MACHINE, "peaks": cpath,
                      "variables": "paper", "sigma_mm": sig})
    rep = os.path.join(d, "report-centroids.json")
    t0 = time.time()
    run([tools["localsearch"], prob, "--no-minimax", "--report", rep, "-o", os.path.join(d, "best-centroids.json"),
         "--threads", str(args.threads), "-q"], "turnfit-localsearch (centroid reference)")
    rr = json.load(open(rep))
    ref = {v["name"]: v["value"] for v in rr["variables"]}
    vs_peaks = norms(track_turns(tools, os.path.join(d, "best-centroids.json")), peaks)[:2]
    for c in row["determined"]:
        c["ref"] = ref[c["name"]]
        c["z_ref"] = (c["value"] - c["ref"]) / c["sigma"] if c["sigma"] > 0 else float("inf")
    row["ref"] = {"after": (rr["after"]["linf_mm"], rr["after"]["rms_mm"]), "vs_peaks": vs_peaks,
                  "evaluations": rr["evaluations"],
                  "wall_s": time.time() - t0,
                  "within2": sum(1 for c in row["determined"] if abs(c["z_ref"]) <= 2),
                  "within3": sum(1 for c in row["determined"] if abs(c["z_ref"]) <= 3)}


# ---------------------------------------------------------------------------------------------
# The SciPy peer (optional).

def peer_fit(row, variables, args, tools, work):
    import numpy as np
    from scipy.optimize import least_squares

    d = os.path.join(work, row["label"], "peer")
    os.makedirs(d, exist_ok=True)
    peaks = turns_of(read_csv(os.path.join(work, row["label"], "rri2.csv")) +
                     read_csv(os.path.join(work, row["label"], "rrl.csv")))
    keys = sorted(peaks)
    names = [n for n, _, _, _ in variables]
    x0 = np.array([v for _, v, _, _ in variables])
    lo = np.array([l for _, _, l, _ in variables])
    hi = np.array([h for _, _, _, h in variables])
    rng_ = hi - lo
    count = [0]
    counter_lock = threading.Lock()

    def simulate(x, slot):
        path = os.path.join(d, "x%d.json" % slot)
        write_json(path, {n: float(v) for n, v in zip(names, x)})
        p = subprocess.run([tools["track"], MACHINE, "--dvars", path, "-q", "--no-provenance", "-o", "-"],
                           capture_output=True, text=True)
        with counter_lock:
            count[0] += 1
        sim = turns_of(read_csv(p.stdout, is_text=True)) if p.returncode == 0 else {}
        return np.array([sim[k] - peaks[k] if k in sim else MISS_MM for k in keys])

    cache = {}

    def fun(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = simulate(x, 0)
        return cache[key]

    pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, args.threads))

    def jac(x):
        f0 = fun(x)
        steps = []
        for i in range(len(x)):
            h = args.peer_step * rng_[i]
            steps.append(-h if x[i] + h > hi[i] else h)
        futs = []
        for i, h in enumerate(steps):
            xi = x.copy()
            xi[i] += h
            futs.append(pool.submit(simulate, xi, i + 1))
        J = np.empty((len(f0), len(x)))
        for i, (fu, h) in enumerate(zip(futs, steps)):
            J[:, i] = (fu.result() - f0) / h
        return J

    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    c0 = time.process_time()
    t0 = time.time()
    f_start = fun(x0)
    tol = args.peer_tol
    res = least_squares(fun, x0, jac=jac if args.peer_step > 0 else "2-point", bounds=(lo, hi), method="trf",
                        x_scale=rng_, xtol=tol, ftol=tol, gtol=tol)
    wall = time.time() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime) + (time.process_time() - c0)
    pool.shutdown()
    f = fun(res.x)
    write_json(os.path.join(d, "best.json"), {n: float(v) for n, v in zip(names, res.x)})
    return {"before": (float(np.max(np.abs(f_start))), float(np.sqrt(np.mean(f_start ** 2)))),
            "after": (float(np.max(np.abs(f))), float(np.sqrt(np.mean(f ** 2)))),
            "evaluations": count[0], "nfev": int(res.nfev), "njev": int(res.njev or 0),
            "wall_s": wall, "cpu_s": cpu, "status": int(res.status), "message": res.message}


# ---------------------------------------------------------------------------------------------

def fmt_pair(p, digits=3):
    return "%.*f / %.*f" % (digits, p[0], digits + 1, p[1])


def print_row(row, out):
    flag = "ok" if not row["failures"] else "FAIL"
    print("| %s | %d | %s | %s | %s | %s | %d = %d + %d | %.0f / %.0f | %d/%d (%d in 3) | %s | %s |" % (
        row["label"], row["synth_seed"], fmt_pair(row["before"], 2), fmt_pair(row["after"]),
        fmt_pair(row["minimax"]), fmt_pair(row["truth_drift"]), row["evaluations"], row["ls_evaluations"],
        row["polish_evaluations"], row["wall_s"], row["cpu_s"], row["within2"], len(row["determined"]),
        row["within3"], "%d/%d, %d wrong" % (row["peaks"], row["true_turns"], len(row["misnumbered"])), flag),
        file=out)


HEADER = ("| truth | synth seed | worst / RMS before [mm] | least squares: worst / RMS [mm] | "
          "minimax polish: worst / RMS [mm] | truth + drift (centre) vs peaks: worst / RMS [mm] | "
          "evaluations = LS + polish | wall / CPU [s] | determined within 2 sigma | peaks (numbering) | checks |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=3, help="random truths (default 3)")
    ap.add_argument("--control", action="store_true", help="also the negative control (truth = nominal), first")
    ap.add_argument("--master-seed", type=int, help="master seed (default: drawn at random and printed)")
    ap.add_argument("--amplitude", type=float, default=0.05, help="largest move, fraction of each bound range")
    ap.add_argument("--particles", type=int, default=0, help="synth bunch size (default: synth's, 2000 on ring8)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bin", default=os.path.join(REPO, "build", "tools"), help="folder of the turnfit tools")
    ap.add_argument("--work", help="keep every file here (default: a temporary folder, removed)")
    ap.add_argument("--json", help="write every row (and the peer's) to this JSON file")
    ap.add_argument("--max-worst", type=float, default=0.12, help="worst turn threshold [mm] (issue 15: 0.12)")
    ap.add_argument("--max-rms", type=float, default=0.016, help="RMS threshold [mm] (issue 15: 0.016)")
    ap.add_argument("--min-within", type=float, default=0.9, help="fraction of determined variables within 2 sigma")
    ap.add_argument("--max-evaluations", type=int, default=0, help="fail a fit above this many evaluations (0: off)")
    ap.add_argument("--centroid-reference", action="store_true",
                    help="diagnostic: also fit truth.json's noiseless bunch centres and judge against that")
    ap.add_argument("--peer", action="store_true", help="also fit with SciPy's least_squares (needs python3-scipy)")
    ap.add_argument("--peer-on", type=int, default=1, help="the peer on the K-th random truth (default 1)")
    ap.add_argument("--peer-tol", type=float, default=1e-8, help="peer's xtol, ftol and gtol (SciPy's default 1e-8)")
    ap.add_argument("--peer-step", type=float, default=1e-4,
                    help="peer's forward step, fraction of each range (0: SciPy's own 2-point Jacobian, "
                         "relative step 1.5e-8 of |x|, one design at a time)")
    args = ap.parse_args(argv)
    if args.truths < 0 or (args.truths == 0 and not args.control):
        ap.error("nothing to do: --truths 0 without --control")
    if args.peer:
        if not (1 <= args.peer_on <= args.truths):
            ap.error("--peer-on %d: there are %d random truths" % (args.peer_on, args.truths))
        try:
            importlib.import_module("scipy.optimize")
        except ImportError as e:
            print("blind_localsearch: --peer needs SciPy (python3-scipy): %s (python %s)" % (e, sys.executable),
                  file=sys.stderr)
            return 2

    tools = {t: os.path.join(os.path.abspath(args.bin), "turnfit-" + t) for t in ("track", "synth", "peakfind", "localsearch")}
    for t, p in tools.items():
        if not os.access(p, os.X_OK):
            print("blind_localsearch: %s not found (--bin %s)" % (p, args.bin), file=sys.stderr)
            return 2
    master = args.master_seed if args.master_seed is not None else random.SystemRandom().randrange(1, 2 ** 31)
    work = os.path.abspath(args.work) if args.work else tempfile.mkdtemp(prefix="blind-localsearch-")
    os.makedirs(work, exist_ok=True)
    print("# blind_localsearch: master seed %d (repeat: --master-seed %d), %d random truth(s)%s, amplitude %g of "
          "each bound range, synth particles %s, threads %d, tools %s, %s" % (
              master, master, args.truths, " + the control" if args.control else "", args.amplitude,
              args.particles or "default", args.threads, args.bin, time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())))
    print("# load average at start: %.2f %.2f %.2f" % os.getloadavg())
    sys.stdout.flush()
    rows, peer = [], None
    try:
        variables = paper_variables(tools, work, args.threads)
        # Each truth has its own stream (the control's too), so adding the control or truths
        # does not change the others.
        plan = ([("control", True, random.Random("%d/control" % master))] if args.control else []) + [
            ("truth%d" % (k + 1), False, random.Random("%d/%d" % (master, k + 1))) for k in range(args.truths)]
        print(HEADER)
        sys.stdout.flush()
        for label, control, r in plan:
            row = one_truth(label, r, variables, args, tools, work, control)
            rows.append(row)
            print_row(row, sys.stdout)
            sys.stdout.flush()
        for row in rows:
            print("# %s: synth %d particles (%d lost), %.0f s; drift dr %+.3f mm, dpr %+.3f mrad, dV/V %+.2e; "
                  "truth without drift vs peaks %s mm; truth + drift vs the true centres %s mm; fit vs the true "
                  "centres: least squares %s, polish %s mm; peaks vs truth.json centroids max %.3f, RMS %.4f mm; "
                  "chi2/dof %.2f, sigma %s, %s; localsearch's own wall/CPU %.0f/%.0f s" % (
                      row["label"], row["particles"], row["lost"], row["synth_wall_s"], row["drift"]["dr_mm"],
                      row["drift"]["dpr_mrad"], row["drift"]["dvoltage_rel"], fmt_pair(row["truth_nodrift"]),
                      fmt_pair(row["truth_drift_vs_centres"]), fmt_pair(row["ls_vs_centres"]),
                      fmt_pair(row["polish_vs_centres"]),
                      row["peak_err_max_mm"], row["peak_err_rms_mm"], row["chi2_dof"],
                      {k: round(v, 4) for k, v in row["sigma_mm"].get("per_probe", {}).items()} or row["sigma_mm"],
                      row["termination"], row["report_wall_s"], row["report_cpu_s"]))
            outside = [c for c in row["determined"] if abs(c["z"]) > 2]
            print("#   determined: %s" % ", ".join(
                "%s%s %+.1f" % (c["name"], "*" if abs(c["z"]) > 2 else "", c["z"]) for c in row["determined"]))
            for c in outside:
                print("#   outside 2 sigma: %s = %.9g, effective truth %.9g (truth %.9g), sigma %.3g: %+.2f sigma" % (
                    c["name"], c["value"], c["truth_eff"], c["truth"], c["sigma"], c["z"]))
            if "ref" in row:
                ref = row["ref"]
                print("#   centroid reference (the fit on truth.json's bunch centres, no peak noise): worst / RMS %s mm "
                      "against the centres, %s mm against the peaks; %d evaluations, %.0f s; determined within 2 sigma "
                      "of it %d/%d (%d in 3): %s" % (
                          fmt_pair(ref["after"]), fmt_pair(ref["vs_peaks"]), ref["evaluations"], ref["wall_s"], ref["within2"],
                          len(row["determined"]), ref["within3"], ", ".join(
                              "%s %+.1f" % (c["name"], c["z_ref"]) for c in row["determined"])))
                for c in row["determined"]:
                    if abs(c["z"]) > 2:
                        print("#   %s: effective truth to centroid reference %+.2f sigma" % (
                            c["name"], (c["ref"] - c["truth_eff"]) / c["sigma"]))
            for f in row["notes"]:
                print("#   note: %s" % f)
            for f in row["failures"]:
                print("#   FAILED: %s" % f)
        if args.peer:
            target = [r for r in rows if not r["control"]][args.peer_on - 1]
            print("# peer: SciPy least_squares (trf, bounds, x_scale = ranges, forward steps %g of each range, "
                  "%d processes) on %s, from nominal ..." % (args.peer_step, args.threads, target["label"]))
            sys.stdout.flush()
            peer = peer_fit(target, variables, args, tools, work)
            peer["label"] = target["label"]
            print("| peer on %s | worst / RMS before %s | least squares %s | %d evaluations (nfev %d, njev %d) | "
                  "wall / CPU %.0f / %.0f s | %s |" % (
                      target["label"], fmt_pair(peer["before"], 2), fmt_pair(peer["after"]), peer["evaluations"],
                      peer["nfev"], peer["njev"], peer["wall_s"], peer["cpu_s"], peer["message"]))
            print("# localsearch on %s: %d evaluations (%.2f of the peer's), least squares alone %d (%.2f); "
                  "wall %.0f s (%.2f), CPU %.0f s (%.2f)" % (
                      target["label"], target["evaluations"], target["evaluations"] / peer["evaluations"],
                      target["ls_evaluations"], target["ls_evaluations"] / peer["evaluations"], target["wall_s"],
                      target["wall_s"] / peer["wall_s"], target["cpu_s"], target["cpu_s"] / peer["cpu_s"]))
    except ToolError as e:
        print("blind_localsearch: %s" % e, file=sys.stderr)
        for row in rows:
            print_row(row, sys.stderr)
        return 2
    finally:
        if args.json:
            write_json(args.json, {"master_seed": master, "args": vars(args), "rows": rows, "peer": peer})
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)

    failed = [r for r in rows if r["failures"]]
    pooled = [c for r in rows if not r["control"] for c in r["determined"]]
    within = sum(1 for c in pooled if abs(c["z"]) <= 2)
    pooled_ok = not pooled or within >= args.min_within * len(pooled)
    print("# load average at end: %.2f %.2f %.2f" % os.getloadavg())
    if pooled:
        print("# summary: random truths: %d of %d determined variables within 2 sigma of the effective truth "
              "(%.0f %%, need %.0f %%): %s" % (within, len(pooled), 100.0 * within / len(pooled),
                                                100 * args.min_within, "ok" if pooled_ok else "FAIL"))
    truths = [r for r in rows if not r["control"]]
    if truths:
        print("# summary: random truths: least squares worst %.3f-%.3f mm, RMS %.4f-%.4f mm; polish worst %.3f-%.3f mm; "
              "evaluations %d-%d (least squares %d-%d); wall %.0f-%.0f s" % (
                  min(r["after"][0] for r in truths), max(r["after"][0] for r in truths),
                  min(r["after"][1] for r in truths), max(r["after"][1] for r in truths),
                  min(r["minimax"][0] for r in truths), max(r["minimax"][0] for r in truths),
                  min(r["evaluations"] for r in truths), max(r["evaluations"] for r in truths),
                  min(r["ls_evaluations"] for r in truths), max(r["ls_evaluations"] for r in truths),
                  min(r["wall_s"] for r in truths), max(r["wall_s"] for r in truths)))
    print("# summary: %d of %d rows pass their checks%s; %s" % (
        len(rows) - len(failed), len(rows), "" if not failed else " (failed: %s)" % ", ".join(r["label"] for r in failed),
        "ALL CHECKS PASSED" if not failed and pooled_ok else "SOME CHECKS FAILED"))
    return 0 if not failed and pooled_ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
