#!/usr/bin/env bash
# Signatures of the concealed effects (turnfit-machine(5), EFFECTS) on the default machine ring8.
#
#   bench/effect_signatures.sh BIN_DIR [WORK_DIR]
#
# BIN_DIR holds turnfit-track (e.g. build/tools). For every case the script writes a machine
# variant of share/turnfit/ring8/machine.json into WORK_DIR (default: a fresh mktemp folder,
# removed afterwards) with the map/profile paths made absolute and an `effects` array added,
# tracks the single reference particle with and without the effect (default integrator,
# 200 turns, --kicks for the energy per turn and the RF phases), and prints, per case:
#   dr = r(with) - r(without) at RRI2 (turns 1-16) and RRL (turns 9-182): max |dr| and turn,
#   first turn with |dr| > 0.01 mm, dr at RRL turn 182;
#   the dominant oscillation of dr (least-squares sine + quadratic trend, q in 0.03..0.5
#   cycles per turn) in windows RRI2 1-16 and 15-turn windows along RRL, against the alias
#   min(frac(nu_r), 1 - frac(nu_r)) of nu_r from orbits.csv at the window's mean energy;
#   dE and dphase (mean RF phase of main1..main4 crossings) at turns 50, 100, 182;
#   the turn count to 590 MeV (interpolated between turn ends) and its change;
#   a formula prediction where one applies (see PRED lines).
# Truth amplitudes are read from share/turnfit/ring8/params.json "truth.effects" when present.
# Needs bash and python3 only; about 40 tracks of ~0.15 s.
set -euo pipefail
if [ $# -lt 1 ] || [ ! -x "$1/turnfit-track" ]; then
  echo "usage: $0 BIN_DIR [WORK_DIR]   (BIN_DIR/turnfit-track must exist)" >&2
  exit 64
fi
BIN=$(cd "$1" && pwd)
REPO=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -ge 2 ]; then
  WORK=$2; mkdir -p "$WORK"; KEEP=1
else
  WORK=$(mktemp -d /tmp/effsig.XXXXXX); KEEP=0
fi
cleanup() { if [ "$KEEP" = 0 ]; then rm -rf "$WORK"; fi; }
trap cleanup EXIT

python3 - "$BIN" "$REPO" "$WORK" <<'PYEOF'
import csv, json, math, os, subprocess, sys, copy

BIN, REPO, WORK = sys.argv[1:4]
R8 = os.path.join(REPO, 'share/turnfit/ring8')
TRACK = os.path.join(BIN, 'turnfit-track')
MP = 938.27208816          # proton rest energy [MeV]
H = 6                      # harmonic
NSEC = 8
TURNS = 200

base_machine = json.load(open(os.path.join(R8, 'machine.json')))
def absolutize(m):
    m = copy.deepcopy(m)
    m['field']['map'] = os.path.join(R8, m['field']['map'])
    for c in m['cavities']:
        if 'profile' in c:
            c['profile'] = os.path.join(R8, c['profile'])
    for t in m.get('trimcoils', []):
        if 'table' in t:
            t['table'] = os.path.join(R8, t['table'])
    return m

# ---- truth amplitudes -------------------------------------------------------------
truth = {}
try:
    for e in json.load(open(os.path.join(R8, 'params.json')))['truth']['effects']:
        truth.setdefault(e['type'], e)
except Exception:
    pass
def tget(typ, key, default):
    return truth.get(typ, {}).get(key, default)
fh_A = tget('field-harmonic', 'amplitude_T', 1.5e-4)
fh_phi = tget('field-harmonic', 'phase_deg', 40.0)
fh_r = tget('field-harmonic', 'r_mm', 3100.0)
fh_w = tget('field-harmonic', 'width_mm', 500.0)
gb_cav = tget('gap-bow', 'cavity', 'main3')
gb_sag = tget('gap-bow', 'sagitta_mm', 3.0)
vt_cav = tget('voltage-tilt', 'cavity', 'main1')
vt_slope = tget('voltage-tilt', 'slope', 0.02)
po_probe = tget('probe-offset', 'probe', 'RRL')
po_dphi = tget('probe-offset', 'dphi_deg', 0.15)
tc_coils = tget('trimcoil-sectors', 'coils', ['TC%d' % i for i in range(6, 15)])
tc_secs = tget('trimcoil-sectors', 'sectors', [1, 3, 5, 7])

