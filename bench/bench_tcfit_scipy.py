#!/usr/bin/python3
"""turnfit's rational fits of the trim coil phase scans against SciPy's least_squares.

Runs bench_tcfit (turnfit's fit_rational at the paper's degrees: 2/4 for TC2-TC15, 4/5 for TC1
and TC16-TC18, windows = the machine coils' [rmin_mm, rmax_mm] clipped to the data), then fits
the same points with scipy.optimize.least_squares on the same model y ~ f(x)/g(x), in the same
scaled variable x = (r - centre)/half_width, g = 1 + b_1 x + ... (b_0 = 1), two ways:

  (a) paper-style script: method='lm' (MINPACK) with SciPy's defaults (finite-difference
      Jacobian, ftol = xtol = gtol = 1e-8) on the raw values, started from a = the degree-n
      polynomial least-squares fit, b = 0;
  (b) the best we make SciPy do: values scaled to max |y| = 1 (as turnfit does), the analytic
      Jacobian, tolerances 1e-15, max_nfev 4000, methods 'lm' and 'trf' each from two starts:
      the polynomial one of (a) and the linearized (Levy) fit reweighted by 1/g
      (Sanathanan-Koerner) as turnfit computes it ("lin": the best of 8 passes, stopping at the
      first g turnfit would not accept: g <= 1e-9 on [-1, 1] or a root within one data
      spacing of it, see below); where that stops at the first pass (turnfit then has no
      linearized start) the best of 8 unconstrained passes ("lin*": scipy does not mind a pole
      in its start). The lowest rss of the 4 runs is kept (column "(b) run"), the time is that
      of all 4.

Each fit (start included) is repeated until --min-time seconds have passed; the median per fit is
reported (for a coil turnfit refuses, the time to the refusal). Every denominator g is judged
the way turnfit's fit_rational judges its own since the commit "rational fit: poles kept one
data spacing from the window": the distance, in the complex plane and in x, from g's nearest
root (complex roots too) to [-1, 1], against the median spacing of the window's samples (in x;
25 mm for ring8's steps). Nearer, f/g has a feature the samples cannot resolve (a spike in the
fitted curve and far more in its slope, the field); fit_rational keeps its trial steps out of
that zone and does not return a fit held at its boundary (distance < 1.02 spacings, 25.5 mm):
that is the bound used here. Columns "pole mm": ROOT, a real root of g on [-1, 1] (the plain
check: f/g infinite between two samples, which least_squares has no way to forbid); "near D",
no real root on the window but a root D mm from it, inside the bound; a number, the nearest
root's distance in mm, pole-free by that measure. Column "tf held rss": fit_rational's
rss_at_pole_bound, the lower rss a fit held at the bound reached where the fit returned is a
resolvable optimum above it. turnfit is also run with --extra-starts 0 (without the placed-root
starts fit_rational adds when every other start ends at the bound): the coils whose answer
those starts change are listed.

--multistart K adds, per coil, the best scipy optimum over K seeded random starts ('lm',
analytic Jacobian) whose g is pole-free by the same bound: a search for a resolvable optimum
below turnfit's (or one on a coil turnfit refuses). SciPy's pole-free result for a coil is the
lowest rss of (a), (b) and that search among those that are pole-free; the summary counts the
coils where turnfit's result (pole-free by construction) is <= it. Where the search finds a
pole-free optimum on a coil turnfit refuses, or below turnfit's, bench_tcfit is run again with
it as an extra start (--seed): does turnfit keep it, or still refuse?

A coil with fewer points than parameters (TC18 at 4/5) is refused by both tools and compared at
2/4 instead (marked *).

Usage: bench/bench_tcfit_scipy.py [--bin build/bench/bench_tcfit] [--machine machine.json]
       [--phase DIR] [--min-time 0.2] [--multistart K] [--markdown]
Needs /usr/bin/python3 with numpy and scipy (Debian: apt-get install python3-scipy).
"""
import argparse
import csv
import io
import os
import subprocess
import sys
import time
import warnings

try:
    import numpy as np
    from scipy.optimize import least_squares
    import scipy
except ImportError as e:  # pragma: no cover
    sys.exit("bench_tcfit_scipy.py: %s: this benchmark needs numpy and scipy; run it with "
             "/usr/bin/python3 after 'apt-get install python3-scipy' (a pyenv or venv python "
             "without scipy will not do)" % e)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARE = os.path.join(REPO, "share", "turnfit", "ring8")
