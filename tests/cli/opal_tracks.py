#!/usr/bin/env python3
"""turnfit-import-opal against the hand-written example: cyclotron2.in imported from ../shared
tracks to the turns of examples/psi-ring/aeo.json (default physics) within 1e-6 mm.

Two readings of the input (physics.md, OPAL 2022.1's trim coil window):
  - as shipped, PHIMIN/PHIMAX unset: OPAL 2022.1 applies tc1 nowhere, so the import carries
    it with bmax_T 0; compared with aeo.json with TC15 at bmax_T 0;
  - with PHIMIN = 0, PHIMAX = 360 added (the window of OPAL's anchor run): compared with
    aeo.json as shipped.
The imported machines get aeo.json's probes (cyclotron2.in has none). Both shipped inputs must
import under --strict (no line left unexplained). Exit 0 ok, 1 a difference, 77 no shared data.
Usage: opal_tracks.py BIN SHARED WORK
"""
import csv, json, os, subprocess, sys

# Also: turnfit-export-opal's output of ring8 and of aeo.json imports back and tracks to the same
# turns (exactly, with the annotation; without it, from OPAL's commands alone, within 1e-6 mm
# for aeo.json and within the OPAL map copy's 9 digits for ring8: its map goes to OPAL as a RING copy with 9 digits, 3e-6 mm at most).

bin_dir, shared, work = sys.argv[1:4]
psi = os.path.join(shared, "data", "psi-ring")
if not os.path.exists(os.path.join(psi, "cyclotron2.in")):
    if os.environ.get("CI") == "true":
        sys.exit("shared data missing under CI")
    print("skipped: no shared data at " + psi)
    sys.exit(77)
here = os.path.dirname(os.path.abspath(__file__))
aeo_path = os.path.join(here, "..", "..", "examples", "psi-ring", "aeo.json")
tool = lambda t: os.path.join(bin_dir, "turnfit-" + t)


def run(args, **kw):
    r = subprocess.run(args, capture_output=True, text=True, **kw)
    if r.returncode != 0:
        sys.exit("FAILED %s: exit %d\n%s" % (" ".join(args), r.returncode, r.stderr))
    return r


# The shipped inputs under --strict, from their own folder.
for name in ("cyclotron2.in", "cyclotronTune-2-1.in"):
    r = run([tool("import-opal"), "--strict", os.path.join(psi, name), "-o", os.path.join(work, name + ".json")])
    if "warning:" in r.stderr:
        sys.exit("FAILED: %s has unexplained lines:\n%s" % (name, r.stderr))
    print("ok   %s imports under --strict (%d lines explained)" % (name, r.stderr.count("note:")))

# The variant with the full-circle window, in a folder with the data files beside it.
for f in ("bfield.dat", "rffield1.dat", "rffield2.dat", "dist2.dat"):
    os.symlink(os.path.join(psi, f), os.path.join(work, f))
text = open(os.path.join(psi, "cyclotron2.in")).read()
coil = "BMAX=1.4e-3, SLPTC=0.6;"
assert text.count(coil) == 2
text = text.replace(coil, "BMAX=1.4e-3, SLPTC=0.6, PHIMIN=0, PHIMAX=360;")
open(os.path.join(work, "full.in"), "w").write(text)
run([tool("import-opal"), "-q", os.path.join(work, "full.in"), "-o", os.path.join(work, "full.json")])

aeo = json.load(open(aeo_path))
aeo_dir = os.path.dirname(os.path.abspath(aeo_path))
def absolute(m, d):
    m["field"]["map"] = os.path.normpath(os.path.join(d, m["field"]["map"]))
    for c in m.get("cavities", []):
        c["profile"] = os.path.normpath(os.path.join(d, c["profile"]))
    return m
aeo = absolute(aeo, aeo_dir)
off = json.loads(json.dumps(aeo))
off["trimcoils"][0]["bmax_T"] = 0.0