# ---- orbits.csv: nu_r and mean radius against energy --------------------------------
orb = [r for r in csv.DictReader(open(os.path.join(R8, 'orbits.csv'))) if r['status'] == 'ok']
orbE = [float(r['energy_MeV']) for r in orb]
def interp(xs, ys, x):
    if x <= xs[0]: return ys[0]
    if x >= xs[-1]: return ys[-1]
    lo, hi = 0, len(xs) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x: lo = mid
        else: hi = mid
    f = (x - xs[lo]) / (xs[hi] - xs[lo])
    return ys[lo] + f * (ys[hi] - ys[lo])
nu_r = lambda E: interp(orbE, [float(r['nu_r']) for r in orb], E)
ravg = lambda E: interp(orbE, [float(r['r_avg_mm']) for r in orb], E)
gamma = lambda E: 1 + E / MP
brho = lambda E: math.sqrt(E * E + 2 * E * MP) / 299.792458   # T m
def alias(nu):
    f = nu - math.floor(nu)
    return min(f, 1 - f)

# ---- running -------------------------------------------------------------------------
counter = [0]
def run(machine, extra=(), orbit=False):
    counter[0] += 1
    tag = 'v%02d' % counter[0]
    mf = os.path.join(WORK, tag + '.json')
    json.dump(machine, open(mf, 'w'), indent=1)
    out, kf = os.path.join(WORK, tag + '.csv'), os.path.join(WORK, tag + '-kicks.csv')
    cmd = [TRACK, mf, '-q', '--turns', str(TURNS), '--kicks', kf, '-o', out] + list(extra)
    if orbit:
        cmd += ['--orbit', os.path.join(WORK, tag + '-orbit.csv')]
    subprocess.run(cmd, check=True)
    probes = {}
    for r in csv.reader(l for l in open(out) if not l.startswith('#')):
        if r[0] == 'probe': continue
        probes.setdefault(r[0], {})[int(r[1])] = dict(r=float(r[2]), s=float(r[3]), t=float(r[4]),
                                                       E=float(r[5]), ph=float(r[6]))
    # energy at each turn end: the kicks summed, anchored to the final energy of the '# end' line
    # (so design variables such as benergy and injection offsets need no special case)
    E, Eturn, ph = 0.0, {0: 0.0}, {}
    for r in csv.reader(l for l in open(kf) if not l.startswith('#')):
        if r[0] == 'gap': continue
        t = int(r[1]); E += float(r[6]); Eturn[t] = E
        ph.setdefault(t, {})[r[0]] = dict(ph=float(r[4]), rho=float(r[3]), de=float(r[6]))
    end = [l for l in open(out) if l.startswith('# end')][0]
    Efinal = float(end.split('energy_MeV=')[1].split()[0])
    last = max(Eturn)
    Eturn = {n: v + Efinal - Eturn[last] for n, v in Eturn.items()}
    res = dict(probes=probes, E=Eturn, kicks=ph, tag=tag)
    if orbit:
        rows = [list(map(float, r)) for r in csv.reader(l for l in open(os.path.join(WORK, tag + '-orbit.csv'))
                                                         if not l.startswith('#')) if r[0] != 'theta_deg']
        res['orbit'] = rows
    return res

def n590(res):
    E = res['E']
    for n in sorted(E):
        if n > 0 and E[n] >= 590.0:
            return n - 1 + (590.0 - E[n - 1]) / (E[n] - E[n - 1])
    return float('nan')

def mainphase(res, n):
    k = res['kicks'].get(n, {})
    v = [k[c]['ph'] for c in ('main1', 'main2', 'main3', 'main4') if c in k]
    return sum(v) / len(v) if v else float('nan')