REL_TIE = 1e-9
GUARD = np.linspace(-1.0, 1.0, 2001)
SOURCE = {"a": "(a)", "b": "(b)", "ms": "multistart"}


def read_scan(path):
    r, y = [], []
    with open(path) as f:
        rows = [ln for ln in f if ln.strip() and not ln.lstrip().startswith("#")]
    rd = csv.DictReader(rows)
    for row in rd:
        r.append(float(row["r_mm"]))
        y.append(float(row["dsinphi"]))
    return np.array(r), np.array(y)


def run_bench(binary, machine, phase, min_time, seeds=(), extra=None):
    cmd = [binary, "--detail", "--min-time", str(min_time)]
    if extra is not None:
        cmd += ["--extra-starts", str(extra)]
    for sd in seeds:
        cmd += ["--seed", sd]
    if machine:
        cmd += ["--machine", machine]
    if phase:
        cmd += ["--phase", phase]
    out = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, universal_newlines=True).stdout
    lines = [ln for ln in out.splitlines() if not ln.startswith("#")]
    rows = list(csv.DictReader(io.StringIO("\n".join(lines))))
    return cmd, rows


# ---- the model in x: theta = (a_0..a_n, b_1..b_m) ----------------------------------------------

def vander(x, k):
    return np.vander(x, k + 1, increasing=True)


def model_parts(theta, X, n, m):
    a = theta[: n + 1]
    b = np.concatenate(([1.0], theta[n + 1:]))
    f = X[:, : n + 1] @ a
    g = X[:, : m + 1] @ b
    return f, g


def make_problem(x, y, n, m):
    X = vander(x, max(n, m))

    def fun(theta):
        f, g = model_parts(theta, X, n, m)
        return f / g - y

    def jac(theta):
        f, g = model_parts(theta, X, n, m)
        q = f / g
        J = np.empty((len(x), n + 1 + m))
        J[:, : n + 1] = X[:, : n + 1] / g[:, None]
        J[:, n + 1:] = -(q / g)[:, None] * X[:, 1: m + 1]
        return J

    return fun, jac


def den_min(b):
    return np.polyval(np.asarray(b)[::-1], GUARD).min()


def has_pole(b):
    """A real root of g = b_0 + b_1 x + ... on [-1, 1] (companion roots, and g <= 0 on a grid)."""
    b = np.asarray(b, dtype=float)
    while len(b) > 1 and b[-1] == 0:
        b = b[:-1]
    if len(b) <= 1:
        return False
    roots = np.roots(b[::-1])
    real = roots[np.abs(roots.imag) <= 1e-7 * np.maximum(1.0, np.abs(roots))].real
    return bool(np.any((real >= -1) & (real <= 1))) or den_min(b) <= 0


def polynomial_start(x, y, n, m):
    a = np.linalg.lstsq(vander(x, n), y, rcond=None)[0]
    return np.concatenate((a, np.zeros(m)))


def linearized_start(x, y, n, m, feasible_only=True, bound=0.0):
    """Levy's linearized fit f - y g = 0, reweighted by 1/g (Sanathanan-Koerner), 8 passes: the
    pass with the least true rss. With feasible_only (turnfit's start) the passes stop at the
    first g that turnfit would not accept (g <= 1e-9 somewhere on [-1, 1], or a root within the
    bound of it; None if the first pass has one); without, any finite pass counts."""
    A = np.hstack((vander(x, n), -y[:, None] * vander(x, m)[:, 1:]))
    w = np.ones(len(x))
    best, best_cost = None, np.inf
    for _ in range(8):
        t = np.linalg.lstsq(w[:, None] * A, w * y, rcond=None)[0]
        if not np.all(np.isfinite(t)):
            break
        b = np.concatenate(([1.0], t[n + 1:]))
        if feasible_only and m > 0 and (den_min(b) <= 1e-9 or not nearest_root(b)[0] > bound):
            break
        g = vander(x, m) @ b
        cost = np.sum((vander(x, n) @ t[: n + 1] / g - y) ** 2)
        if not np.isfinite(cost) or np.any(g == 0):
            break
        w = 1 / np.abs(g)
        if cost < best_cost:
            best, best_cost = t, cost
    return best


