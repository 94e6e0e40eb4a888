#!/usr/bin/env python3
"""Check a sentence of turnfit-peakfind(1)'s ACCURACY section against peakfind and a truth.json.

The sentence (the man page's text from --sentence, de-roffed, to the first '.' that ends a
sentence) states the figures; nothing here restates them, so editing the man page or changing
peakfind without the other fails. What it may state, and what is checked:

- "every turn found": each turn of the truth (truth.json's turns[PROBE]) has a peak numbered so;
  "none spurious": no peak has a turn number the truth does not have; "every turn numbered
  right": each peak's nearest true turn is the one its number says, nearer than half the
  separation to that turn's neighbour on the peak's side.
- "PROBE max X mm, RMS Y mm" or "PROBE turns A-B max X[ mm], RMS Y mm": the largest and the RMS
  of |r_peak - r_true| over the probe's turns (or turns A-B). Tolerance: half a unit of the last
  digit the man page prints (the figure is the measured one, rounded).
- "(with --position fit: X1/Y1 and X2/Y2 mm)": the same figures, in the same order, with peakfind
  --position fit.

Every probe given with --profile must have a figure in the sentence and every figure a profile,
and a probe's turn ranges must cover its true turns once each.
Exit 0 ok, 1 a figure or a claim is not what peakfind gives, 2 the sentence or the inputs are wrong.
"""
import argparse
import csv
import io
import json
import math
import os
import re
import subprocess
import sys

CLAIM = re.compile(r"\b([A-Z][A-Z0-9]*)(?: turns (\d+)-(\d+))? max (\d+\.\d+)(?: mm)?, RMS (\d+\.\d+) mm")
FIT = re.compile(r"\(with --position fit ?: ((?:\d+\.\d+/\d+\.\d+(?: and |, )?)+) mm\)")


class Bad(Exception):
    pass


def sentence(man_path, start):
    text = []
    with open(man_path, encoding="utf-8") as f:
        for line in f:
            line = line.rstrip("\n")
            if line.startswith(".\\\""):
                continue
            m = re.match(r"^\.(B|I|BR|IR|RB|BI|IB|RI)\s+(.*)$", line)
            if m:
                line = m.group(2).replace('"', "")
            elif line.startswith("."):
                line = "\n\n"  # another request (.SH, .PP, ...) ends any sentence
            text.append(line)
    flat = re.sub(r"[ \t]*\n[ \t]*", " ", "\n".join(text)).replace("\\-", "-").replace("\\(em", "--")
    flat = re.sub(r"[ \t]+", " ", flat)
    i = flat.find(start)
    if i < 0:
        raise Bad("%s: no sentence starting %r" % (man_path, start))
    m = re.compile(r"\.(\s|$)").search(flat, i)
    return flat[i:m.start() + 1] if m else flat[i:]


def half_unit(figure):
    return 0.5 * 10.0 ** -len(figure.split(".")[1])


def run_peakfind(bin_dir, path, first_turn, position):
    argv = [os.path.join(bin_dir, "turnfit-peakfind"), path, "--no-provenance"]
    if first_turn is not None:
        argv += ["--first-turn", str(first_turn)]
    if position:
        argv += ["--position", position]
    p = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=120)
    if p.returncode != 0:
        raise Bad("%s exited %d: %s" % (" ".join(argv), p.returncode, p.stderr.decode().strip()))
    rows = csv.DictReader(io.StringIO("".join(l for l in p.stdout.decode().splitlines(True)
                                              if not l.startswith("#"))))
    peaks = {}
    for row in rows:
        turn = int(row["turn"])
        if turn in peaks:
            raise Bad("%s: turn %d twice" % (path, turn))
        peaks[turn] = float(row["r_mm"])
    return peaks


