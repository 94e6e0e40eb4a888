#!/usr/bin/env python3
"""Builds the default machine ring8 from field-design.json and params.json.

Run by `make -f Makefile.wrap ring8` (BIN = the folder with the built turnfit tools). Writes, next
to this script: field.json (the isochronized field spec), field.map (turnfit-fieldmap/1),
field-ring.dat (the same map in OPAL's RING format), main-cavity.dat and flattop-cavity.dat
(radial voltage profiles, OPAL rffield format), orbits.csv (the isochronism and tune table),
machine.json, and turns.csv (the nominal turn pattern). Every output is deterministic: running it
twice gives the same bytes.

The script only decides what params.json leaves open, each by a stated rule:
  * cavity gap lines: straight lines x sin A - y cos A = PDIS through the valley centre line of
    the spiral field at two radii (params cavity_fit_radii_mm);
  * cavity phases: the reference proton crosses every main gap on the crest and the flat-top
    on its decelerating crest (mean RF phase over all turns);
  * the common main voltage: the proton reaches the extraction energy after the given turns;
  * injection radius and radial momentum: no coherent betatron oscillation over the first
    centring_turns turns at the injection azimuth (paper Sec. II.C: r_n = r_0 + <dr/dn> n +
    A sin(2 pi nu_r n + phi), here with A = 0);
  * probe extents: each probe sees exactly its turn range, its ends half-way between turns.
"""
import argparse
import csv
import io
import json
import math
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))


def log(msg):
    print("make_ring8: " + msg, file=sys.stderr, flush=True)


def run(args, capture=True, cwd=None):
    r = subprocess.run(args, stdout=subprocess.PIPE if capture else None, stderr=subprocess.PIPE, text=True, cwd=cwd)
    if r.returncode != 0:
        sys.exit("make_ring8: %s failed (exit %d):\n%s" % (" ".join(args), r.returncode, r.stderr))
    return r.stdout


def write(path, text):
    """Atomic write: a failed run leaves the previous file in place."""
    tmp = path + ".tmp.%d" % os.getpid()
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def rows(text):
    return list(csv.DictReader(io.StringIO("".join(l for l in text.splitlines(True) if not l.startswith("#")))))


# ---- the spiral centre line (the same natural spline and integral as lib/turnfit/field/sector_field.cpp) ----

def natural_spline(xs, ys):
    n = len(xs)
    m = [0.0] * n
    if n >= 3:
        c, d = [0.0] * n, [0.0] * n
        for i in range(1, n - 1):
            h0, h1 = xs[i] - xs[i - 1], xs[i + 1] - xs[i]
            rhs = 6 * ((ys[i + 1] - ys[i]) / h1 - (ys[i] - ys[i - 1]) / h0)
            diag = 2 * (h0 + h1) - h0 * c[i - 1]
            c[i], d[i] = h1 / diag, (rhs - h0 * d[i - 1]) / diag
        for i in range(n - 2, 0, -1):
            m[i] = d[i] - c[i] * m[i + 1]

    def slope(i, r):
        h = xs[i + 1] - xs[i]
        a = (xs[i + 1] - r) / h
        b = 1 - a
        return (ys[i + 1] - ys[i]) / h + ((1 - 3 * a * a) * m[i] + (3 * b * b - 1) * m[i + 1]) * h / 6

    def f(r):
        if n == 1:
            return ys[0]
        if r <= xs[0]:
            return ys[0] + slope(0, xs[0]) * (r - xs[0])
        if r >= xs[-1]:
            return ys[-1] + slope(n - 2, xs[-1]) * (r - xs[-1])
        i = max(k for k in range(n - 1) if xs[k] <= r)
        h = xs[i + 1] - xs[i]
        a = (xs[i + 1] - r) / h
        b = 1 - a
        return a * ys[i] + b * ys[i + 1] + ((a ** 3 - a) * m[i] + (b ** 3 - b) * m[i + 1]) * h * h / 6
    return f


