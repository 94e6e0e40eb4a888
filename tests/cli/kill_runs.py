#!/usr/bin/env python3
"""Hard stops (issue 18): runs a command to its end, then again several times, each stopped by a
signal at a random moment, and checks what a stop may leave behind.

    kill_runs.py --signal KILL|INT|TERM --times N --seed S --outputs PATH... -- COMMAND ARG...

The first run is the reference: it must exit 0, and its outputs are the "earlier outputs". Each
later run is sent the signal after a delay drawn uniformly from 5-95 % of the reference's
duration (seeded: the same moments every time). After each:
  - the run ended by the signal (or finished first, exit 0);
  - every output is byte for byte the reference's: an earlier output is never replaced by a
    partial one (the command is deterministic, so a finished one is the same again);
  - INT and TERM leave no temporary (*.tmp.* beside an output, turnfit's atomic writer); KILL
    cannot clean up, so its temporaries are counted and removed.
At least one run must have been ended by the signal. One line per run on stdout, then "all N
stopped runs left the outputs intact". Exit 1 on a failure.
"""
import argparse
import glob
import os
import random
import signal
import subprocess
import sys
import time


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--signal", required=True, choices=["KILL", "INT", "TERM"])
    ap.add_argument("--times", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--outputs", nargs="+", required=True)
    ap.add_argument("command", nargs=argparse.REMAINDER)
    a = ap.parse_args()
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    sig = getattr(signal, "SIG" + a.signal)

    t0 = time.monotonic()
    ref = subprocess.run(cmd, stdout=subprocess.DEVNULL)
    took = time.monotonic() - t0
    if ref.returncode != 0:
        sys.exit("kill_runs: the reference run failed (exit %d): %s" % (ref.returncode, " ".join(cmd)))
    want = {}
    for out in a.outputs:
        if not os.path.isfile(out):
            sys.exit("kill_runs: the reference run wrote no %s" % out)
        want[out] = open(out, "rb").read()

    def temporaries():
        found = set()
        for out in a.outputs:
            found.update(glob.glob(os.path.join(os.path.dirname(out) or ".", "*.tmp.*")))
        return sorted(found)

    rng = random.Random(a.seed)
    failed = False
    stopped = 0
    for i in range(1, a.times + 1):
        delay = rng.uniform(0.05, 0.95) * took
        # Its own session: the shell's job control does not ignore INT for it, and it is the
        # only process the signal goes to (as a user's kill or a queue's would).
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, start_new_session=True)
        time.sleep(delay)
        p.send_signal(sig)
        rc = p.wait()
        how = "finished first" if rc == 0 else "stopped" if rc == -sig else "exit %d" % rc
        problems = []
        if rc not in (0, -sig):
            problems.append("ended by %s, not by SIG%s" % ("exit %d" % rc if rc >= 0 else "signal %d" % -rc, a.signal))
        for out, data in want.items():
            if not os.path.isfile(out):
                problems.append("%s is gone" % out)
            elif open(out, "rb").read() != data:
                problems.append("%s differs from the earlier output (%d bytes now)" % (out, os.path.getsize(out)))
        left = temporaries()
        if left and a.signal != "KILL":
            problems.append("temporaries left: %s" % ", ".join(os.path.basename(t) for t in left))
        for t in left:
            os.remove(t)
        print("run %d: SIG%s at %.2f s of %.2f: %s; outputs %s; temporaries left %d%s"
              % (i, a.signal, delay, took, how, "intact" if not problems else "NOT intact", len(left),
                 "" if not problems else " (" + "; ".join(problems) + ")"))
        failed = failed or bool(problems)
        stopped += rc == -sig
    # A run that always finishes first tests nothing (a handler that never re-raises, a signal
    # inherited as ignored, a command too quick for its moments).
    if not stopped:
        print("none of the %d runs was ended by SIG%s" % (a.times, a.signal))
        failed = True
    if failed:
        sys.exit(1)
    print("all %d stopped runs left the outputs intact" % a.times)


if __name__ == "__main__":
    main()
