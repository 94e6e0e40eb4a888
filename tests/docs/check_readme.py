#!/usr/bin/env python3
"""Check that the output the README shows is what the programs print.

Every plain fenced block of the README (``` with no language) is preceded, on the line just
above its opening fence, by a marker comment saying what it is:

  <!-- output: group=NAME run=above show=stdout [exit=N] [timeout=S] -->
  <!-- output: group=NAME run="COMMAND" show=stdout -->
  <!-- not output: REASON -->

- run=above runs the nearest ```sh block above the marker; run="COMMAND" runs COMMAND. Either is
  run with `sh -e -c` in a sandbox folder that looks like the project seen from its root: `share`
  and `Makefile.wrap` link to the project's, `examples` is a copy (its files reach `../shared`,
  which links to --shared), `build/tools` links to --bin, and --bin is first on PATH. Blocks of
  one group run in README order in the same sandbox, so a later block sees an earlier one's files.
- show: what the block shows: stdout, stderr, output (both, merged) or file:PATH (a file the
  command wrote, relative to the sandbox). exit: the expected exit status (default 0).
- A line of the block that holds only `...` stands for any number of lines (none included);
  `...` inside a line for any text within that line. Every other line must be printed, in the
  block's order, the lines between two `...` lines consecutively. Lines are compared token by
  token (numbers and single characters; white space is not compared): text exactly, a number
  with as many decimals as the program prints and within half a unit of its last digit (the
  README's digits are the program's; -0.0000 and 0.0000 are the same number).

Every plain block must have a marker, and every group named in a marker must have its CLI case
tests/cli/cases/readme_GROUP.json: a new output block cannot be added unchecked by mistake.
`--group NAME` checks that group's blocks (the CLI cases run one group each); the marker rules are
checked on every run. Exit 0 ok, 1 a block differs from the program (a report says where), 2 the
README's markers are wrong.
"""
import argparse
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile

FENCE = re.compile(r"^```(\S*)\s*$")
MARKER = re.compile(r"^<!--\s*(output|not output):(.*?)-->\s*$")
TOKEN = re.compile(r"\.\.\.|[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|\S")
NUMBER = re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")
ELLIPSIS = "..."


class MarkerError(Exception):
    pass


def parse_readme(path):
    """The README's fenced blocks: (language, first line number, lines, marker line or None)."""
    with open(path, encoding="utf-8") as f:
        lines = f.read().split("\n")
    blocks = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start = i
        j = i + 1
        while j < len(lines) and lines[j].rstrip() != "```":
            j += 1
        if j == len(lines):
            raise MarkerError("%s:%d: a fenced block is not closed" % (path, start + 1))
        marker = lines[start - 1] if start > 0 and MARKER.match(lines[start - 1]) else None
        blocks.append({"lang": m.group(1), "line": start + 1, "body": lines[start + 1:j],
                       "marker": marker})
        i = j + 1
    return blocks


def parse_marker(path, block, previous_sh):
    kind, rest = MARKER.match(block["marker"]).groups()
    where = "%s:%d" % (path, block["line"] - 1)
    if kind == "not output":
        if not rest.strip():
            raise MarkerError("%s: 'not output:' needs a reason" % where)
        return None
    fields = {}
    for item in shlex.split(rest):
        key, eq, value = item.partition("=")
        if not eq or key not in ("group", "run", "show", "exit", "timeout"):
            raise MarkerError("%s: unknown marker field %r (group, run, show, exit, timeout)" % (where, item))
        fields[key] = value
    for key in ("group", "run", "show"):
        if key not in fields:
            raise MarkerError("%s: the marker needs %s=" % (where, key))
    if not re.match(r"^[a-z0-9_]+$", fields["group"]):
        raise MarkerError("%s: group %r: lower-case letters, digits, _" % (where, fields["group"]))
    if fields["run"] == "above":
        if previous_sh is None:
            raise MarkerError("%s: run=above but no ```sh block above" % where)
        command = "\n".join(previous_sh["body"])
        source = "the ```sh block at line %d" % previous_sh["line"]
    else:
        command = fields["run"]
        source = "the marker's command"
    show = fields["show"]
    if show not in ("stdout", "stderr", "output") and not show.startswith("file:"):
        raise MarkerError("%s: show=%s: stdout, stderr, output or file:PATH" % (where, show))
    try:
        exit_code = int(fields.get("exit", "0"))
        # TURNFIT_TIMEOUT_SCALE multiplies the hang guard (the sanitizer build runs slower).
        timeout = float(fields.get("timeout", "120")) * float(os.environ.get("TURNFIT_TIMEOUT_SCALE", "1"))
    except ValueError as e:
        raise MarkerError("%s: %s" % (where, e))
    return {"group": fields["group"], "command": command, "source": source, "show": show,
            "exit": exit_code, "timeout": timeout, "line": block["line"], "body": block["body"]}