def fit_paper(x, y, n, m):
    fun, _ = make_problem(x, y, n, m)
    s = least_squares(fun, polynomial_start(x, y, n, m), method="lm")
    return s.x, s.nfev, s.status, "lm"


def fit_best(x, y, n, m, spacing):
    scale = np.max(np.abs(y)) or 1.0
    ys = y / scale
    fun, jac = make_problem(x, ys, n, m)
    starts = []
    lin = linearized_start(x, ys, n, m, bound=spacing)  # fit_rational's feasibility: > 1 spacing
    if lin is not None:
        starts.append(("lin", lin))
    else:  # turnfit has no linearized start here; scipy does not mind a pole in its start
        lin = linearized_start(x, ys, n, m, feasible_only=False)
        if lin is not None:
            starts.append(("lin*", lin))
    starts.append(("poly", polynomial_start(x, ys, n, m)))
    best, nfev = None, 0
    for name, t0 in starts:
        for method in ("lm", "trf"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                s = least_squares(fun, t0, jac=jac, method=method, ftol=1e-15, xtol=1e-15, gtol=1e-15,
                                  max_nfev=4000)
            nfev += s.nfev
            if best is None or s.cost < best[0].cost:
                best = (s, method + " " + name)
    s, how = best
    th = s.x.copy()
    th[: n + 1] *= scale
    return th, nfev, s.status, how


def rss_of(theta, x, y, n, m):
    fun, _ = make_problem(x, y, n, m)
    return float(np.sum(fun(theta) ** 2))


def timed(fn, min_time):
    ts = []
    t_start = time.perf_counter()
    while len(ts) < 3 or time.perf_counter() - t_start < min_time:
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return out, 1e3 * float(np.median(ts))


def multistart(x, y, n, m, k, bound, seed=1):
    """Best (rss in data units, theta) over k random starts of 'lm' (analytic Jacobian) whose
    optimum's g is pole-free by root_class (no root within bound of [-1, 1]), and how many such
    optima there were."""
    scale = np.max(np.abs(y)) or 1.0
    fun, jac = make_problem(x, y / scale, n, m)
    rng = np.random.default_rng(seed)
    best, best_theta, count = None, None, 0
    for _ in range(k):
        t0 = np.concatenate((rng.normal(0, 1, n + 1), rng.normal(0, 1, m) * rng.choice([0.1, 0.5, 1, 2])))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                s = least_squares(fun, t0, jac=jac, method="lm", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=2000)
            except Exception:
                continue
        if not np.isfinite(s.cost) or root_class(np.concatenate(([1.0], s.x[n + 1:])), bound)[0] != "-":
            continue
        count += 1
        rss = 2 * s.cost * scale * scale
        if best is None or rss < best:
            th = s.x.copy()
            th[: n + 1] *= scale
            best, best_theta = rss, th
    return best, best_theta, count


def nearest_root(b):
    """Distance (in x, complex plane) from the nearest root of g = b_0 + b_1 x + ... to [-1, 1],
    as fit_rational's pole_distance; the nearest root itself (None if g is constant)."""
    b = np.asarray(b, dtype=float)
    while len(b) > 1 and b[-1] == 0:
        b = b[:-1]
    if len(b) <= 1:
        return np.inf, None
    roots = np.roots(b[::-1])
    d = np.hypot(np.maximum(np.abs(roots.real) - 1, 0), np.abs(roots.imag))
    k = int(np.argmin(d))
    return float(d[k]), roots[k]


def root_class(b, bound):
    """'ROOT': g has a real root on [-1, 1]; 'near': none, but a root (complex ones too) lies
    within bound (in x) of the window; '-' otherwise. Also the distance (0 for ROOT)."""
    if has_pole(b):
        return "ROOT", 0.0
    dist, _ = nearest_root(b)
    return ("near" if dist < bound else "-"), dist


def edge_values(a, b):
    """Largest |f/g| and |d(f/g)/dx| on [-1, 1] (fine grid), and the largest |d(f/g)/dx| on
    [-0.9, 0.9]."""
    X = np.linspace(-1, 1, 400001)
    q = np.polyval(np.asarray(a)[::-1], X) / np.polyval(np.asarray(b)[::-1], X)
    dq = np.gradient(q, X)
    return np.max(np.abs(q)), np.max(np.abs(dq)), np.max(np.abs(dq[np.abs(X) <= 0.9]))


def short_refusal(msg):
    if "wants a pole" in msg:
        return "refused: pole"
    if "points in the window for" in msg:
        return "refused: points"
    return "refused"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default="build/bench/bench_tcfit", help="bench_tcfit binary")
    ap.add_argument("--machine", default=os.path.join(SHARE, "machine.json"))
    ap.add_argument("--phase", default=os.path.join(SHARE, "measured", "phase"))
    ap.add_argument("--min-time", type=float, default=0.2, help="seconds of repeats per coil and tool")
    ap.add_argument("--multistart", type=int, default=0, metavar="K",
                    help="also search K random starts per coil for a pole-free optimum (below turnfit's)")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    o = ap.parse_args()
    binary = o.bin
    if not os.path.exists(binary) and os.path.exists(os.path.join(REPO, binary)):
        binary = os.path.join(REPO, binary)
    if not os.path.exists(binary):
        sys.exit("bench_tcfit_scipy.py: %s: no such binary (build it: cmake --build BUILD --target bench_tcfit)" % o.bin)
    cmd, rows = run_bench(binary, o.machine, o.phase, o.min_time)
    _, rows0 = run_bench(binary, o.machine, o.phase, o.min_time, extra=0)
    print("# turnfit: %s" % " ".join(cmd))
    print("# scipy %s, numpy %s, python %s; scipy (a) and (b) as in this script's docstring" % (
        scipy.__version__, np.__version__, sys.version.split()[0]))

    coils = {}
    for row in rows:
        if row["coil"] != "total":
            coils.setdefault(row["coil"], []).append(row)
    table, notes, seeds = [], [], []
    for coil, crows in coils.items():
        first, row = crows[0], crows[-1]
        n, m = int(row["n"]), int(row["m"])
        label = coil
        r, y = read_scan(os.path.join(o.phase, coil + ".csv"))
        lo, hi = float(row["r_lo"]), float(row["r_hi"])
        sel = (r >= lo) & (r <= hi)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        x, yw = (r[sel] - centre) / half, y[sel]
        sp = float(np.median(np.diff(x))) if len(x) > 1 else 0.0  # fit_rational's min_pole
        hs = 1.02 * sp  # the bound: fit_rational returns no fit with a root nearer than this
        if len(x) != int(row["points"]):
            sys.exit("%s: %d points in the window here, %s in bench_tcfit" % (coil, len(x), row["points"]))
        if len(crows) > 1:  # refused at the paper's degrees for too few points, fitted at 2/4
            fn_, fm_ = int(first["n"]), int(first["m"])
            try:
                fun, _ = make_problem(x, yw, fn_, fm_)
                least_squares(fun, polynomial_start(x, yw, fn_, fm_), method="lm")
                smsg = "scipy's lm fitted it"
            except Exception as e:  # MINPACK needs at least as many residuals as parameters
                smsg = "scipy's lm refused it too (%s)" % str(e).rstrip(".")
            notes.append("%s at %d/%d: %d points for %d parameters; turnfit %s; %s. Compared at %d/%d (marked *)."
                         % (coil, fn_, fm_, len(x), fn_ + 1 + fm_, first["start"], smsg, n, m))
            label = coil + "*"
        res = {"coil": label, "n": n, "m": m, "points": len(x), "half": half, "hs_mm": hs * half, "tf_rss": None,
               "tf_ms": float(row["time_ms"]), "tf_state": "fitted", "tf_dist": None, "tf_held": None,
               "tf_start": row["start"]}
        held = float(row["rss_at_pole_bound"])
        if np.isfinite(held):
            res["tf_held"] = held
        if not row["start"].startswith("refused"):
            tf_theta = np.array([float(v) for v in row["a"].split()] + [float(v) for v in row["b"].split()[1:]])
            tf_b = np.concatenate(([1.0], tf_theta[n + 1:]))
            res["tf_rss"] = float(row["rss"])
            cls, dist = root_class(tf_b, hs)
            res["tf_dist"] = dist
            here = rss_of(tf_theta, x, yw, n, m)
            if abs(here - res["tf_rss"]) > 1e-6 * res["tf_rss"]:
                notes.append("%s: turnfit's coefficients give rss %.6e here, it reported %.6e" % (coil, here, res["tf_rss"]))
            if cls != "-":
                notes.append("%s turnfit: its g has a root %.3g mm from the window (bound %.3g mm): the library "
                             "should have refused this fit" % (label, dist * half, hs * half))
            if res["tf_held"] is not None:
                notes.append("%s turnfit: fitted (start %s, rss %.10e); a fit held at the pole bound reached rss %.10e "
                             "(x%.6f)" % (label, row["start"], res["tf_rss"], held, held / res["tf_rss"]))
        else:
            res["tf_state"] = short_refusal(row["start"])
            notes.append("%s at %d/%d: turnfit %s" % (label, n, m, row["start"]))
        cands = []  # scipy's pole-free results: (rss, source, dist)
        for key, fn in (("a", lambda: fit_paper(x, yw, n, m)), ("b", lambda: fit_best(x, yw, n, m, sp))):
            (th, nfev, status, method), ms = timed(fn, o.min_time)
            b = np.concatenate(([1.0], th[n + 1:]))
            res[key + "_rss"] = rss_of(th, x, yw, n, m)
            res[key + "_g"], dist = root_class(b, hs)
            res[key + "_dist"] = dist
            res[key + "_ms"] = ms
            res[key + "_method"] = method
            if res[key + "_g"] == "-":
                cands.append((res[key + "_rss"], key, dist))
            if res[key + "_g"] == "ROOT":
                rts = np.roots(b[::-1])
                rts = np.sort(rts[np.abs(rts.imag) <= 1e-7 * np.maximum(1.0, np.abs(rts))].real)
                rts = rts[(rts >= -1) & (rts <= 1)]
                notes.append("%s scipy (%s): g has a real root on the window at x = %s (r = %s mm)" % (
                    label, key, ", ".join("%.4f" % v for v in rts), ", ".join("%.1f" % (centre + half * v) for v in rts)))
            elif res[key + "_g"] == "near":
                _, z = nearest_root(b)
                notes.append("%s scipy (%s): g's nearest root x = %.4f%+.4fi (r = %.1f%+.1fi mm), %.2f mm from the window "
                             "(bound %.1f mm)" % (label, key, z.real, z.imag, centre + half * z.real, half * z.imag,
                                                          dist * half, hs * half))
            if res["tf_rss"] is not None and res[key + "_rss"] < res["tf_rss"] * (1 - REL_TIE):
                notes.append("%s scipy (%s): rss %.10e < turnfit's %.10e (%s, g %s, min g on [-1, 1] %.3g); a = [%s], b = [1, %s]" % (
                    label, key, res[key + "_rss"], res["tf_rss"], method, res[key + "_g"], den_min(b),
                    ", ".join("%.10g" % v for v in th[: n + 1]), ", ".join("%.10g" % v for v in th[n + 1:])))
        if o.multistart > 0:
            best, th, count = multistart(x, yw, n, m, o.multistart, hs)
            res["ms"] = (best, count)
            if best is not None:
                b = np.concatenate(([1.0], th[n + 1:]))
                if res["tf_rss"] is None or best < res["tf_rss"] * (1 - REL_TIE):
                    seeds.append((label, "%s,%d,%d,%s,%s" % (coil, n, m, " ".join("%.17g" % v for v in th[: n + 1]),
                                                             " ".join("%.17g" % v for v in b))))
                dist = nearest_root(b)[0]
                cands.append((best, "ms", dist))
                if res["tf_rss"] is None or best < res["tf_rss"] * (1 - REL_TIE):
                    qmax, dqmax, dqin = edge_values(th[: n + 1], b)
                    notes.append("%s multistart: pole-free optimum rss %.10e, nearest root %.1f mm from the window, "
                                 "min g %.3g, max |f/g| %.3g, max |d(f/g)/dx| %.3g (%.3g on |x| <= 0.9); a = [%s], b = [1, %s]"
                                 % (label, best, dist * half, den_min(b), qmax, dqmax, dqin,
                                    ", ".join("%.10g" % v for v in th[: n + 1]), ", ".join("%.10g" % v for v in th[n + 1:])))
        res["sp_free"] = None
        if cands:  # the lowest; on a tie (rel. 1e-9) the first of (a), (b), multistart
            low = min(c[0] for c in cands)
            res["sp_free"] = next(c for c in cands if c[0] <= low * (1 + REL_TIE))
        table.append(res)

    def num(v, f):
        return "-" if v is None else f % v

    def ratio(u, v):
        return "-" if u is None or v is None else "%.6f" % (u / v)

    def tratio(u, v):
        return "-" if u is None or v is None else "%.2f" % (u / v)

    def mm(t, key):
        d = t[key + "_dist"]
        if d is None:
            return "-"
        g = t.get(key + "_g", "-")
        if g == "ROOT":
            return "ROOT"
        v = "inf" if not np.isfinite(d) else "%.1f" % (d * t["half"])
        return "near " + v if g == "near" else v

    def state(t):
        if t["tf_state"] == "fitted" and t["tf_start"] == "placed roots":
            return "fitted (placed)"
        return t["tf_state"]

    hdr = ["coil", "n/m", "pts", "turnfit", "turnfit rss", "tf pole mm", "tf held rss", "scipy(a) rss", "(a)/tf",
           "(a) pole mm", "scipy(b) rss", "(b)/tf", "(b) pole mm", "(b) run", "scipy pole-free rss", "from", "tf ms",
           "(a) ms", "(b) ms"]
    body = []
    for t in table:
        body.append([t["coil"], "%d/%d" % (t["n"], t["m"]), str(t["points"]), state(t), num(t["tf_rss"], "%.6e"),
                     mm(t, "tf"), num(t["tf_held"], "%.6e"), "%.6e" % t["a_rss"], ratio(t["a_rss"], t["tf_rss"]),
                     mm(t, "a"), "%.6e" % t["b_rss"], ratio(t["b_rss"], t["tf_rss"]), mm(t, "b"), t["b_method"],
                     "-" if t["sp_free"] is None else "%.6e" % t["sp_free"][0],
                     "-" if t["sp_free"] is None else SOURCE[t["sp_free"][1]],
                     "%.2f" % t["tf_ms"], "%.2f" % t["a_ms"], "%.2f" % t["b_ms"]])
    if o.markdown:
        print("| " + " | ".join(hdr) + " |")
        print("| " + " | ".join("---" for _ in hdr) + " |")
        for b in body:
            print("| " + " | ".join(b) + " |")
    else:
        w = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(hdr)]
        print("  ".join(h.rjust(w[i]) for i, h in enumerate(hdr)))
        for b in body:
            print("  ".join(c.rjust(w[i]) for i, c in enumerate(b)))
    fitted = [t for t in table if t["tf_rss"] is not None]
    refused = [t for t in table if t["tf_rss"] is None]
    tf_fit_ms = sum(t["tf_ms"] for t in fitted)
    tf_all_ms = sum(t["tf_ms"] for t in table)
    why = ", ".join("%s (%s)" % (t["coil"], t["tf_state"][len("refused: "):]) for t in refused) or "none"
    dists = [t["tf_dist"] * t["half"] for t in fitted]
    spacing = [t["hs_mm"] for t in table]
    print("turnfit: %d of %d coils fitted, refused %s; nearest root of the fitted g's %s mm from the window "
          "(bound %.1f-%.1f mm); time %.1f ms for the fits, %.1f ms with the refusals"
          % (len(fitted), len(table), why, "%.1f-%.1f" % (min(dists), max(dists)) if dists else "-",
             min(spacing), max(spacing), tf_fit_ms, tf_all_ms))
    for key, name in (("a", "scipy (a) paper-style lm"), ("b", "scipy (b) analytic Jacobian, best of 4 runs")):
        le = [t for t in fitted if t["tf_rss"] <= t[key + "_rss"] * (1 + REL_TIE)]
        lower = [t for t in fitted if t not in le]
        clean = [t for t in fitted if t[key + "_g"] == "-"]
        tot = sum(t[key + "_ms"] for t in table)
        print("summary %s: real root of g on the window on %d coils (%s); root within the bound (ROOT or near) on %d "
              "(%s); on turnfit's %d fitted coils turnfit rss <= scipy's (rel. 1e-9) on %d, scipy lower on %s; where "
              "scipy's is pole-free too (%d) turnfit <= scipy on %d (largest |rss ratio - 1| %.1e); time %.1f ms for all "
              "%d coils against turnfit's %.1f (x%.2f)"
              % (name, sum(t[key + "_g"] == "ROOT" for t in table),
                 ", ".join(t["coil"] for t in table if t[key + "_g"] == "ROOT") or "none",
                 sum(t[key + "_g"] != "-" for t in table),
                 ", ".join(t["coil"] for t in table if t[key + "_g"] != "-") or "none",
                 len(fitted), len(le), ", ".join("%s (g %s)" % (t["coil"], t[key + "_g"]) for t in lower) or "none",
                 len(clean), sum(t["tf_rss"] <= t[key + "_rss"] * (1 + REL_TIE) for t in clean),
                 max([abs(t[key + "_rss"] / t["tf_rss"] - 1) for t in clean] or [0]), tot, len(table), tf_all_ms,
                 tot / tf_all_ms))
    both = [t for t in fitted if t["sp_free"] is not None]
    le = [t for t in both if t["tf_rss"] <= t["sp_free"][0] * (1 + REL_TIE)]
    print("summary pole-free: turnfit's result <= scipy's best pole-free result (of (a), (b)%s; rel. 1e-9) on %d of %d "
          "coils (%d where both have one); scipy lower on %s; turnfit refused, scipy has a pole-free result: %s; "
          "turnfit fitted, scipy none: %s; neither: %s"
          % (" and the multistart" if o.multistart > 0 else "", len(le), len(table), len(both),
             ", ".join("%s (x%.6f)" % (t["coil"], t["sp_free"][0] / t["tf_rss"]) for t in both if t not in le) or "none",
             ", ".join("%s (%.6e, %s)" % (t["coil"], t["sp_free"][0], SOURCE[t["sp_free"][1]]) for t in refused
                       if t["sp_free"] is not None) or "none",
             ", ".join(t["coil"] for t in fitted if t["sp_free"] is None) or "none",
             ", ".join(t["coil"] for t in refused if t["sp_free"] is None) or "none"))
    # what the placed-root starts change: the same run with --extra-starts 0
    last0 = {}
    for r0 in rows0:
        if r0["coil"] != "total":
            last0[r0["coil"]] = r0
    for t in table:
        r0 = last0.get(t["coil"].rstrip("*"))
        if r0 is None:
            continue
        s0 = r0["start"]
        if t["tf_start"] != s0 or (t["tf_rss"] is not None and abs(float(r0["rss"]) - t["tf_rss"]) > REL_TIE * t["tf_rss"]):
            print("extra starts %s %d/%d: with --extra-starts 0 turnfit %s (%s ms); with 64 %s (%.2f ms)" % (
                t["coil"], t["n"], t["m"],
                ("refuses: " + short_refusal(s0)[len("refused: "):]) if s0.startswith("refused") else
                "fits rss %.10e (start %s)" % (float(r0["rss"]), s0), r0["time_ms"],
                t["tf_state"] if t["tf_rss"] is None else "fits rss %.10e (start %s)" % (t["tf_rss"], t["tf_start"]),
                t["tf_ms"]))
        elif t["tf_rss"] is None:
            print("extra starts %s %d/%d: refused either way; %s ms without the placed-root starts, %.2f ms with 64" % (
                t["coil"], t["n"], t["m"], r0["time_ms"], t["tf_ms"]))
    if o.multistart > 0:
        for t in table:
            best, k = t["ms"]
            print("multistart %s %d/%d: %d of %d random starts end pole-free; best rss %s%s" % (
                t["coil"], t["n"], t["m"], k, o.multistart, num(best, "%.10e"),
                "" if best is None or t["tf_rss"] is None else " = turnfit's x %.9f" % (best / t["tf_rss"])))
    if seeds:
        scmd, srows = run_bench(binary, o.machine, o.phase, o.min_time, [sd for _, sd in seeds])
        for (label, _), row in zip(seeds, [r_ for r_ in srows if r_["coil"] != "total"]):
            if row["start"].startswith("refused"):
                print("seeded %s %s/%s: turnfit given scipy's pole-free optimum as a start still refuses (%s ms): %s"
                      % (label, row["n"], row["m"], row["time_ms"], row["start"]))
            else:
                print("seeded %s %s/%s: turnfit given scipy's pole-free optimum as a start fits rss %.10e (start %s, "
                      "%s ms)" % (label, row["n"], row["m"], float(row["rss"]), row["start"], row["time_ms"]))
    for s in notes:
        print("note: " + s)


if __name__ == "__main__":
    main()
