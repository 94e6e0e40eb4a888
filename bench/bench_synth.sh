#!/bin/sh
# bench_synth.sh (issue 17): turnfit-synth of the shipped measurement (the command make_ring8.py
# runs for measured/: the truth with truth-dvars.json, seed and current from params.json, 5000
# particles) with the reference stepper and with the default, in the same script, on all cores;
# wall times, their ratio, and how far the two measurements are apart (turn centroids and
# probe profiles).
#
# Usage: bench/bench_synth.sh BUILD_DIR [PARTICLES]
set -eu
build=${1:?usage: bench_synth.sh BUILD_DIR [PARTICLES]}
particles=${2:-5000}
here=$(cd "$(dirname "$0")" && pwd)
ring8="$here/../share/turnfit/ring8"
synth="$(cd "$build" && pwd)/tools/turnfit-synth"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
seed=$(python3 -c "import json; print(json.load(open('$ring8/params.json'))['truth']['seed'])")
current=$(python3 -c "import json; print(json.load(open('$ring8/params.json'))['truth']['current_uA'])")
run() {  # label, extra flags
  start=$(date +%s.%N)
  (cd "$ring8" && "$synth" truth-machine.json --dvars truth-dvars.json --seed "$seed" --current-uA "$current" \
     --particles "$particles" --no-provenance -q -o "$work/$1" $2)
  end=$(date +%s.%N)
  python3 -c "print('%.2f' % ($end - $start))"
}
echo "turnfit-synth of ring8's measurement: $particles particles, seed $seed, $(nproc) cores, $(date -u +%Y-%m-%dT%H:%MZ)"
t_ref=$(run reference --reference-stepper)
t_new=$(run default "")
python3 - "$work" "$t_ref" "$t_new" <<'PY'
import csv, json, sys, os
work, t_ref, t_new = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
print("reference stepper: %.2f s   default: %.2f s   ratio %.2fx" % (t_ref, t_new, t_ref / t_new))
a = json.load(open(os.path.join(work, "reference", "truth.json")))
b = json.load(open(os.path.join(work, "default", "truth.json")))
worst = 0.0
for probe, rows in a["turns"].items():
    for ra, rb in zip(rows, b["turns"][probe]):
        worst = max(worst, abs(ra["r_mm"] - rb["r_mm"]))
print("bunch centroids (truth.json turns): max |dr| %.2e mm" % worst)
def profile(path):
    with open(path) as f:
        return [r for r in csv.reader(l for l in f if not l.startswith("#"))]
for name in sorted(os.listdir(os.path.join(work, "reference"))):
    if not name.endswith(".csv") or name.startswith("TC"):
        continue
    pa, pb = profile(os.path.join(work, "reference", name)), profile(os.path.join(work, "default", name))
    diff = 0.0
    for ra, rb in zip(pa[1:], pb[1:]):
        for x, y in zip(ra, rb):
            try:
                diff = max(diff, abs(float(x) - float(y)))
            except ValueError:
                pass
    print("profile %s: %d rows, max |difference| of any column %.3g" % (name, len(pa) - 1, diff))
PY
