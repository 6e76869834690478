#!/usr/bin/env bash
# Runs one libFuzzer harness of this folder. Used by ctest (-L fuzz) and tools/fuzz.
# Usage: run_fuzz.sh MODE HARNESS_BINARY NAME SECONDS WORK_DIR
#   ci        replays corpus/NAME/ and every file in tests/data/bad/ (each input whole, as a
#             test), then fuzzes from a fresh copy of corpus/NAME/ in WORK_DIR/corpus with a
#             fixed seed for a fixed number of executions (about SECONDS); exits 1 on the first
#             finding.
#   campaign  fuzzes SECONDS from WORK_DIR/corpus (kept between campaigns; the committed seeds
#             are copied in, the committed corpus is never written), continuing after findings
#             (libFuzzer fork mode), and prints executions, coverage and findings.
# Findings (crash-*, leak-*, timeout-*, oom-*) go to WORK_DIR/crashes/. Every one becomes a file in
# tests/data/bad/ (once the bug is fixed) so the CLI error test and this replay keep it fixed.
set -uo pipefail
mode="${1:?usage: run_fuzz.sh ci|campaign HARNESS NAME SECONDS WORK_DIR}"
bin="$2" name="$3" seconds="$4" work="$5"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
seeds="$here/corpus/$name"
[ -x "$bin" ] && [ -d "$seeds" ] || { echo "run_fuzz: no harness $bin or corpus $seeds" >&2; exit 2; }

# Longest input to generate: room for the seeds and deep nesting, small enough to stay fast.
case "$name" in
  fuzz_set) max_len=1024 ;;
  fuzz_optimizer_config) max_len=16384 ;;
  *) max_len=65536 ;;
esac
# Sanitizer settings (appended: they win over inherited ones). Only fuzz_image reads PNGs that can
# hit the known OpenImageIO leak, whose suppression (tests/lsan.supp) needs the slow unwinder to see
# through OpenImageIO's missing frame pointers; it costs the other harnesses 5x their speed.
unwind=1
[ "$name" = fuzz_image ] && unwind=0
export ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_leaks=1:fast_unwind_on_malloc=$unwind"
export LSAN_OPTIONS="${LSAN_OPTIONS:+$LSAN_OPTIONS:}suppressions=$repo/tests/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:+$UBSAN_OPTIONS:}print_stacktrace=1:halt_on_error=1"
mkdir -p "$work/crashes" "$work/corpus"
# -timeout: a load taking 10 s is a hang. -rss_limit_mb also caps single allocations
# (malloc_limit_mb defaults to it): a loader allocating 2 GB for a small file is a finding.
opts=(-timeout=10 -rss_limit_mb=2048 -artifact_prefix="$work/crashes/" -print_final_stats=1)
fuzz_opts=(-max_len="$max_len" -dict="$here/$name.dict" -max_total_time="$seconds")
# The CI gate is reproducible: a fixed seed and a fixed number of executions (about SECONDS on
# this project's 2-core machines), so a green local run of a commit is a green CI run of it.
# Random exploration is the campaigns' job (tools/fuzz, a time-based seed; findings become files
# in tests/data/bad/). The wall-clock cap (3 x SECONDS) only bounds a slow machine: it then runs
# a prefix of the same sequence. BACKLIGHT_FUZZ_SEED picks another sequence.
case "$name" in
  fuzz_image) rate=600 ;;
  fuzz_vdb) rate=7 ;;
  fuzz_gltf | fuzz_scene_json | fuzz_xml) rate=4000 ;;
  fuzz_optimizer_config) rate=6000 ;;
  *) rate=20000 ;;
esac
ci_opts=(-max_len="$max_len" -dict="$here/$name.dict" -seed="${BACKLIGHT_FUZZ_SEED:-20261124}"
         -runs=$((seconds * rate)) -max_total_time=$((seconds * 3)))
log="$work/fuzz.log"

summary() {  # executions, rate, coverage and findings from the libFuzzer log
  local execs rate cov findings
  execs="$(grep -aoE 'stat::number_of_executed_units: [0-9]+' "$log" | awk '{ s += $2 } END { print s + 0 }')"
  if [ "$execs" -eq 0 ]; then  # fork mode: the last status line carries the total
    execs="$(grep -aoE '#[0-9]+: cov' "$log" | tail -1 | grep -oE '[0-9]+')"
  fi
  local elapsed=$((SECONDS - start))
  rate=$(( ${execs:-0} / (elapsed > 0 ? elapsed : 1) ))
  cov="$(grep -aoE 'cov: [0-9]+' "$log" | tail -1 | grep -oE '[0-9]+$')"
  findings="$(find "$work/crashes" -type f | wc -l)"
  echo "$name: ${execs:-0} executions in $elapsed s ($rate exec/s), coverage ${cov:-?} edges," \
       "corpus $(find "$work/corpus" -type f | wc -l) files, $findings finding(s) in $work/crashes/"
  find "$work/crashes" -type f | sed 's/^/  /'
}

if [ "$mode" = ci ]; then
  rm -rf "$work/crashes" "$work/corpus"
  mkdir -p "$work/crashes" "$work/corpus"
  # 1. Replay: files given one by one are run whole (no -max_len truncation), once each.
  mapfile -t replay < <(find "$seeds" "$repo/tests/data/bad" -type f 2>/dev/null | sort)
  echo "$name: replaying ${#replay[@]} files (corpus/$name and tests/data/bad)"
  if ! "$bin" "${opts[@]}" "${replay[@]}" >"$work/replay.log" 2>&1; then
    grep -a -E "Running:|ERROR|SUMMARY|what\(\)|==[0-9]+==" "$work/replay.log" | tail -20
    echo "$name: an input above crashed the harness (full log: $work/replay.log)"; exit 1
  fi
  # 2. Fuzz from the seeds; new inputs go to the work copy (the first directory), never the tree.
  start=$SECONDS
  "$bin" "${opts[@]}" "${ci_opts[@]}" "$work/corpus" "$seeds" >"$log" 2>&1
  rc=$?
  summary
  if [ "$rc" -ne 0 ]; then
    grep -a -B2 -A30 -m1 -E "ERROR|deadly signal|Timeout|out-of-memory" "$log" | head -60
    echo "$name: FINDING (exit $rc); reproduce: $bin <file from $work/crashes/>; log: $log"; exit 1
  fi
  exit 0
fi

[ "$mode" = campaign ] || { echo "run_fuzz: unknown mode $mode" >&2; exit 2; }
cp -n "$seeds"/* "$work/corpus/" 2>/dev/null
before="$(find "$work/crashes" -type f | wc -l)"
start=$SECONDS
echo "$name: fuzzing for $seconds s; corpus $work/corpus, findings $work/crashes, log $log"
"$bin" "${opts[@]}" "${fuzz_opts[@]}" -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
  "$work/corpus" >"$log" 2>&1
summary
new=$(( $(find "$work/crashes" -type f | wc -l) - before ))
echo "$name: $new new finding(s) in this campaign"
[ "$new" -eq 0 ]