def sinefit(ts, ys):
    """best q in [0.03,0.5]: y = a + b t + c t^2 + A cos(2 pi q t + p); returns (q, amplitude)"""
    if len(ts) < 8: return (float('nan'), float('nan'))
    t0 = sum(ts) / len(ts)
    best = None
    q = 0.03
    while q <= 0.5 + 1e-9:
        X = [[1.0, t - t0, (t - t0) ** 2, math.cos(2 * math.pi * q * t), math.sin(2 * math.pi * q * t)] for t in ts]
        # normal equations 5x5
        m = 5
        A = [[sum(x[i] * x[j] for x in X) for j in range(m)] for i in range(m)]
        b = [sum(x[i] * y for x, y in zip(X, ys)) for i in range(m)]
        try:
            sol = solve(A, b)
        except ZeroDivisionError:
            q += 0.0025; continue
        rss = sum((y - sum(s * xi for s, xi in zip(sol, x))) ** 2 for x, y in zip(X, ys))
        if best is None or rss < best[0]:
            best = (rss, q, math.hypot(sol[3], sol[4]))
        q += 0.0025
    return (best[1], best[2]) if best else (float('nan'), float('nan'))

def solve(A, b):
    n = len(b); M = [row[:] + [bb] for row, bb in zip(A, b)]
    for i in range(n):
        p = max(range(i, n), key=lambda r: abs(M[r][i]))
        if abs(M[p][i]) < 1e-12: raise ZeroDivisionError
        M[i], M[p] = M[p], M[i]
        for r in range(n):
            if r != i:
                f = M[r][i] / M[i][i]
                M[r] = [a - f * c for a, c in zip(M[r], M[i])]
    return [M[i][n] / M[i][i] for i in range(n)]

# 15-turn windows: nu_r changes too fast along RRL for longer ones (the fit has no chirp)
WINDOWS = [('RRI2', 1, 16), ('RRL', 9, 23), ('RRL', 33, 47), ('RRL', 63, 77), ('RRL', 93, 107),
           ('RRL', 116, 130), ('RRL', 143, 157), ('RRL', 168, 182)]

# ---- baseline ---------------------------------------------------------------------------
base_m = absolutize(base_machine)
BASE = run(base_m, orbit=True)
N0 = n590(BASE)
print('# ring8 effect signatures: turnfit-track from %s, repo %s' % (BIN, REPO))
print('# baseline: RRI2 turns %d-%d, RRL turns %d-%d, E(182) = %.4f MeV, turns to 590 MeV = %.3f'
      % (min(BASE['probes']['RRI2']), max(BASE['probes']['RRI2']), min(BASE['probes']['RRL']),
         max(BASE['probes']['RRL']), BASE['E'][182], N0))
for p, a, b in WINDOWS:
    Em = sum(BASE['probes'][p][n]['E'] for n in range(a, b + 1)) / (b - a + 1)
    print('# window %-4s %3d-%3d: mean E %6.1f MeV, nu_r %.3f, alias q = %.3f /turn (period %.1f turns)'
          % (p, a, b, Em, nu_r(Em), alias(nu_r(Em)), 1 / alias(nu_r(Em))))

def diff(res, ref, probe):
    a, b = res['probes'].get(probe, {}), ref['probes'].get(probe, {})
    return {n: a[n]['r'] - b[n]['r'] for n in sorted(set(a) & set(b))}

def crossing_psi(probe, s):
    p = next(p for p in base_machine['probes'] if p['name'] == probe)
    return p['phi_deg'] - math.degrees(math.atan2(p.get('a_mm', 0.0), s))

