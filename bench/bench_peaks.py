#!/usr/bin/python3
"""bench_peaks: turnfit-peakfind against scipy.signal.find_peaks on the same probe profiles.

Usage: bench_peaks.py --bin BUILD/tools CASE...   where CASE is NAME:PROFILE.csv:TRUTH[:FIRST_TURN]
and TRUTH is a turnfit-synth truth.json or a turnfit-track turns.csv (bunch centroids).
Prints recall, precision, max and RMS position error side by side (a found turn counts when it
is the nearest to a true turn within half the local turn separation; each true turn once).
scipy is tuned once for these profiles (see TUNED) and refined with a 3-point parabola, its
best use without a fit; needs python3-scipy (bench only).
"""
import argparse, csv, json, math, subprocess, sys, time
import numpy as np
from scipy.signal import find_peaks

def read_profile(path):
    x, y = [], []
    for r in csv.DictReader(l for l in open(path) if not l.startswith('#')):
        x.append(float(r['position_mm'])); y.append(float(r['intensity']))
    return np.array(x), np.array(y)

def read_truth(path, probe):
    if path.endswith('.json'):
        return sorted(t['r_mm'] for t in json.load(open(path))['turns'][probe])
    return sorted(float(r['r_mm']) for r in csv.DictReader(l for l in open(path) if not l.startswith('#')) if r['probe'] == probe)

# Tuned on these profiles: heights relative to the tallest reading, prominence against ripple,
# a minimum distance of 2 mm (below the 4.4 mm closest turn separation of ring8).
TUNED = dict(height=0.02, prominence=0.02, distance_mm=2.0)

def scipy_peaks(x, y):
    step = x[1] - x[0]
    base = np.percentile(y, 5)
    yn = (y - base) / (y.max() - base)
    idx, _ = find_peaks(yn, height=TUNED['height'], prominence=TUNED['prominence'],
                        distance=max(1, int(round(TUNED['distance_mm'] / step))))
    out = []
    for k in idx:  # 3-point parabola through the top
        if 0 < k < len(y) - 1:
            a, b, c = yn[k - 1], yn[k], yn[k + 1]
            den = a - 2 * b + c
            out.append(x[k] + (0.5 * step * (a - c) / den if den != 0 else 0))
        else:
            out.append(x[k])
    return out

def peakfind(binp, path, first):
    args = [binp + '/turnfit-peakfind', path, '-q', '--no-provenance']
    if first: args += ['--first-turn', str(first)]
    t0 = time.perf_counter()
    out = subprocess.run(args, check=True, capture_output=True, text=True).stdout
    dt = time.perf_counter() - t0
    return [float(r['r_mm']) for r in csv.DictReader(l for l in out.splitlines() if not l.startswith('#'))], dt

def score(found, truth):
    truth = np.array(truth)
    sep = np.diff(truth)
    half = np.minimum(np.r_[sep[0], sep], np.r_[sep, sep[-1]]) / 2
    used, errs = set(), []
    for r in found:
        j = int(np.argmin(np.abs(truth - r)))
        if abs(truth[j] - r) < half[j] and j not in used:
            used.add(j); errs.append(r - truth[j])
    tp = len(used)
    e = np.array(errs) if errs else np.array([np.nan])
    return dict(recall=tp / len(truth), precision=tp / max(1, len(found)), max=np.nanmax(np.abs(e)),
                rms=math.sqrt(np.nanmean(e * e)), n=len(truth), found=len(found))

def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--bin', required=True)
    ap.add_argument('cases', nargs='+')
    a = ap.parse_args()
    print('| profile | turns | tool | found | recall | precision | max err [mm] | RMS err [mm] | time [ms] |')
    print('| --- | --- | --- | --- | --- | --- | --- | --- | --- |')
    for c in a.cases:
        parts = c.split(':')
        name, prof, truthp = parts[:3]
        first = int(parts[3]) if len(parts) > 3 else 0
        probe = next(l.split('probe=')[1].split()[0] for l in open(prof) if 'probe=' in l and not l.startswith('# argv'))
        truth = read_truth(truthp, probe)
        x, y = read_profile(prof)
        pf, dt = peakfind(a.bin, prof, first)
        t0 = time.perf_counter(); sp = scipy_peaks(x, y); ds = time.perf_counter() - t0
        for tool, found, t in (('turnfit-peakfind', pf, dt), ('scipy find_peaks', sp, ds)):
            s = score(found, truth)
            print('| %s | %d | %s | %d | %.3f | %.3f | %.3f | %.3f | %.0f |' % (
                name, s['n'], tool, s['found'], s['recall'], s['precision'], s['max'], s['rms'], 1000 * t))
    return 0

if __name__ == '__main__':
    sys.exit(main())