def centre_line_deg(spec):
    """theta_c(r) of magnet 1 [deg]: the integral of tan(xi(r')) / r' from r0."""
    sp = spec.get("spiral")
    if not sp:
        return lambda r: 0.0
    xi = natural_spline(sp["r_mm"], sp["angle_deg"])
    r0 = sp["r0_mm"]

    def theta(r):
        n = 4000
        h = (r - r0) / n
        return math.degrees(sum(math.tan(math.radians(xi(r0 + (k + 0.5) * h))) / (r0 + (k + 0.5) * h) for k in range(n)) * h)
    return theta


def gap_line(theta_v, r1, r2):
    """(A [deg], PDIS [mm]) of the straight line x sin A - y cos A = PDIS that crosses radius r at
    azimuth theta_v(r) for r = r1 and r2 (turnfit's gap: theta = A - asin(PDIS / r))."""
    want = math.radians(theta_v(r2) - theta_v(r1))
    lo, hi = -0.99 * r1, 0.99 * r1
    g = lambda p: math.asin(p / r1) - math.asin(p / r2) - want
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if (g(lo) < 0) == (g(mid) < 0):
            lo = mid
        else:
            hi = mid
    p = 0.5 * (lo + hi)
    return theta_v(r1) + math.degrees(math.asin(p / r1)), p


# ---- voltage profiles (OPAL rffield format: a row count, then rho_n, V, dV/drho_n) ----

def profile_text(v, dv, n=41):
    out = ["%d" % n]
    for k in range(n):
        x = k / (n - 1)
        out.append("%.6f %.12f %.12f" % (x, v(x), dv(x)))
    return "\n".join(out) + "\n"


# ---- trim coil shapes: rational functions of r [m], peak normalized to 1 (paper Sec. II.C) ----

def poly_in_r(cu, rc, w):
    """Coefficients in r of sum_k cu[k] u^k with u = (r - rc) / w."""
    out = [0.0] * len(cu)
    a, b = 1.0 / w, -rc / w
    for k, c in enumerate(cu):
        for j in range(k + 1):
            out[j] += c * math.comb(k, j) * a ** j * b ** (k - j)
    return out


def polyval(c, x):
    s = 0.0
    for v in reversed(c):
        s = s * x + v
    return s


def polymul(p, q):
    out = [0.0] * (len(p) + len(q) - 1)
    for i, a in enumerate(p):
        for j, b in enumerate(q):
            out[i + j] += a * b
    return out


def trim_coil(name, k, rc_mm, w_mm, asym, tail, halfwidths, grid_lo_mm):
    """A bump with a slight asymmetry and small negative tails (the flux a pole-face coil
    returns): f/g = (1 + a u - t u^2) / (1 + u^2/2 + u^4), degrees 2/4 as the paper's TC2-TC15;
    TC1 and TC16-TC18 get the paper's degrees 4/5 through a second factor of f and g."""
    f = [1.0, asym, -tail]
    g = [1.0, 0.0, 0.5, 0.0, 1.0]
    if k == 1 or k >= 16:
        f = polymul(f, [1.0, 0.0, 0.3])
        g = polymul(g, [1.0, 0.12 * asym])  # root at u = -1 / (0.12 a): far outside the support
    rc, w = rc_mm * 1e-3, w_mm * 1e-3
    rmin = max(grid_lo_mm, rc_mm - halfwidths * w_mm) if k > 1 else grid_lo_mm  # TC1: the whole lower half
    rmax = rc_mm + halfwidths * w_mm
    fu = lambda r: polyval(f, (r - rc) / w) / polyval(g, (r - rc) / w)
    peak = max(abs(fu((rmin + (rmax - rmin) * i / 4000) * 1e-3)) for i in range(4001))
    num = [c / peak for c in poly_in_r(f, rc, w)]
    den = poly_in_r(g, rc, w)
    # The expanded coefficients cancel heavily at r ~ 4 m (terms up to (r/w)^5 ~ 1e9 for a value
    # of 1): check they still give the shape to 1e-6 of the peak, i.e. 1e-9 T for a 1 mT coil.
    worst = max(abs(polyval(num, r) / polyval(den, r) - fu(r) / peak)
                for r in ((rmin + (rmax - rmin) * i / 400) * 1e-3 for i in range(401)))
    if worst > 1e-6:
        sys.exit("make_ring8: %s: polynomial coefficients lose the shape (%.1e of the peak)" % (name, worst))
    return {"name": name, "type": "psi-bfield", "rmin_mm": round(rmin, 6), "rmax_mm": round(rmax, 6),
            "bmax_T": 0.0, "coefnum": num, "coefdenom": den}