rows_out = []
def report(name, size, res, ref=None, pred=None, note=None):
    ref = ref or BASE
    d1, d2 = diff(res, ref, 'RRI2'), diff(res, ref, 'RRL')
    def mx(d):
        if not d: return (float('nan'), 0)
        n = max(d, key=lambda k: abs(d[k])); return (d[n], n)
    def onset(d):
        for n in sorted(d):
            if abs(d[n]) > 0.01: return n
        return '-'
    m1, m2 = mx(d1), mx(d2)
    lost = sorted(set(ref['probes']['RRL']) ^ set(res['probes'].get('RRL', {})))
    nN = n590(res)
    print('\n== %s, %s' % (name, size))
    print('   RRI2: max|dr| %+.3f mm at turn %d, first |dr|>0.01 at %s;  RRL: max|dr| %+.3f mm at turn %d, '
          'first |dr|>0.01 at %s, dr(182) %+.3f mm' % (m1[0], m1[1], onset(d1), m2[0], m2[1], onset(d2),
                                                       d2.get(182, float('nan'))))
    if lost:
        print('   RRL turns present in only one run: %s' % lost)
    osc = []
    for p, a, b in WINDOWS:
        d = d1 if p == 'RRI2' else d2
        ts = [n for n in range(a, b + 1) if n in d]
        q, amp = sinefit(ts, [d[n] for n in ts])
        Em = sum(ref['probes'][p][n]['E'] for n in ts) / max(len(ts), 1)
        if amp >= 0.02:
            osc.append('%s %d-%d: q %.3f (alias of nu_r %.3f) amp %.3f' % (p, a, b, q, alias(nu_r(Em)), amp))
        else:
            osc.append('%s %d-%d: amp %.3f' % (p, a, b, amp))
    print('   oscillation: ' + '; '.join(osc))
    sm = []
    for c in (20, 40, 60, 80, 100, 120, 140, 160, 178):
        v = [d2[n] for n in range(c - 4, c + 5) if n in d2]
        if v: sm.append('t%d %+.3f' % (c, sum(v) / len(v)))
    print('   RRL dr, 9-turn running mean: ' + ' '.join(sm))
    dE = {n: res['E'][n] - ref['E'][n] for n in (50, 100, 182)}
    dP = {n: mainphase(res, n) - mainphase(ref, n) for n in (50, 100, 182)}
    print('   dE [MeV] t50 %+.4f t100 %+.4f t182 %+.4f;  dphase [deg] t50 %+.3f t100 %+.3f t182 %+.3f;  '
          'turns to 590 MeV %.3f (%+.3f)' % (dE[50], dE[100], dE[182], dP[50], dP[100], dP[182], nN, nN - n590(ref)))
    if pred:
        for l in pred(res, ref, d1, d2):
            print('   PRED ' + l)
    if note:
        print('   NOTE ' + note)
    rows_out.append((name, size, m1, m2, d2.get(182, float('nan')), dE[182], dP[182], nN - n590(ref)))
    return res

def with_effects(effs, m=None):
    m = copy.deepcopy(m or base_m)
    m['effects'] = effs
    return m

# ---- field-harmonic ---------------------------------------------------------------------
def fh_pred(A, phi, r0, w):
    def f(res, ref, d1, d2):
        out = []
        for probe, d in (('RRI2', d1), ('RRL', d2)):
            best = None
            for n in d:
                row = ref['probes'][probe][n]
                E, R = row['E'], ravg(row['E'])
                g = 1.0 if r0 is None else math.exp(-(row['r'] - r0) ** 2 / (2 * w * w))
                psi = crossing_psi(probe, row['s'])
                amp = (R / 1000) ** 2 * A * g / (brho(E) * (nu_r(E) ** 2 - 1)) * 1000
                x = -amp * math.cos(math.radians(psi - phi))
                if best is None or abs(x) > abs(best[0]): best = (x, n, amp, nu_r(E))
            mean = sum(d.values()) / len(d)
            out.append('%s closed-orbit shift -R^2 A g cos(psi-phi)/(B rho (nu_r^2-1)): max %+.3f mm at turn %d '
                       '(amplitude %.3f mm, nu_r %.3f); measured max %+.3f mm, mean dr %+.3f mm'
                       % (probe, best[0], best[1], best[2], best[3], max(d.values(), key=abs), mean))
        return out
    return f

for A, lab in ((fh_A, 'truth'), (2 * fh_A, '2x truth')):
    report('field-harmonic n=1 local', '%s: %.1f G, phase %g deg, r %g mm, width %g mm' % (lab, A * 1e4, fh_phi, fh_r, fh_w),
           run(with_effects([dict(type='field-harmonic', n=1, amplitude_T=A, phase_deg=fh_phi, r_mm=fh_r, width_mm=fh_w)])),
           pred=fh_pred(A, fh_phi, fh_r, fh_w))