def collect(path, repo):
    """The checked blocks; every plain block must say what it is."""
    checked = []
    previous_sh = None
    for block in parse_readme(path):
        if block["lang"] == "sh":
            previous_sh = block
            continue
        if block["lang"]:
            continue  # json and other languages are inputs, not output
        if block["marker"] is None:
            raise MarkerError("%s:%d: a plain block without a marker on the line above: say what it "
                              "shows (<!-- output: group=... run=... show=... --> or "
                              "<!-- not output: REASON -->)" % (path, block["line"]))
        spec = parse_marker(path, block, previous_sh)
        if spec is not None:
            checked.append(spec)
    for group in sorted({s["group"] for s in checked}):
        case = os.path.join(repo, "tests", "cli", "cases", "readme_%s.json" % group)
        if not os.path.isfile(case):
            raise MarkerError("%s: group %s has no CLI case %s" % (path, group, case))
    return checked


# --- comparison ----------------------------------------------------------------------------------

def tokens(line):
    return TOKEN.findall(line)


def decimals(number):
    mantissa, _, exponent = number.lower().partition("e")
    return (len(mantissa.split(".")[1]) if "." in mantissa else 0), int(exponent or 0)


def token_equal(shown, printed):
    """Text exactly; a number printed with the same digits, and equal to within half a unit of
    its last digit (so -0.0000 is 0.0000, and 1.5e+06 is 1.5e+006)."""
    if NUMBER.match(shown) and NUMBER.match(printed):
        (places, exponent), (printed_places, _) = decimals(shown), decimals(printed)
        if places != printed_places:
            return False
        half_unit = 0.5 * 10.0 ** (exponent - places)
        return abs(float(shown) - float(printed)) <= half_unit * (1 + 1e-9)
    return shown == printed


def line_matches(shown, printed):
    """Token lists; '...' in shown matches any run of tokens (within the line)."""
    n, m = len(shown), len(printed)
    # reach[j]: shown[:i] can match printed[:j]
    reach = [True] + [False] * m
    for i in range(n):
        if shown[i] == ELLIPSIS:
            nxt = reach[:]
            for j in range(1, m + 1):
                nxt[j] = nxt[j] or nxt[j - 1]
        else:
            nxt = [False] * (m + 1)
            for j in range(1, m + 1):
                nxt[j] = reach[j - 1] and token_equal(shown[i], printed[j - 1])
        reach = nxt
    return reach[m]


def segments(body, first_line):
    """The block split at its '...' lines: lists of (README line number, text)."""
    out, cur = [], []
    for k, text in enumerate(body):
        if tokens(text) == [ELLIPSIS]:
            if cur:
                out.append(cur)
            cur = []
        else:
            cur.append((first_line + 1 + k, text))
    if cur:
        out.append(cur)
    return out


def compare(spec, printed_text, readme):
    """None when the block is what was printed, else a report."""
    printed = printed_text.split("\n")
    if printed and printed[-1] == "":
        printed.pop()
    ptoks = [tokens(p) for p in printed]
    pos = 0
    for seg in segments(spec["body"], spec["line"]):
        stoks = [tokens(text) for _, text in seg]
        found = None
        best = (-1, None)  # the start that matches most of the segment's lines, for the report
        for start in range(pos, len(printed) - len(seg) + 1):
            k = 0
            while k < len(seg) and line_matches(stoks[k], ptoks[start + k]):
                k += 1
            if k == len(seg):
                found = start
                break
            if k > best[0] or (k == best[0] and best[1] is None):
                best = (k, start)
        if found is None:
            k, start = best
            report = ["%s:%d: not printed (after output line %d)" % (readme, seg[0][0], pos)]
            if start is not None and k > 0:
                report.append("  the closest place matches %d of %d lines from output line %d; then"
                              % (k, len(seg), start + 1))
                report.append("  README %d: %s" % (seg[k][0], seg[k][1]))
                report.append("  printed %d: %s" % (start + k + 1, printed[start + k]))
            else:
                for line_no, text in seg[:3]:
                    report.append("  README %d: %s" % (line_no, text))
                # the printed line that agrees longest with the first one shown, from its start
                def agree(p):
                    n = 0
                    while n < min(len(p), len(stoks[0])) and token_equal(stoks[0][n], p[n]):
                        n += 1
                    return n
                near = max(range(pos, len(printed)), key=lambda j: agree(ptoks[j]), default=None)
                if near is not None and agree(ptoks[near]) > 0:
                    report.append("  nearest printed %d: %s" % (near + 1, printed[near]))
            return "\n".join(report)
        pos = found + len(seg)
    return None