# ---- tracking helpers ----

class Tracker:
    """Runs turnfit-track on machine documents written to a scratch folder; the documents' relative
    paths (map, profiles) are made absolute against the output folder first."""
    def __init__(self, bin_dir, workdir, base):
        self.bin = os.path.join(bin_dir, "turnfit-track")
        self.work = workdir
        self.base = base

    def track(self, machine, extra=()):
        m = json.loads(json.dumps(machine))
        m["field"]["map"] = os.path.join(self.base, m["field"]["map"])
        for c in m["cavities"]:
            c["profile"] = os.path.join(self.base, c["profile"])
        path = os.path.join(self.work, "m.json")
        self.calls = getattr(self, "calls", 0) + 1
        with open(path, "w") as f:
            json.dump(m, f)
        import time; t0 = time.time()
        o = run([self.bin, path, "-q", "--no-provenance"] + list(extra))
        if os.environ.get("RING8_DEBUG"): log("track %.3f s %s" % (time.time() - t0, " ".join(extra)))
        return o

    def kicks(self, machine):
        kpath = os.path.join(self.work, "kicks.csv")
        self.track(machine, ["--kicks", kpath, "-o", os.path.join(self.work, "t.csv")])
        with open(kpath) as f:
            return rows(f.read())


def end_energy(turns_text):
    for line in turns_text.splitlines():
        if line.startswith("# end"):
            return float(line.split("energy_MeV=")[1].split()[0])
    sys.exit("make_ring8: no '# end' line in the track output")


def solve(a, b):
    """Gaussian elimination with partial pivoting (small dense systems)."""
    n = len(b)
    m = [row[:] + [b[i]] for i, row in enumerate(a)]
    for c in range(n):
        p = max(range(c, n), key=lambda i: abs(m[i][c]))
        m[c], m[p] = m[p], m[c]
        for i in range(c + 1, n):
            f = m[i][c] / m[c][c]
            for j in range(c, n + 1):
                m[i][j] -= f * m[c][j]
    x = [0.0] * n
    for i in reversed(range(n)):
        x[i] = (m[i][n] - sum(m[i][j] * x[j] for j in range(i + 1, n))) / m[i][i]
    return x


def coherent(radii, nu_r_of_turn):
    """(A cos, A sin) of the betatron oscillation in turn radii at one azimuth, after a cubic trend:
    least squares of r_n = c0 + c1 n + c2 n^2 + c3 n^3 + A cos(psi_n) + B sin(psi_n), psi_n the
    accumulated fractional tune."""
    psi, acc = [], 0.0
    for n in range(len(radii)):
        psi.append(acc)
        acc += 2 * math.pi * (nu_r_of_turn(n) % 1.0)
    cols = lambda n: [1.0, n / 10, (n / 10) ** 2, (n / 10) ** 3, math.cos(psi[n]), math.sin(psi[n])]
    ata = [[0.0] * 6 for _ in range(6)]
    atb = [0.0] * 6
    for n, r in enumerate(radii):
        c = cols(n)
        for i in range(6):
            atb[i] += c[i] * r
            for j in range(6):
                ata[i][j] += c[i] * c[j]
    x = solve(ata, atb)
    return x[4], x[5]