for A in (fh_A, fh_A / 3):
    report('field-harmonic n=1 global', '%.2f G, phase %g deg, all radii' % (A * 1e4, fh_phi),
           run(with_effects([dict(type='field-harmonic', n=1, amplitude_T=A, phase_deg=fh_phi)])),
           pred=fh_pred(A, fh_phi, None, None),
           note='beam starts on the unperturbed orbit: expect dr oscillating about the closed-orbit shift with '
                'an amplitude of about that shift')

# ---- sector-strength --------------------------------------------------------------------
def ss_pred(rel):
    def f(res, ref, d1, d2):
        out, acc = [], 0.0
        cum = {}
        for n in range(1, 183):
            E = ref['E'][n - 1]
            acc += -360.0 * H * (rel / NSEC) / gamma(E) ** 2
            cum[n] = acc
        out.append('phase slip -360 h (rel/N)/gamma^2 per turn, summed: t50 %+.2f t100 %+.2f t182 %+.2f deg '
                   '(uniform-field -360 h rel/N per turn: t182 %+.2f deg)'
                   % (cum[50], cum[100], cum[182], -360.0 * H * rel / NSEC * 182))
        E = ref['E'][0]; R = ravg(E)
        a1 = rel * 2 / math.pi * math.sin(math.pi / NSEC)
        amp = R * a1 / (nu_r(E) ** 2 - 1)
        out.append('first harmonic %.2e of <B> (window of one sector): closed-orbit shift at injection %.2f mm '
                   '(x = -%.2f cos(psi - sector azimuth)); RRI2 measured oscillation range %+.3f..%+.3f mm'
                   % (a1, amp, amp, min(d1.values()), max(d1.values())))
        return out
    return f
for rel in (0.001, 0.0003):
    report('sector-strength', 'sector 1, relative %+g' % rel,
           run(with_effects([dict(type='sector-strength', sector=1, relative=rel)])), pred=ss_pred(rel))

# ---- trimcoil-sectors -------------------------------------------------------------------
def tc_machine(bmax_by_coil):
    m = copy.deepcopy(base_m)
    for t in m['trimcoils']:
        if t['name'] in bmax_by_coil: t['bmax_T'] = bmax_by_coil[t['name']]
    return m
def tc_pred(nom, uniform=True):
    def f(res, ref, d1, d2):
        out = []
        for n in ((50, 100, 182) if uniform else ()):
            a = mainphase(ref, n) - mainphase(nom, n)
            o = mainphase(res, n) - mainphase(nom, n)
            out.append('turn %d: phase vs bmax 0: all sectors %+.3f deg, odd sectors %+.3f deg (ratio %.3f; '
                       'half the average field predicts 0.5)' % (n, a, o, o / a if a else float('nan')))
        da = diff(ref, nom, 'RRL'); do = diff(res, nom, 'RRL')
        na = max(da, key=lambda k: abs(da[k])); no = max(do, key=lambda k: abs(do[k]))
        out.append('RRL vs bmax 0: all sectors max %+.3f mm (turn %d), odd sectors max %+.3f mm (turn %d); '
                   'turns to 590: all %+.3f, odd %+.3f' % (da[na], na, do[no], no, n590(ref) - N0, n590(res) - N0))
        return out
    return f
for b in (5e-4, 2e-4):
    coils = {c: b for c in tc_coils}
    m_all = tc_machine(coils)
    all_res = run(m_all)
    report('trimcoil-sectors', '%s at %.1f mT, sectors %s vs all sectors' % (
        '%s-%s' % (tc_coils[0], tc_coils[-1]), b * 1e3, tc_secs),
        run(with_effects([dict(type='trimcoil-sectors', coils=tc_coils, sectors=tc_secs)], m_all)),
        ref=all_res, pred=tc_pred(BASE))
# the truth's trim-coil settings (truth dvars) with and without the odd-sector placement
try:
    tdv = json.load(open(os.path.join(R8, 'params.json')))['truth']['dvars']
