#!/bin/sh
# Closing the loop on ring8 (issue 5): the committed phase scans of the truth coils (turnfit-synth,
# seed 88) fitted by turnfit-tc-fit with the paper's model and with the tracked model; each
# fitted field shape against the truth coil's, per coil, and the fitted strengths against the
# scans' test excitation. Prints a table; with gnuplot, draws the paper's Figs. 8-9 for ring8.
#   bench/tcfit_loop.sh [BIN [OUT [SCANS]]]   (defaults: build/tools, /tmp/tcfit-loop,
#                                              share/turnfit/ring8/measured/phase)
set -eu
BIN=${1:-build/tools}
OUT=${2:-/tmp/tcfit-loop}
R=share/turnfit/ring8
SCANS=${3:-$R/measured/phase}
mkdir -p "$OUT"
for model in paper tracked; do
  start=$(date +%s.%N)
  "$BIN/turnfit-tc-fit" "$SCANS"/TC*.csv --machine "$R/machine.json" --model "$model" --degrees auto \
    --format csv -q -o "$OUT/$model.csv" --report "$OUT/$model.json" 2> "$OUT/$model.err" || true
  end=$(date +%s.%N)
  echo "$model: $(echo "$end - $start" | bc) s, $(grep -c "coil " "$OUT/$model.err" || true) coil(s) refused"
done

python3 - "$OUT" "$R" "$SCANS" <<'EOF'
import csv, json, math, sys
out, ring8, scans = sys.argv[1], sys.argv[2], sys.argv[3]
truth = {t["name"]: t for t in json.load(open(ring8 + "/truth-machine.json"))["trimcoils"]}
def poly(c, x):
    v = 0.0
    for a in reversed(c):
        v = v * x + a
    return v
def tshape(t, r_mm):
    if r_mm < t["rmin_mm"] or r_mm > t["rmax_mm"]:
        return 0.0
    x = r_mm * 1e-3 - t.get("coef_origin_mm", 0) * 1e-3
    return poly(t["coefnum"], x) / poly(t["coefdenom"], x)
def rows(path):
    with open(path) as f:
        return list(csv.DictReader(l for l in f if not l.startswith("#")))
fits = {m: rows(f"{out}/{m}.csv") for m in ("paper", "tracked")}
reps = {m: {c["name"]: c for c in json.load(open(f"{out}/{m}.json"))["coils"]} for m in ("paper", "tracked")}
names = sorted(truth, key=lambda s: int(s[2:]))
lines = ["coil,r_mm,truth_shape"]
print("coil   paper: degrees rms(shape-truth)  tracked: degrees rms(shape-truth) peak_field_mT  (truth excitation 0.5 mT;"
      " TC6-TC14 on odd sectors: 0.25 mT as an all-sector coil)")
acc = {"paper": [], "tracked": []}
for n in names:
    cells = [f"{n:5s}"]
    for m in ("paper", "tracked"):
        rep = reps[m].get(n)
        if not rep or rep["status"] != "ok":
            cells.append(f"  {m}: refused ({rep['error'][:40] if rep else 'missing'}...)")
            continue
        pts = [(float(x["r_mm"]), float(x["b_shape"])) for x in fits[m] if x["coil"] == n]
        lo, hi = rep["window_mm"]
        grid = [lo + (hi - lo) * i / 400 for i in range(401)]
        tv = [tshape(truth[n], r) for r in grid]
        peak = max(tv, key=abs)
        def fitted(r):
            for (r0, s0), (r1, s1) in zip(pts, pts[1:]):
                if r0 <= r <= r1:
                    return s0 + (s1 - s0) * (r - r0) / (r1 - r0) if r1 > r0 else s0
            return pts[-1][1]
        e = math.sqrt(sum((fitted(r) - t / peak) ** 2 for r, t in zip(grid, tv)) / len(grid))
        acc[m].append(e)
        extra = f" {rep['peak_field_T'] * 1e3:6.3f}" if "peak_field_T" in rep else ""
        cells.append(f"  {m}: {rep['degrees'][0]}/{rep['degrees'][1]} {e:6.3f}{extra}")
        if m == "tracked":
            lines += [f"{n},{r:.3f},{t / peak:.6f}" for r, t in zip(grid, tv)]
    print("".join(cells))
for m in acc:
    v = sorted(acc[m])
    if v:
        print(f"{m}: {len(v)} coils, median rms {v[len(v) // 2]:.3f}, mean {sum(v) / len(v):.3f}")
open(f"{out}/truth.csv", "w").write("\n".join(lines) + "\n")
EOF

if command -v gnuplot > /dev/null 2>&1; then
  # Panels like the paper's Figs. 8-9: scans with their fits, and field shapes against the truth.
  for c in TC3 TC8 TC13 TC16; do
    grep -v '^#' "$SCANS/$c.csv" | tail -n +2 | tr ',' ' ' > "$OUT/scan-$c.dat"
    for m in paper tracked; do grep "^$c," "$OUT/$m.csv" | tr ',' ' ' > "$OUT/$m-$c.dat"; done
    grep "^$c," "$OUT/truth.csv" | tr ',' ' ' > "$OUT/truth-$c.dat"
  done
  gnuplot <<EOF
set terminal pngcairo size 1400,900 font ",10"
set output "$OUT/tcfit-loop.png"
set multiplot layout 2,4 title "ring8: trim coil phase scans (seed 88) fitted by turnfit-tc-fit, and the field shapes against the truth"
coils = "TC3 TC8 TC13 TC16"
do for [i = 1:4] {
  c = word(coils, i)
  set title sprintf("%s delta sin(phi)", c); set xlabel "r [mm]"; set key bottom left
  plot "$OUT/scan-".c.".dat" u 1:2 w p pt 7 ps 0.5 lc rgb "gray40" t "scan", \
       "$OUT/paper-".c.".dat" u 2:3 w l lw 2 lc rgb "dark-green" t "paper model fit", \
       "$OUT/tracked-".c.".dat" u 2:3 w l lw 2 lc rgb "blue" t "tracked model fit"
}
do for [i = 1:4] {
  c = word(coils, i)
  set title sprintf("%s field shape", c); set xlabel "r [mm]"; set key top right
  plot "$OUT/tracked-".c.".dat" u 2:(\$5-\$6):(\$5+\$6) w filledcurves fs transparent solid 0.25 lc rgb "blue" t "tracked 1 sigma", \
       "$OUT/truth-".c.".dat" u 2:3 w l lw 3 lc rgb "black" t "truth", \
       "$OUT/paper-".c.".dat" u 2:5 w l lw 2 lc rgb "dark-green" t "paper model", \
       "$OUT/tracked-".c.".dat" u 2:5 w l lw 2 lc rgb "blue" t "tracked model"
}
unset multiplot
EOF
  echo "figure: $OUT/tcfit-loop.png"
else
  echo "gnuplot not installed: no figure (apt-get install gnuplot-nox)"
fi
