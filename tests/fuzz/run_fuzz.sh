#!/usr/bin/env bash
# Runs every libFuzzer target of a TURNFIT_FUZZ build for SECONDS each (make -f Makefile.wrap fuzz).
#   tests/fuzz/run_fuzz.sh BUILD_DIR SECONDS [FORMAT ...]
# Each target starts from its seeds (seeds.txt) and its regression inputs (files over 64 kB of
# either are replayed by the suite but left out here: they would slow every execution), and keeps what it
# finds in BUILD_DIR/fuzz-corpus/FORMAT. A crash, leak, timeout (10 s) or memory blow-up
# (2 GB) leaves its input in BUILD_DIR/fuzz-artifacts/FORMAT/ and fails the run: make it a
# fixed bug and a file under tests/fuzz/regressions/FORMAT/. A line per target goes to stdout:
# executions, seconds, corpus size, and what was found.
set -uo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
build="$(cd "${1:?usage: run_fuzz.sh BUILD_DIR SECONDS [FORMAT ...]}" && pwd)"
seconds="${2:?usage: run_fuzz.sh BUILD_DIR SECONDS [FORMAT ...]}"
shift 2
shared="${SHARED:-$root/../shared}"
formats=("$@")
if [ ${#formats[@]} -eq 0 ]; then
  for exe in "$build"/tests/fuzz/fuzz_*; do
    [ -x "$exe" ] && formats+=("$(basename "$exe" | sed 's/^fuzz_//')")
  done
fi
[ ${#formats[@]} -gt 0 ] || { echo "run_fuzz: no fuzz targets in $build/tests/fuzz (configure with -DTURNFIT_FUZZ=ON)" >&2; exit 2; }

failed=0
printf '%-16s %10s %8s %8s  %s\n' format executions seconds corpus found
for f in "${formats[@]}"; do
  exe="$build/tests/fuzz/fuzz_$f"
  [ -x "$exe" ] || { echo "run_fuzz: $exe missing" >&2; failed=1; continue; }
  corpus="$build/fuzz-corpus/$f" artifacts="$build/fuzz-artifacts/$f"
  mkdir -p "$corpus" "$artifacts"
  while read -r fmt path; do
    [ "$fmt" = "$f" ] || continue
    path="${path/\$SHARED/$shared}"
    case "$path" in /*) ;; *) path="$root/$path" ;; esac
    [ -f "$path" ] && [ "$(stat -c %s "$path")" -le 65536 ] && cp "$path" "$corpus/seed-$(basename "$path")"
  done < <(grep -E '^[a-z_]+ ' "$here/seeds.txt")
  for path in "$here/regressions/$f"/*; do  # the same 64 kB cap: the suite replays the larger ones
    [ -f "$path" ] && [ "$(stat -c %s "$path")" -le 65536 ] && cp "$path" "$corpus/"
  done
  log="$build/fuzz-artifacts/$f.log"
  start=$(date +%s)
  "$exe" "$corpus" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2560 -malloc_limit_mb=2048 \
         -max_len=65536 -artifact_prefix="$artifacts/" -print_final_stats=1 > "$log" 2>&1
  rc=$?
  took=$(( $(date +%s) - start ))
  execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
  found="nothing"
  if [ $rc -ne 0 ]; then
    failed=1
    found="$(grep -m1 -oE 'ERROR: (libFuzzer|AddressSanitizer|LeakSanitizer|UndefinedBehaviorSanitizer).*|runtime error: .*|BUG: .*' "$log" | head -1) (exit $rc; $log; inputs in $artifacts)"
  fi
  printf '%-16s %10s %8s %8s  %s\n' "$f" "${execs:-?}" "$took" "$(ls "$corpus" | wc -l)" "$found"
done
exit $failed