except Exception:
    tdv = {}
tcb = {}
for k, v in tdv.items():
    if k.startswith('tc') and k.endswith('mb'):
        tcb['TC%d' % int(k[2:-2])] = v
if tcb:
    m_t = tc_machine(tcb)
    t_res = run(m_t)
    report('trimcoil-sectors', 'truth trim settings %s, sectors %s vs all'
           % (', '.join('%s %.2f mT' % (c, v * 1e3) for c, v in sorted(tcb.items(), key=lambda x: int(x[0][2:]))), tc_secs),
           run(with_effects([dict(type='trimcoil-sectors', coils=tc_coils, sectors=tc_secs)], m_t)),
           ref=t_res, pred=tc_pred(BASE, uniform=False))

# ---- gap-bow ----------------------------------------------------------------------------
def gb_pred(cav, sag):
    c = next(c for c in base_m['cavities'] if c['name'] == cav)
    def f(res, ref, d1, d2):
        out = []
        for n in (1, 50, 100, 182):
            k0, k1 = ref['kicks'][n][cav], res['kicks'][n][cav]
            rho = k0['rho']
            u = c.get('rmin_mm', 0) + rho * (c['rmax_mm'] - c['rmin_mm'])
            r = math.hypot(u, c.get('pdis_mm', 0.0))
            bow = sag * 4 * rho * (1 - rho)
            pred = math.degrees(H * c.get('harmonic_factor', 1) * bow * (u / r) / r)
            out.append('turn %d (rho_n %.3f, r %.0f mm): %s RF phase h*bow/r %+.4f deg, measured %+.4f deg; '
                       'de %+.5f MeV' % (n, rho, r, cav, pred, k1['ph'] - k0['ph'], k1['de'] - k0['de']))
        return out
    return f
for sag in (gb_sag, 10.0):
    report('gap-bow', '%s sagitta %g mm' % (gb_cav, sag),
           run(with_effects([dict(type='gap-bow', cavity=gb_cav, sagitta_mm=sag)])), pred=gb_pred(gb_cav, sag))

# ---- voltage-tilt -----------------------------------------------------------------------
PROFILES = {}
def dlnV(c, rho):
    f = c.get('profile')
    if not f: return 0.0
    if f not in PROFILES:
        rows = [list(map(float, l.split())) for l in open(f).read().split('\n')[1:] if l.strip()]
        PROFILES[f] = rows
    rows = PROFILES[f]
    xs = [r[0] for r in rows]
    return interp(xs, [r[2] for r in rows], rho) / interp(xs, [r[1] for r in rows], rho)
def vt_pred(cav, slope):
    def f(res, ref, d1, d2):
        acc, cum = 0.0, {}
        for n in range(1, 201):
            k = ref['kicks'].get(n, {}).get(cav)
            if k: acc += k['de'] * slope * (k['rho'] - 0.5)
            cum[n] = acc
        nmin = min(cum, key=lambda n: cum[n] if slope > 0 else -cum[n])
        # dr from dE with the RRL turn pattern's dr/dE
        rr = ref['probes']['RRL']; best = None
        for n in range(10, 182):
            if n - 1 in rr and n + 1 in rr:
                drdE = (rr[n + 1]['r'] - rr[n - 1]['r']) / (rr[n + 1]['E'] - rr[n - 1]['E'])
                x = cum[n] * drdE
                if best is None or abs(x) > abs(best[0]): best = (x, n)
        meas = {n: res['E'][n] - ref['E'][n] for n in (50, 100, 182)}
        # closed loop: a particle dE behind sits dE dR/dE further in, where every gap's profile
        # V(rho_n) gives a different voltage (d ln V/d rho_n from the profile files)
        cavs = {c['name']: c for c in base_m['cavities']}
        dE, cl = 0.0, {}
        for n in range(1, 201):
            for g, k in ref['kicks'].get(n, {}).items():
                c = cavs[g]
                E = ref['E'][n - 1]
                dRdE = (ravg(E + 1) - ravg(E - 1)) / 2
                u = c.get('rmin_mm', 0) + k['rho'] * (c['rmax_mm'] - c['rmin_mm'])
                r = math.hypot(u, c.get('pdis_mm', 0.0))
                drho = dE * dRdE * (r / u) / (c['rmax_mm'] - c['rmin_mm'])
                rel = dlnV(c, k['rho']) * drho
                if g == cav: rel += slope * (k['rho'] - 0.5)
                dE += k['de'] * rel
            cl[n] = dE
        return ['dE = sum of de(%s) slope (rho_n - 0.5): t50 %+.4f t100 %+.4f t182 %+.4f MeV, extreme %+.4f at turn %d '
                '(measured %+.4f %+.4f %+.4f)' % (cav, cum[50], cum[100], cum[182], cum[nmin], nmin,
                                                   meas[50], meas[100], meas[182]),
                'closed loop (the radius lag changes every gap\'s voltage through its profile): t50 %+.4f '
                't100 %+.4f t182 %+.4f MeV' % (cl[50], cl[100], cl[182]),
                'dr = dE dr/dE at RRL: extreme %+.3f mm at turn %d' % best]
    return f