def turns(machine, name):
    path = os.path.join(work, name)
    json.dump(machine, open(path, "w"))
    r = run([tool("track"), path, "--no-provenance", "--kicks", path + ".kicks.csv"])
    rows = [row for row in csv.DictReader(l for l in r.stdout.splitlines() if not l.startswith("#"))]
    kicks = [row for row in csv.DictReader(l for l in open(path + ".kicks.csv") if not l.startswith("#"))]
    return rows, kicks


worst = 0.0
for imported, reference, what in (("cyclotron2.in.json", off, "as shipped (tc1 acts nowhere in 2022.1)"),
                                  ("full.json", aeo, "PHIMIN = 0, PHIMAX = 360")):
    m = absolute(json.load(open(os.path.join(work, imported))), work)
    m["probes"] = aeo["probes"]
    a, ka = turns(m, "imp-" + imported)
    b, kb = turns(reference, "ref-" + imported)
    if len(a) != len(b) or len(a) != 388 or len(ka) != len(kb):
        sys.exit("FAILED %s: %d/%d turn rows, %d/%d kicks" % (what, len(a), len(b), len(ka), len(kb)))
    d = 0.0
    for x, y in zip(a, b):
        if (x["probe"], x["turn"]) != (y["probe"], y["turn"]):
            sys.exit("FAILED %s: rows differ: %s %s" % (what, x, y))
        d = max(d, abs(float(x["r_mm"]) - float(y["r_mm"])))
    de = max(abs(float(x["energy_MeV"]) - float(y["energy_MeV"])) for x, y in zip(a, b))
    worst = max(worst, d)
    print("ok   cyclotron2.in %s: %d crossings, %d kicks, largest radius difference %.1e mm, energy %.1e MeV"
          % (what, len(a), len(ka), d, de))
    if d > 1e-6:
        sys.exit("FAILED: %s differs from aeo.json by %.3g mm (> 1e-6 mm)" % (what, d))
print("ok   worst difference %.1e mm" % worst)

ring8_path = os.path.join(here, "..", "..", "share", "turnfit", "ring8", "machine.json")
for src, label in ((aeo_path, "aeo"), (ring8_path, "ring8")):
    d = os.path.join(work, "export-" + label)
    os.mkdir(d)
    args = [tool("export-opal"), "-q", src, "-o", os.path.join(d, "m.in"), "--dist-out", os.path.join(d, "dist1.dat")]
    if label == "ring8":
        args += ["--map-out", os.path.join(d, "map.dat")]
    run(args)
    text = open(os.path.join(d, "m.in")).read()
    open(os.path.join(d, "bare.in"), "w").write("".join(l for l in text.splitlines(True) if not l.startswith("//turnfit|")))
    run([tool("import-opal"), "-q", "--strict", os.path.join(d, "m.in"), "-o", os.path.join(d, "back.json")])
    run([tool("import-opal"), "-q", "--strict", os.path.join(d, "bare.in"), "-o", os.path.join(d, "bare.json")])
    def track(path):
        r = run([tool("track"), path, "--no-provenance"])
        return [row for row in csv.DictReader(l for l in r.stdout.splitlines() if not l.startswith("#"))]
    ref = track(src)
    for which, limit in (("back.json", 0.0), ("bare.json", 1e-6 if label == "aeo" else 1e-5)):
        got = track(os.path.join(d, which))
        if [(x["probe"], x["turn"]) for x in got] != [(x["probe"], x["turn"]) for x in ref]:
            sys.exit("FAILED %s %s: other crossings than the original's" % (label, which))
        diff = max(abs(float(x["r_mm"]) - float(y["r_mm"])) for x, y in zip(got, ref))
        print("ok   %s exported and imported back (%s): %d crossings, largest radius difference %.1e mm"
              % (label, "with the annotation" if which == "back.json" else "OPAL's commands alone", len(got), diff))
        if diff > limit:
            sys.exit("FAILED: %s %s differs by %.3g mm (> %g)" % (label, which, diff, limit))