def measure(bin_dir, truth_dir, dest, T):
    """turnfit-synth on the truth in truth_dir, into dest (relative to truth_dir, or absolute).
    Relative machine names, run in truth_dir: truth.json records the machine's path as given."""
    log("measuring the truth (turnfit-synth, %d particles)" % T["particles"])
    run([os.path.abspath(os.path.join(bin_dir, "turnfit-synth")), "truth-machine.json", "--dvars", "truth-dvars.json",
         "--seed", str(T["seed"]), "--current-uA", str(T["current_uA"]), "--particles", str(T["particles"]),
         "--no-provenance", "-q", "-o", dest], cwd=truth_dir)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", required=True, help="folder with the built turnfit tools")
    ap.add_argument("--out", default=HERE, help="where to write (default: next to this script)")
    ap.add_argument("--no-measured", action="store_true", help="skip the synthetic measurements (measured/)")
    ap.add_argument("--measure-into", metavar="DIR",
                    help="only measure the committed truth (truth-machine.json, truth-dvars.json) into DIR")
    args = ap.parse_args()
    if args.measure_into:
        with open(os.path.join(HERE, "params.json")) as f:
            measure(args.bin, HERE, os.path.abspath(args.measure_into), json.load(f)["truth"])
        return
    orbit = os.path.join(args.bin, "turnfit-orbit")
    out = lambda name: os.path.join(args.out, name)
    with open(os.path.join(HERE, "params.json")) as f:
        P = json.load(f)
    design = os.path.join(HERE, "field-design.json")

    # 1. The isochronized field, its maps and its orbit table.
    log("isochronizing the hill field")
    with tempfile.TemporaryDirectory() as tmp:
        run([orbit, "--sector-field", design, "--isochronize", "-q", "--no-provenance",
             "--write-spec", os.path.join(tmp, "field.json"), "-o", os.path.join(tmp, "iso.csv")])
        os.replace(os.path.join(tmp, "field.json"), out("field.json"))
    log("writing the maps and the orbit table")
    run([orbit, "--sector-field", out("field.json"), "--no-provenance", "--write-map", out("field.map"),
         "--energies", "72:590:2", "-o", out("orbits.csv")])
    run([orbit, "--sector-field", out("field.json"), "--no-provenance", "--write-map", out("field-ring.dat"),
         "--write-map-format", "psi-ring"])
    with open(out("field.json")) as f:
        spec = json.load(f)
    with open(out("orbits.csv")) as f:
        table = rows(f.read())
    E_tab = [float(r["energy_MeV"]) for r in table]
    nu_tab = [float(r["nu_r"]) for r in table]
    nu_r_at = lambda e: nu_tab[min(range(len(E_tab)), key=lambda i: abs(E_tab[i] - e))]

    # 2. Voltage profiles.
    write(out("main-cavity.dat"), profile_text(lambda x: math.sin(math.pi * x), lambda x: math.pi * math.cos(math.pi * x)))
    ft = P["flattop"]
    e = math.asin(ft["profile_edge"]) / math.pi
    write(out("flattop-cavity.dat"), profile_text(lambda x: math.sin(math.pi * (e + (1 - 2 * e) * x)),
                                                  lambda x: math.pi * (1 - 2 * e) * math.cos(math.pi * (e + (1 - 2 * e) * x))))

    # 3. Cavities on the valley centre lines.
    theta_c = centre_line_deg(spec)
    period = 360.0 / spec["sectors"]
    r1, r2 = P["cavity_fit_radii_mm"]
    mc = P["main_cavities"]
    cavities = []
    for i, valley in enumerate(mc["valleys"]):
        a, p = gap_line(lambda r: theta_c(r) + period * (valley + 0.5), r1, r2)
        cavities.append({"name": "main%d" % (i + 1), "voltage_MV": mc["voltage_MV"] + mc["voltage_spread_MV"][i],
                         "profile": "main-cavity.dat", "phase_deg": 0.0, "angle_deg": round(a % 360, 6),
                         "pdis_mm": round(p, 6), "rmin_mm": mc["rmin_mm"], "rmax_mm": mc["rmax_mm"],
                         "gap_width_mm": mc["gap_width_mm"]})
    a, p = gap_line(lambda r: theta_c(r) + period * (ft["valley"] + 0.5), r1, r2)
    v_main_sum = sum(c["voltage_MV"] for c in cavities)
    cavities.append({"name": "ft", "voltage_MV": ft["voltage_fraction"] * v_main_sum, "harmonic_factor": ft["harmonic_factor"],
                     "profile": "flattop-cavity.dat", "phase_deg": 0.0, "angle_deg": round(a % 360, 6),
                     "pdis_mm": round(p, 6), "rmin_mm": ft["rmin_mm"], "rmax_mm": ft["rmax_mm"],
                     "gap_width_mm": ft["gap_width_mm"]})

    # 4. Trim coils TC1-TC18.
    tc = P["trimcoils"]
    coils = [trim_coil("TC%d" % k, k, tc["first_centre_mm"] + (k - 1) * tc["spacing_mm"], tc["width_mm"][k - 1],
                       tc["asymmetry"][k - 1], tc["tail"][k - 1], tc["support_halfwidths"], spec["grid"]["r_min_mm"])
             for k in range(1, 19)]

    # 5. The machine, first with a guess of the injection and a probe along the injection azimuth.
    inj = P["injection"]
    first = next(r for r in table if abs(float(r["energy_MeV"]) - inj["energy_MeV"]) < 1e-9) if any(
        abs(float(r["energy_MeV"]) - inj["energy_MeV"]) < 1e-9 for r in table) else table[0]
    turns = P["extraction"]["turns"]
    machine = {
        "format": "turnfit-machine/1",
        "name": "ring8",
        "description": "",
        "particle": {"species": P["particle"]},
        "field": {"map": "field.map", "format": "turnfit", "symmetry": spec["sectors"],
                  "trimcoil_threshold_T": tc["threshold_T"]},
        "rf": P["rf"],
        "cavities": cavities,
        "trimcoils": coils,
        "probes": [{"name": "C0", "phi_deg": inj["phi_deg"], "a_mm": 0.0, "s_min_mm": 1850.0, "s_max_mm": 4850.0,
                    "step_mm": 0.5}],
        "injection": {"energy_MeV": inj["energy_MeV"], "r_mm": float(first["r_avg_mm"]), "pr_betagamma": 0.0,
                      "phi_deg": inj["phi_deg"]},
        "tracking": {"turns": turns},
    }
    scratch = tempfile.TemporaryDirectory(prefix="ring8-")
    tr = Tracker(args.bin, scratch.name, args.out)
    mass = 938.27208816
    e_inj = inj["energy_MeV"]
    bg = math.sqrt((1 + e_inj / mass) ** 2 - 1)

    def c0_radii(m, n):
        rs = [r for r in rows(tr.track(m, ["--turns", "%g" % (n + 0.5)])) if r["probe"] == "C0"]
        return [float(r["r_mm"]) for r in rs], [float(r["energy_MeV"]) for r in rs]

    def amplitude(m):
        rs, es = c0_radii(m, P["centring_turns"])
        return coherent(rs, lambda n: nu_r_at(es[min(n, len(es) - 1)]))

    for sweep in range(4):
        # Phases on the crest (flat-top on its decelerating crest).
        for _ in range(3):
            ks = tr.kicks(machine)
            for c in machine["cavities"]:
                ph = [float(k["phase_deg"]) for k in ks if k["gap"] == c["name"]]
                target = 180.0 if c["name"] == "ft" else 0.0
                # Mean of the wrapped offset from the target, as a unit-vector average.
                sx = sum(math.cos(math.radians(x - target)) for x in ph)
                sy = sum(math.sin(math.radians(x - target)) for x in ph)
                c["phase_deg"] = round((c["phase_deg"] + math.degrees(math.atan2(sy, sx))) % 360, 6)
        # Common main voltage for the extraction energy (secant on a scale factor).
        def energy(scale):
            mm = json.loads(json.dumps(machine))
            for c in mm["cavities"]:
                c["voltage_MV"] *= scale
            return end_energy(tr.track(mm))
        s0, s1 = 1.0, 1.01
        f0, f1 = energy(s0) - P["extraction"]["energy_MeV"], energy(s1) - P["extraction"]["energy_MeV"]
        for _ in range(20):
            if abs(f1) < 1e-4 or f1 == f0:
                break
            s0, s1, f0 = s1, s1 - f1 * (s1 - s0) / (f1 - f0), f1
            f1 = energy(s1) - P["extraction"]["energy_MeV"]
        for c in machine["cavities"]:
            c["voltage_MV"] = round(c["voltage_MV"] * s1, 9)
        # Centring: Newton on (r, p_r) to remove the coherent oscillation.
        for _ in range(4):
            a0 = amplitude(machine)
            jac = []
            for key, h in (("r_mm", 0.05), ("pr_betagamma", 2e-5)):
                mm = json.loads(json.dumps(machine))
                mm["injection"][key] += h
                a1 = amplitude(mm)
                jac.append([(a1[0] - a0[0]) / h, (a1[1] - a0[1]) / h])
            d = solve([[jac[0][0], jac[1][0]], [jac[0][1], jac[1][1]]], [-a0[0], -a0[1]])
            machine["injection"]["r_mm"] = round(machine["injection"]["r_mm"] + d[0], 6)
            machine["injection"]["pr_betagamma"] = round(machine["injection"]["pr_betagamma"] + d[1], 9)
        amp = math.hypot(*amplitude(machine))
        log("sweep %d: main voltage x%.6f, injection r %.3f mm, pr %.6f, coherent amplitude %.4f mm"
            % (sweep + 1, s1, machine["injection"]["r_mm"], machine["injection"]["pr_betagamma"], amp))

    # 6. Probes from the nominal turn pattern: a probe line at each paper probe, whole range first.
    probes = []
    for name, pp in P["probes"].items():
        probes.append({"name": name, "phi_deg": pp["phi_deg"], "a_mm": pp["a_mm"], "s_min_mm": 1850.0,
                       "s_max_mm": 4850.0, "step_mm": pp["step_mm"]})
    machine["probes"] = probes
    pattern = rows(tr.track(machine))
    for pr, (name, pp) in zip(machine["probes"], P["probes"].items()):
        s = [float(r["s_mm"]) for r in pattern if r["probe"] == name]
        lo, hi = pp["turns"]
        pr["s_min_mm"] = round(s[lo - 1] - 0.5 * (s[lo - 1] - s[lo - 2]) if lo > 1 else s[0] - 10.0, 3)
        pr["s_max_mm"] = round(0.5 * (s[hi - 1] + s[hi]) if hi < len(s) else s[hi - 1] + 0.5 * (s[hi - 1] - s[hi - 2]), 3)
    b = dict(P["bunch"])
    b["particles"] = 0  # single-particle tracks by default; synth and --particles ask for bunches
    machine["bunch"] = b
    machine["description"] = (
        "ring8: turnfit's PSI-Ring-like default machine, generated by make_ring8.py from field-design.json and "
        "params.json (do not edit; run make -f Makefile.wrap ring8). 8 spiral sector magnets isochronized for "
        "protons at h = 6, 50.65 MHz; 4 main cavities and a third-harmonic flat-top on the valley centre lines; "
        "18 trim coils TC1-TC18 (rational field shapes, degrees 2/4 and 4/5 as the paper's fits; nominal bmax 0: the "
        "field is isochronous without them; spread over all sectors above the threshold, the paper's model); "
        "probes RRI2 (turns 1-16, 0.05 mm steps) and RRL (turns 9-182, 0.5 mm) at azimuth 170 deg as in the "
        "paper's drawing; a centred beam injected at 72 MeV, 110 deg; 590 MeV after 182 turns.")
    text = json.dumps(machine, indent=1) + "\n"
    write(out("machine.json"), text)
    write(out("turns.csv"), tr.track(machine))
    log("wrote machine.json and turns.csv")

    # 7. The truth: ring8 as it really runs (design-variable values the fit may recover) plus
    # concealed effects; then its synthetic measurements.
    T = P["truth"]
    truth = json.loads(json.dumps(machine))
    truth["name"] = "ring8-truth"
    truth["description"] = ("The hidden truth behind ring8's synthetic measurements (measured/): ring8 plus concealed "
                            "effects, run with the design-variable values of truth-dvars.json. Generated by make_ring8.py "
                            "from params.json. A fit must never read this file.")
    truth["effects"] = T["effects"]
    write(out("truth-machine.json"), json.dumps(truth, indent=1) + "\n")
    write(out("truth-dvars.json"), json.dumps(T["dvars"], indent=1) + "\n")
    if args.no_measured:
        return
    measure(args.bin, args.out, "measured", T)
    log("wrote measured/")


if __name__ == "__main__":
    main()