for sl in (vt_slope, 0.05):
    report('voltage-tilt', '%s slope %g (pivot 0.5)' % (vt_cav, sl),
           run(with_effects([dict(type='voltage-tilt', cavity=vt_cav, slope=sl)])), pred=vt_pred(vt_cav, sl))

# ---- probe-offset -----------------------------------------------------------------------
orbit = []                     # theta_deg, r_mm, z, pr, t_ns, E; theta unwrapped, deduplicated
for row in BASE['orbit']:
    if not orbit or row[0] > orbit[-1][0]: orbit.append(row)
OTH = [o[0] for o in orbit]
def orbit_at(key, x):
    """theta at time x (key 4) or r at azimuth x (key 0): quadratic through the 3 nearest rows"""
    xs = [o[key] for o in orbit] if key != 0 else OTH
    lo, hi = 0, len(xs) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x: lo = mid
        else: hi = mid
    i = max(1, min(len(xs) - 2, lo if x - xs[lo] < xs[hi] - x else hi))
    ys = [o[0] if key == 4 else o[1] for o in orbit[i - 1:i + 2]]
    xx = xs[i - 1:i + 2]
    v = 0.0
    for j in range(3):
        l = 1.0
        for k in range(3):
            if k != j: l *= (x - xx[k]) / (xx[j] - xx[k])
        v += ys[j] * l
    return v
def rotation_pred(t_ns, dphi, s, a):
    """reading change of a probe turned by dphi about the centre: the orbit dphi further on,
    corrected for a probe line that is not radial (its azimuth changes with r)"""
    th = orbit_at(4, t_ns)
    r0 = orbit_at(0, th)
    d = orbit_at(0, th + dphi) - r0
    if dphi == 0 or a == 0: return d
    g = d / math.radians(dphi)                 # mm per rad
    return d / (1 + g * a / (r0 * s))