# --- running -------------------------------------------------------------------------------------

def make_sandbox(root, repo, bin_dir, shared):
    work = os.path.join(root, "repo")
    os.makedirs(os.path.join(work, "build"))
    os.symlink(os.path.join(repo, "share"), os.path.join(work, "share"))
    os.symlink(os.path.join(repo, "Makefile.wrap"), os.path.join(work, "Makefile.wrap"))
    shutil.copytree(os.path.join(repo, "examples"), os.path.join(work, "examples"))
    os.symlink(bin_dir, os.path.join(work, "build", "tools"))
    if shared:
        os.symlink(shared, os.path.join(root, "shared"))
    return work


def run_block(spec, work, env):
    merged = spec["show"] == "output"
    # A session of its own, so a timeout stops the whole command (make and the tools it runs),
    # not only its shell: an orphaned diagnosis once ran on for 20 minutes after its test.
    p = subprocess.Popen(["sh", "-e", "-c", spec["command"]], cwd=work, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT if merged else subprocess.PIPE, start_new_session=True)
    try:
        out, err = p.communicate(timeout=spec["timeout"])
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        return None, "timed out after %g s" % spec["timeout"]
    out = out.decode("utf-8", "replace")
    err = "" if merged else err.decode("utf-8", "replace")
    problems = []
    if p.returncode != spec["exit"]:
        problems.append("exit %d, README says %d" % (p.returncode, spec["exit"]))
    show = spec["show"]
    if show in ("stdout", "output"):
        text = out
    elif show == "stderr":
        text = err
    else:
        path = os.path.join(work, show[len("file:"):])
        try:
            with open(path, encoding="utf-8") as f:
                text = f.read()
        except OSError as e:
            problems.append("cannot read %s: %s" % (show, e))
            text = None
    if problems:
        tail = (out + err).strip().split("\n")[-15:]
        return None, "; ".join(problems) + "\n  last lines printed:\n    " + "\n    ".join(tail)
    return text, None


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repo", required=True, help="the project's root")
    ap.add_argument("--readme", help="default: REPO/README.md")
    ap.add_argument("--bin", required=True, help="the built tools (build/tools)")
    ap.add_argument("--shared", help="the shared data folder (../shared)")
    ap.add_argument("--group", help="check this group's blocks (default: only the markers)")
    ap.add_argument("--work", help="folder for the sandbox (default: a temporary one)")
    args = ap.parse_args()
    repo = os.path.abspath(args.repo)
    readme = args.readme or os.path.join(repo, "README.md")
    try:
        checked = collect(readme, repo)
    except MarkerError as e:
        print("check_readme: %s" % e, file=sys.stderr)
        return 2
    print("README: %d checked output blocks in groups %s" %
          (len(checked), ", ".join(sorted({s["group"] for s in checked}))))
    if not args.group:
        return 0
    mine = [s for s in checked if s["group"] == args.group]
    if not mine:
        print("check_readme: no block in group %r" % args.group, file=sys.stderr)
        return 2
    root = tempfile.mkdtemp(prefix="readme-", dir=args.work)
    try:
        work = make_sandbox(root, repo, os.path.abspath(args.bin),
                            os.path.abspath(args.shared) if args.shared else None)
        env = dict(os.environ)
        # A make above us (make test -> ctest -> here) passes its flags and overrides through
        # MAKEFLAGS, and Makefile.wrap's ?= variables take the environment's: the README's
        # commands run as a user's shell would run them.
        for name in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES", "BUILD", "PREFIX", "JOBS",
                     "SHARED", "CMAKE_ARGS", "DESTDIR"):
            env.pop(name, None)
        env["PATH"] = os.path.abspath(args.bin) + os.pathsep + env.get("PATH", "")
        env["LC_ALL"] = "C"
        failed = 0
        for spec in mine:
            what = "README:%d (%s, %s)" % (spec["line"], spec["source"], spec["show"])
            text, problem = run_block(spec, work, env)
            if problem is None:
                problem = compare(spec, text, readme)
            if problem is None:
                shown = sum(1 for t in spec["body"] if tokens(t) != [ELLIPSIS])
                print("ok   %s: %d lines as printed" % (what, shown))
            else:
                failed += 1
                print("FAIL %s: %s" % (what, problem))
        return 1 if failed else 0
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
