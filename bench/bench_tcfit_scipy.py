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
      first g with a root on [-1, 1]); where that stops at the first pass (turnfit then has no
      linearized start) the best of 8 unconstrained passes ("lin*": scipy does not mind a pole
      in its start). The lowest rss of the 4 runs is kept (column "(b) run"), the time is that
      of all 4.

--multistart K adds, per coil, the best scipy optimum without a root of g on or within 1e-6 of
the window over K seeded random starts ('lm', analytic Jacobian): a search for a root-free
local optimum below turnfit's.

Each fit (start included) is repeated until --min-time seconds have passed; the median per fit is
reported. Every result's denominator is classified (columns "g"): POLE, a real root on [-1, 1]
(an infinity inside the coil's window: unusable as a field; scipy has no way to forbid it);
edge, the nearest root within 1e-6 (in x) outside the window (turnfit refuses steps with
g <= 1e-9 on the window, and an optimum that wants a pole ends pressed against that bound: the
fitted curve and its slope, the field, spike at the window's edge); "-" otherwise. A coil with
fewer points than parameters (TC18 at 4/5) is reported as refused by both tools and compared at
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


def read_scan(path):
    r, y = [], []
    with open(path) as f:
        rows = [ln for ln in f if ln.strip() and not ln.lstrip().startswith("#")]
    rd = csv.DictReader(rows)
    for row in rd:
        r.append(float(row["r_mm"]))
        y.append(float(row["dsinphi"]))
    return np.array(r), np.array(y)


def run_bench(binary, machine, phase, min_time):
    cmd = [binary, "--detail", "--min-time", str(min_time)]
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


def linearized_start(x, y, n, m, feasible_only=True):
    """Levy's linearized fit f - y g = 0, reweighted by 1/g (Sanathanan-Koerner), 8 passes: the
    pass with the least true rss. With feasible_only (turnfit's start) the passes stop at the
    first g with a root on [-1, 1] (None if the first has one); without, any finite pass counts."""
    A = np.hstack((vander(x, n), -y[:, None] * vander(x, m)[:, 1:]))
    w = np.ones(len(x))
    best, best_cost = None, np.inf
    for _ in range(8):
        t = np.linalg.lstsq(w[:, None] * A, w * y, rcond=None)[0]
        if not np.all(np.isfinite(t)):
            break
        b = np.concatenate(([1.0], t[n + 1:]))
        if feasible_only and m > 0 and den_min(b) <= 1e-9:
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


def fit_best(x, y, n, m):
    scale = np.max(np.abs(y)) or 1.0
    ys = y / scale
    fun, jac = make_problem(x, ys, n, m)
    starts = []
    lin = linearized_start(x, ys, n, m)
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


def multistart(x, y, n, m, k, seed=1):
    """Best rss (data units) over k random starts of 'lm' (analytic Jacobian) whose optimum's g
    has no root on or within 1e-6 of [-1, 1], and how many such optima there were."""
    scale = np.max(np.abs(y)) or 1.0
    fun, jac = make_problem(x, y / scale, n, m)
    rng = np.random.default_rng(seed)
    best, count = None, 0
    for _ in range(k):
        t0 = np.concatenate((rng.normal(0, 1, n + 1), rng.normal(0, 1, m) * rng.choice([0.1, 0.5, 1, 2])))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                s = least_squares(fun, t0, jac=jac, method="lm", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=2000)
            except Exception:
                continue
        if not np.isfinite(s.cost) or root_class(np.concatenate(([1.0], s.x[n + 1:])))[0] != "-":
            continue
        count += 1
        rss = 2 * s.cost * scale * scale
        if best is None or rss < best:
            best = rss
    return best, count


def root_class(b):
    """'POLE': g has a real root on [-1, 1]; 'edge': its nearest root lies within 1e-6 (in x) of
    the window, where turnfit's constraint g >= 1e-9 holds an optimum that wants a pole (the
    fitted curve, and far more its slope, the field, spike at the window's edge); '-' otherwise.
    Also the distance (in x, complex roots too) from the nearest root to [-1, 1]."""
    b = np.asarray(b, dtype=float)
    while len(b) > 1 and b[-1] == 0:
        b = b[:-1]
    if len(b) <= 1:
        return "-", np.inf
    roots = np.roots(b[::-1])
    dist = float(np.min(np.abs(roots - np.clip(roots.real, -1, 1))))
    if has_pole(b):
        return "POLE", 0.0
    return ("edge" if dist < 1e-6 else "-"), dist


def edge_values(a, b):
    """Largest |f/g| and |d(f/g)/dx| on [-1, 1] (fine grid), and the largest |d(f/g)/dx| on
    [-0.9, 0.9]."""
    X = np.linspace(-1, 1, 400001)
    q = np.polyval(np.asarray(a)[::-1], X) / np.polyval(np.asarray(b)[::-1], X)
    dq = np.gradient(q, X)
    return np.max(np.abs(q)), np.max(np.abs(dq)), np.max(np.abs(dq[np.abs(X) <= 0.9]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default="build/bench/bench_tcfit", help="bench_tcfit binary")
    ap.add_argument("--machine", default=os.path.join(SHARE, "machine.json"))
    ap.add_argument("--phase", default=os.path.join(SHARE, "measured", "phase"))
    ap.add_argument("--min-time", type=float, default=0.2, help="seconds of repeats per coil and tool")
    ap.add_argument("--multistart", type=int, default=0, metavar="K",
                    help="also search K random starts per coil for a root-free optimum below turnfit's")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    o = ap.parse_args()
    binary = o.bin
    if not os.path.exists(binary) and os.path.exists(os.path.join(REPO, binary)):
        binary = os.path.join(REPO, binary)
    if not os.path.exists(binary):
        sys.exit("bench_tcfit_scipy.py: %s: no such binary (build it: cmake --build BUILD --target bench_tcfit)" % o.bin)
    cmd, rows = run_bench(binary, o.machine, o.phase, o.min_time)
    print("# turnfit: %s" % " ".join(cmd))
    print("# scipy %s, numpy %s, python %s; scipy (a) and (b) as in this script's docstring" % (
        scipy.__version__, np.__version__, sys.version.split()[0]))

    coils = {}
    for row in rows:
        if row["coil"] != "total":
            coils.setdefault(row["coil"], []).append(row)
    table, notes = [], []
    for coil, crows in coils.items():
        first, row = crows[0], crows[-1]
        n, m = int(row["n"]), int(row["m"])
        label = coil
        r, y = read_scan(os.path.join(o.phase, coil + ".csv"))
        lo, hi = float(row["r_lo"]), float(row["r_hi"])
        sel = (r >= lo) & (r <= hi)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        x, yw = (r[sel] - centre) / half, y[sel]
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
        res = {"coil": label, "n": n, "m": m, "points": len(x), "tf_rss": None, "tf_ms": None, "tf_g": "refused"}
        if not row["start"].startswith("refused"):
            tf_theta = np.array([float(v) for v in row["a"].split()] + [float(v) for v in row["b"].split()[1:]])
            tf_a, tf_b = tf_theta[: n + 1], np.concatenate(([1.0], tf_theta[n + 1:]))
            res["tf_rss"], res["tf_ms"] = float(row["rss"]), float(row["time_ms"])
            res["tf_g"], dist = root_class(tf_b)
            here = rss_of(tf_theta, x, yw, n, m)
            if abs(here - res["tf_rss"]) > 1e-6 * res["tf_rss"]:
                notes.append("%s: turnfit's coefficients give rss %.6e here, it reported %.6e" % (coil, here, res["tf_rss"]))
            if res["tf_g"] != "-":
                qmax, dqmax, dqin = edge_values(tf_a, tf_b)
                notes.append("%s turnfit: g's nearest root %.1e (in x) outside the window, min g on [-1, 1] %.2e: "
                             "max |f/g| %.3g, max |d(f/g)/dx| %.3g on the window (%.3g on |x| <= 0.9); a = [%s], b = [%s]"
                             % (label, dist, den_min(tf_b), qmax, dqmax, dqin, row["a"].replace(" ", ", "),
                                row["b"].replace(" ", ", ")))
        else:
            notes.append("%s at %d/%d: turnfit %s" % (coil, n, m, row["start"]))
        for key, fn in (("a", fit_paper), ("b", fit_best)):
            (th, nfev, status, method), ms = timed(lambda: fn(x, yw, n, m), o.min_time)
            b = np.concatenate(([1.0], th[n + 1:]))
            res[key + "_rss"] = rss_of(th, x, yw, n, m)
            res[key + "_g"], dist = root_class(b)
            res[key + "_ms"] = ms
            res[key + "_method"] = method
            if res[key + "_g"] == "POLE":
                rts = np.roots(b[::-1])
                rts = np.sort(rts[np.abs(rts.imag) <= 1e-7 * np.maximum(1.0, np.abs(rts))].real)
                rts = rts[(rts >= -1) & (rts <= 1)]
                notes.append("%s scipy (%s): g has a root on the window at x = %s (r = %s mm)" % (
                    label, key, ", ".join("%.4f" % v for v in rts), ", ".join("%.1f" % (centre + half * v) for v in rts)))
            if res["tf_rss"] is not None and res[key + "_rss"] < res["tf_rss"] * (1 - REL_TIE):
                notes.append("%s scipy (%s): rss %.10e < turnfit's %.10e (%s, g %s, min g on [-1, 1] %.3g); a = [%s], b = [1, %s]" % (
                    label, key, res[key + "_rss"], res["tf_rss"], method, res[key + "_g"], den_min(b),
                    ", ".join("%.10g" % v for v in th[: n + 1]), ", ".join("%.10g" % v for v in th[n + 1:])))
        if o.multistart > 0:
            res["ms"] = multistart(x, yw, n, m, o.multistart)
        table.append(res)

    def num(v, f):
        return "-" if v is None else f % v

    def ratio(u, v):
        return "-" if u is None or v is None else "%.6f" % (u / v)

    def tratio(u, v):
        return "-" if u is None or v is None else "%.2f" % (u / v)

    hdr = ["coil", "n/m", "pts", "turnfit rss", "tf g", "scipy(a) rss", "(a)/tf", "(a) g", "scipy(b) rss", "(b)/tf",
           "(b) g", "(b) run", "tf ms", "(a) ms", "(b) ms", "(a)/tf time", "(b)/tf time"]
    body = []
    for t in table:
        body.append([t["coil"], "%d/%d" % (t["n"], t["m"]), str(t["points"]), num(t["tf_rss"], "%.6e"), t["tf_g"],
                     "%.6e" % t["a_rss"], ratio(t["a_rss"], t["tf_rss"]), t["a_g"],
                     "%.6e" % t["b_rss"], ratio(t["b_rss"], t["tf_rss"]), t["b_g"], t["b_method"],
                     num(t["tf_ms"], "%.2f"), "%.2f" % t["a_ms"], "%.2f" % t["b_ms"],
                     tratio(t["a_ms"], t["tf_ms"]), tratio(t["b_ms"], t["tf_ms"])])
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
    refused = [t["coil"] for t in table if t["tf_rss"] is None]
    tf_total = sum(t["tf_ms"] for t in fitted)
    print("turnfit: %d coils fitted%s; g held at the window's edge (nearest root < 1e-6 outside) on %d: %s; "
          "total time %.1f ms" % (len(fitted), (", refused " + ", ".join(refused)) if refused else "",
                                  sum(t["tf_g"] != "-" for t in fitted),
                                  ", ".join(t["coil"] for t in fitted if t["tf_g"] != "-") or "none", tf_total))
    for key, name in (("a", "scipy (a) paper-style lm"), ("b", "scipy (b) analytic Jacobian, best of 4 runs")):
        le = [t for t in fitted if t["tf_rss"] <= t[key + "_rss"] * (1 + REL_TIE)]
        lower = [t for t in fitted if t not in le]
        clean = [t for t in fitted if t["tf_g"] == "-" and t[key + "_g"] == "-"]
        tot = sum(t[key + "_ms"] for t in fitted)
        print("summary %s: turnfit rss <= scipy's (rel. 1e-9) on %d of %d coils; scipy lower on %s%s; "
              "g with a root on the window: %s; on the %d coils where neither g has a root on or within 1e-6 of the "
              "window, turnfit <= scipy on %d (largest |rss ratio - 1| %.1e); time %.1f ms against turnfit's %.1f (x%.2f)"
              % (name, len(le), len(fitted), ", ".join("%s (g %s)" % (t["coil"], t[key + "_g"]) for t in lower) or "none",
                 "", ", ".join(t["coil"] for t in table if t[key + "_g"] == "POLE") or "none", len(clean),
                 sum(t["tf_rss"] <= t[key + "_rss"] * (1 + REL_TIE) for t in clean),
                 max([abs(t[key + "_rss"] / t["tf_rss"] - 1) for t in clean] or [0]), tot, tf_total, tot / tf_total))
    if o.multistart > 0:
        for t in table:
            best, k = t["ms"]
            print("multistart %s %d/%d: %d of %d random starts end root-free; best rss %s%s" % (
                t["coil"], t["n"], t["m"], k, o.multistart, num(best, "%.10e"),
                "" if best is None or t["tf_rss"] is None else " = turnfit's x %.9f" % (best / t["tf_rss"])))
    for s in notes:
        print("note: " + s)


if __name__ == "__main__":
    main()