def po_pred(probe, dphi, ds):
    pr = next(p for p in base_machine['probes'] if p['name'] == probe)
    def f(res, ref, d1, d2):
        d = d1 if probe == 'RRI2' else d2
        rows = ref['probes'][probe]
        pred = {}
        for n in d:
            row = rows[n]
            a = pr.get('a_mm', 0.0)
            pred[n] = rotation_pred(row['t'], dphi, row['s'], a) - ds * row['s'] / math.hypot(row['s'], a)
        err = max(abs(d[n] - pred[n]) for n in d)
        nm = max(d, key=lambda n: abs(d[n]))
        ts = sorted(d)
        sample = ', '.join('t%d %+.3f (pred %+.3f)' % (n, d[n], pred[n]) for n in ts[::max(1, len(ts) // 6)])
        other = d2 if probe == 'RRI2' else d1
        return ['%s dr = r_orbit(psi + dphi) - r_orbit(psi) - ds s/r: max |measured - pred| %.3f mm; %s'
                % (probe, err, sample),
                'the other probe changes by at most %.2g mm' % max([abs(v) for v in other.values()] or [0])]
    return f
PO = [(po_probe, po_dphi, 0.0), (po_probe, 0.5, 0.0), ('RRL', 0.0, 1.0), ('RRI2', po_dphi, 0.0), ('RRI2', 0.0, 1.0)]
for probe, dphi, ds in PO:
    e = dict(type='probe-offset', probe=probe)
    if dphi: e['dphi_deg'] = dphi
    if ds: e['ds_mm'] = ds
    res = report('probe-offset', '%s dphi %g deg, ds %g mm' % (probe, dphi, ds), run(with_effects([e])),
                 pred=po_pred(probe, dphi, ds))
    if dphi and not ds:
        idx = [p['name'] for p in base_machine['probes']].index(probe)
        same = run(base_m, extra=['--set', '/probes/%d/phi_deg=%r' % (idx, base_machine['probes'][idx]['phi_deg'] + dphi)])
        dd = diff(res, same, probe)
        print('   CHECK same as phi_deg %+g: max |difference| %.2g mm' % (dphi, max(abs(v) for v in dd.values())))

# ---- injection-offset -------------------------------------------------------------------
def io_pred(dr, dpr):
    def f(res, ref, d1, d2):
        E0 = ref['E'][0]; R0 = ravg(E0); n0 = nu_r(E0)
        A0 = math.hypot(dr, R0 / n0 * dpr / 1000)
        E1 = ref['probes']['RRL'][182]['E']
        A1 = A0 * math.sqrt(n0 * gamma(E0) / (nu_r(E1) * gamma(E1)))
        late = [abs(d2[n]) for n in d2 if n >= 160]
        mid = [abs(d2[n]) for n in d2 if 50 <= n <= 70]
        return ['betatron amplitude at injection hypot(dr, R/nu dpr) = %.3f mm (R %.0f mm, nu_r %.3f); '
                'RRI2 measured range %+.3f..%+.3f' % (A0, R0, n0, min(d1.values()), max(d1.values())),
                'adiabatic damping A ~ 1/sqrt(nu_r gamma): %.3f mm at turn 182; RRL measured max|dr| turns 50-70 '
                '%.3f, turns 160-182 %.3f mm' % (A1, max(mid), max(late))]
    return f
for dr, dpr in ((2.0, 0.0), (0.5, 0.0), (0.0, 1.0), (0.0, 0.3)):
    e = dict(type='injection-offset')
    if dr: e['dr_mm'] = dr
    if dpr: e['dpr_mrad'] = dpr
    report('injection-offset', 'dr %g mm, dpr %g mrad' % (dr, dpr), run(with_effects([e])), pred=io_pred(dr, dpr))

# ---- all truth effects together -----------------------------------------------------------
if truth:
    effs = []
    for e in json.load(open(os.path.join(R8, 'params.json')))['truth']['effects']:
        effs.append({k: v for k, v in e.items() if k != 'description'})
    # the truth machine: ring8 with the truth's design variables (trim coils, voltages, ...) and
    # its effects, against the same design variables without effects
    extra = []
    if tdv:
        dvf = os.path.join(WORK, 'truth-dvars.json')
        json.dump(tdv, open(dvf, 'w'), indent=1)
        extra = ['--dvars', dvf]
    ref = run(base_m, extra=extra)
    report('truth effects together', ', '.join(e['type'] for e in effs) + ', truth dvars in both runs',
           run(with_effects(effs), extra=extra), ref=ref)

# ---- summary table ------------------------------------------------------------------------
print('\n%-26s %-58s %18s %18s %9s %9s %9s %8s' % ('effect', 'size', 'RRI2 max|dr| (t)', 'RRL max|dr| (t)',
                                               'RRL dr182', 'dE182', 'dph182', 'dN590'))
for name, size, m1, m2, d182, dE, dP, dN in rows_out:
    print('%-26s %-58s %+9.3f (t%3d) %+9.3f (t%3d) %+9.3f %+9.4f %+9.3f %+8.3f'
          % (name, size[:58], m1[0], m1[1], m2[0], m2[1], d182, dE, dP, dN))
PYEOF