def numbering_errors(peaks, truth):
    """Peaks whose nearest true turn is another, or that sit beyond half a separation."""
    turns = sorted(truth)
    bad = []
    for k, r in sorted(peaks.items()):
        nearest = min(turns, key=lambda j: abs(truth[j] - r))
        if nearest != k:
            bad.append("turn %d at %.3f mm is nearest to true turn %d" % (k, r, nearest))
            continue
        side = k + 1 if r > truth[k] else k - 1
        if side in truth and abs(r - truth[k]) >= 0.5 * abs(truth[side] - truth[k]):
            bad.append("turn %d at %.3f mm is half a separation or more from its true %.3f mm"
                       % (k, r, truth[k]))
    return bad


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--man", required=True, help="man/man1/turnfit-peakfind.1")
    ap.add_argument("--sentence", required=True, help="how the sentence starts")
    ap.add_argument("--bin", required=True, help="folder of turnfit-peakfind")
    ap.add_argument("--truth", required=True, help="truth.json of turnfit-synth")
    ap.add_argument("--profile", action="append", required=True, metavar="PROBE=FILE[:FIRST_TURN]")
    args = ap.parse_args()
    try:
        text = sentence(args.man, args.sentence)
        print("man page: %s" % text)
        claims = [(m.group(1), int(m.group(2)) if m.group(2) else None,
                   int(m.group(3)) if m.group(3) else None, m.group(4), m.group(5))
                  for m in CLAIM.finditer(text)]
        if not claims:
            raise Bad("the sentence states no 'PROBE [turns A-B] max X mm, RMS Y mm'")
        fit = FIT.search(text)
        fit_claims = []
        if fit:
            fit_claims = [tuple(pair.split("/")) for pair in re.findall(r"\d+\.\d+/\d+\.\d+", fit.group(1))]
            if len(fit_claims) != len(claims):
                raise Bad("%d --position fit figures for %d figures" % (len(fit_claims), len(claims)))
        with open(args.truth, encoding="utf-8") as f:
            truth_doc = json.load(f)
        profiles = {}
        for spec in args.profile:
            probe, eq, rest = spec.partition("=")
            path, _, first = rest.partition(":")
            if not eq or not path:
                raise Bad("--profile %s: PROBE=FILE[:FIRST_TURN]" % spec)
            if probe not in truth_doc.get("turns", {}):
                raise Bad("%s: no turns of %s" % (args.truth, probe))
            profiles[probe] = (path, int(first) if first else None)
        stated = {c[0] for c in claims}
        if stated != set(profiles):
            raise Bad("the sentence has figures for %s, the profiles are %s"
                      % (", ".join(sorted(stated)), ", ".join(sorted(profiles))))
    except (Bad, OSError, ValueError) as e:
        print("check_peakfind_accuracy: %s" % e, file=sys.stderr)
        return 2

    failures = []
    checks = 0
    truth = {p: {d["turn"]: d["r_mm"] for d in truth_doc["turns"][p]} for p in profiles}
    try:
        found = {p: run_peakfind(args.bin, path, first, None) for p, (path, first) in profiles.items()}
        found_fit = ({p: run_peakfind(args.bin, path, first, "fit") for p, (path, first) in profiles.items()}
                     if fit_claims else {})
    except (Bad, subprocess.TimeoutExpired) as e:
        print("check_peakfind_accuracy: %s" % e, file=sys.stderr)
        return 1

    for p in sorted(profiles):
        missing = sorted(set(truth[p]) - set(found[p]))
        spurious = sorted(set(found[p]) - set(truth[p]))
        bad = numbering_errors(found[p], truth[p])
        print("%s: %d true turns, %d peaks, %d missing, %d spurious, %d numbered wrong"
              % (p, len(truth[p]), len(found[p]), len(missing), len(spurious), len(bad)))
        for claim, wrong, what in (("every turn found", missing, "missing turns"),
                                   ("none spurious", spurious, "spurious turns"),
                                   ("every turn numbered right", bad, "numbered wrong")):
            if claim in text:
                checks += 1
                if wrong:
                    failures.append("%s: '%s', but %s: %s" % (p, claim, what, wrong[:10]))

    for index, (p, a, b, max_s, rms_s) in enumerate(claims):
        runs = [("", found[p], max_s, rms_s)]
        if fit_claims:
            runs.append((" --position fit", found_fit[p], fit_claims[index][0], fit_claims[index][1]))
        turns = [k for k in sorted(truth[p]) if a is None or a <= k <= b]
        if not turns:
            failures.append("%s turns %s-%s: the truth has none" % (p, a, b))
            continue
        for label, peaks, max_fig, rms_fig in runs:
            errors = [peaks[k] - truth[p][k] for k in turns if k in peaks]
            name = "%s%s%s" % (p, " turns %d-%d" % (a, b) if a is not None else "", label)
            if len(errors) != len(turns):
                failures.append("%s: %d of %d turns found" % (name, len(errors), len(turns)))
                continue
            largest = max(abs(e) for e in errors)
            rms = math.sqrt(sum(e * e for e in errors) / len(errors))
            for what, value, figure in (("max", largest, max_fig), ("RMS", rms, rms_fig)):
                checks += 1
                ok = abs(value - float(figure)) <= half_unit(figure) * (1 + 1e-9)
                print("%s %s: %.4f mm, man page %s mm (+-%g): %s"
                      % (name, what, value, figure, half_unit(figure), "ok" if ok else "DIFFERS"))
                if not ok:
                    failures.append("%s %s %.4f mm, the man page says %s mm" % (name, what, value, figure))

    # The figures of a probe cover its turns: a range left out would go unchecked.
    for p in sorted(profiles):
        covered = []
        for q, a, b, _, _ in claims:
            if q == p:
                covered += sorted(truth[p]) if a is None else list(range(a, b + 1))
        checks += 1
        if sorted(covered) != sorted(truth[p]):
            left = sorted(set(truth[p]) - set(covered))
            twice = sorted({k for k in covered if covered.count(k) > 1})
            failures.append("%s: the figures' turn ranges leave out turns %s, repeat turns %s, "
                            "or name turns the truth has not" % (p, left[:10], twice[:10]))

    for f in failures:
        print("FAIL %s" % f)
    print("%d checks, %d failed" % (checks, len(failures)))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
