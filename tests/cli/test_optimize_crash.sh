#!/usr/bin/env bash
# backlight optimize is crash-safe: a process killed anywhere (kill -9, or at each step of the
# checkpoint swap through the BACKLIGHT_CRASH_AT fault-injection points) leaves a checkpoint that
# --resume finishes from, and the finished run's parameters are bitwise those of a run that was
# never interrupted (one thread: the sums are then in a fixed order). Stale temporaries of
# killed processes are removed when a run starts. Usage: test_optimize_crash.sh BACKLIGHT_BIN
set -u
bin="$1"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
cd "$dir"
fail() { echo "FAIL: $*"; exit 1; }
. "$here/floor_scene.sh"
write_floor_scene 16
iterations=16
job() {  # job OUTPUT_DIR > config
  cat <<JSON
{"scene": "scene.json", "output": "$1",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 8}},
 "spp": 8, "iterations": $iterations, "checkpoint_every": 2, "snapshot_every": 4}
JSON
}
job ref > ref.json
job out > out.json
"$bin" optimize ref.json --threads 1 --quiet 2> ref.log || fail "uninterrupted run failed: $(cat ref.log)"

# resume_until_done: resumes (or starts) until summary.json exists; at most 20 attempts.
run_once() {  # run_once [ENV...]: one start or resume of the interrupted job
  local args=(optimize out.json --threads 1 --quiet)
  [ -f out/checkpoint/state.json ] || [ -f out/checkpoint.old/state.json ] && args+=(--resume out)
  # In the background (RUN_EXEC=1) the subshell becomes backlight, so that kill -9 $! reaches it
  # (killing the subshell alone left backlight running beside the next run).
  ${RUN_EXEC:+exec} env "$@" "$bin" "${args[@]}" 2>> out.log
}
# 1. Crash at every point of the checkpoint swap, in turn, each on a later checkpoint.
for point in checkpoint-written old-removed final-moved tmp-renamed checkpoint-written final-moved \
             checkpoint-written tmp-renamed; do
  had=0
  [ -f out/checkpoint/state.json ] || [ -f out/checkpoint.old/state.json ] && had=1
  run_once BACKLIGHT_CRASH_AT=$point
  code=$?
  [ $code -eq 137 ] || fail "crash at $point: exit $code, expected the injected 137 ($(tail -n 2 out.log))"
  [ $had -eq 0 ] || [ -f out/checkpoint/state.json ] || [ -f out/checkpoint.old/state.json ] ||
    fail "after a crash at $point no complete checkpoint is left: $(ls out)"
done
still_running() {  # whether a backlight process of this job is alive (no procps needed)
  local f
  for f in /proc/[0-9]*/cmdline; do
    tr '\0' ' ' < "$f" 2> /dev/null | grep -qF "$bin optimize out.json" && return 0
  done
  return 1
}
# 2. Plain kill -9 at arbitrary moments, with temporaries of dead processes planted.
for delay in 0.3 0.7 0.5; do
  mkdir -p out/snapshots
  : > out/.loss.tmp999999.csv
  : > out/snapshots/.floor.albedo_00004.tmp999998.png
  RUN_EXEC=1 run_once & pid=$!
  sleep "$delay"
  kill -9 $pid 2>/dev/null
  wait $pid 2>/dev/null
  still_running && fail "a killed optimize is still running"
done
# One run to the end whatever state the kills left (a resume of a finished run finishes at once;
# a kill may have come before a run reached its clean-up), then more if a kill left it unfinished.
run_once || true
for _ in $(seq 1 20); do
  [ -f out/summary.json ] && break
  run_once || true
done
[ -f out/summary.json ] || fail "the run did not finish after repeated resumes: $(tail -n 3 out.log)"
cmp -s ref/checkpoint/floor.albedo.value out/checkpoint/floor.albedo.value ||
  fail "resumed parameters differ from the uninterrupted run's"
rows=$(($(wc -l < out/loss.csv) - 1))
[ "$rows" -eq $iterations ] || fail "loss.csv has $rows rows, expected $iterations"
stale=$(find out -name '.*.tmp*')
[ -z "$stale" ] || fail "temporaries left behind: $stale"
[ ! -e out/checkpoint.tmp ] && [ ! -e out/checkpoint.old ] || fail "checkpoint.tmp/.old left behind: $(ls out)"
# 3. The target cache: a run killed between writing a target and its key left the new image beside
# the old key, and the next run of the old config took the other reference's render as its target
# (helper-45). The old key is removed before the image is replaced.
sed 's/"spp": 8}}/"spp": 9}}/' ref.json > ref9.json
grep -q '"spp": 9}}' ref9.json || fail "ref9.json: the reference spp was not changed"
cp ref/targets/top.exr top8.exr
env BACKLIGHT_CRASH_AT=target-written "$bin" optimize ref9.json --threads 1 --quiet 2>> out.log
code=$?
[ $code -eq 137 ] || fail "crash at target-written: exit $code, expected the injected 137"
cmp -s ref/targets/top.exr top8.exr && fail "the spp-9 reference did not replace the cached target"
"$bin" optimize ref.json --threads 1 --quiet 2>> out.log || fail "the spp-8 run after the crash failed"
cmp -s ref/targets/top.exr top8.exr || fail "the spp-8 run used the spp-9 target left by the crash"
# 4. A fresh start over a finished run's folder, killed at its first checkpoint: the old summary.json
# (a finished run of 16 iterations) stayed beside the new checkpoint, and a checkpoint.tmp/ of a
# killed writer stayed until the next checkpoint. Both go when a run starts.
[ -f ref/summary.json ] || fail "the finished run has no summary.json"
mkdir -p ref/checkpoint.tmp && : > ref/checkpoint.tmp/left.by.a.killed.writer
env BACKLIGHT_CRASH_AT=checkpoint-written "$bin" optimize ref.json --threads 1 --quiet 2>> out.log
code=$?
[ $code -eq 137 ] || fail "fresh start crashed at checkpoint-written: exit $code, expected the injected 137"
[ ! -e ref/summary.json ] || fail "a fresh start killed early left the previous run's summary.json"
[ ! -e ref/checkpoint.tmp/left.by.a.killed.writer ] || fail "a killed writer's checkpoint.tmp/ stayed"
# 5. A fresh start removes what the previous run in the folder wrote before its own first write: the
# old final/ stayed while the new run went on, snapshots of iterations the new run never reached
# stayed for ever, and the old initial.exr (another config's start) went into the new compare.png.
# The cached targets (they have their own key) and the user's own files stay.
job fresh > fresh.json
sed 's/"iterations": 16/"iterations": 8/' fresh.json > fresh8.json
grep -q '"iterations": 8' fresh8.json || fail "fresh8.json: the iteration count was not changed"
"$bin" optimize fresh.json --threads 1 --quiet 2>> out.log || fail "the run of 16 iterations failed"
old_outputs="summary.json loss.csv validation.csv loss.png param_rmse.png report.html compare.png initial.exr
  final/floor.albedo.exr final/floor.albedo.png final/params.json final/view.exr snapshots/floor.albedo_00004.exr
  snapshots/floor.albedo_00016.png snapshots/view_00016.png checkpoint/state.json"
for f in $old_outputs targets/top.exr targets/top.exr.key; do
  [ -f "fresh/$f" ] || fail "fixture: the run of 16 iterations wrote no $f"
done
mine="notes.txt final/notes.txt snapshots/notes.txt"
for f in $mine; do echo "the user's" > "fresh/$f"; done
"$bin" optimize fresh8.json --threads 1 --quiet 2>> out.log || fail "the fresh run of 8 iterations failed"
for f in snapshots/floor.albedo_00012.exr snapshots/floor.albedo_00016.png snapshots/view_00016.png; do
  [ ! -e "fresh/$f" ] || fail "a fresh run of 8 iterations left the previous run's $f"
done
[ -f fresh/snapshots/floor.albedo_00008.exr ] || fail "the fresh run of 8 iterations wrote no snapshot 8"
for f in $mine targets/top.exr; do [ -f "fresh/$f" ] || fail "a fresh start removed $f"; done
# Killed during the clean-up (BACKLIGHT_CRASH_AT=outputs-removed: everything but the checkpoint is
# gone), the folder resumes: the finished run's checkpoint finishes again.
"$bin" optimize fresh.json --threads 1 --quiet 2>> out.log || fail "the second run of 16 iterations failed"
env BACKLIGHT_CRASH_AT=outputs-removed "$bin" optimize fresh8.json --threads 1 --quiet 2>> out.log
code=$?
[ $code -eq 137 ] || fail "crash at outputs-removed: exit $code, expected the injected 137"
for f in $old_outputs; do
  [ "$f" = checkpoint/state.json ] || [ ! -e "fresh/$f" ] || fail "a fresh start killed in its clean-up left $f"
done
[ -f fresh/checkpoint/state.json ] || fail "the clean-up removed the checkpoint before the other outputs"
for f in $mine targets/top.exr targets/top.exr.key; do [ -f "fresh/$f" ] || fail "the clean-up removed $f"; done
"$bin" optimize fresh.json --resume fresh --threads 1 --quiet 2>> out.log ||
  fail "--resume of a folder whose clean-up was killed failed: $(tail -n 1 out.log)"
for f in summary.json final/floor.albedo.exr compare.png initial.exr; do
  [ -f "fresh/$f" ] || fail "the resumed finished run wrote no $f"
done
rows=$(($(wc -l < fresh/loss.csv) - 1))
[ "$rows" -eq $iterations ] || fail "the resumed finished run's loss.csv has $rows rows, expected $iterations"
# Killed after the clean-up, before its first write (outputs-cleared): the previous run's
# checkpoint is gone too, and --resume says why there is none.
env BACKLIGHT_CRASH_AT=outputs-cleared "$bin" optimize fresh8.json --threads 1 --quiet 2>> out.log
code=$?
[ $code -eq 137 ] || fail "crash at outputs-cleared: exit $code, expected the injected 137"
for f in $old_outputs; do [ ! -e "fresh/$f" ] || fail "a fresh start killed after its clean-up left $f"; done
[ ! -e fresh/checkpoint ] && [ ! -e fresh/checkpoint.old ] || fail "the previous run's checkpoint folder stayed"
for f in $mine targets/top.exr; do [ -f "fresh/$f" ] || fail "the clean-up removed $f"; done
"$bin" optimize fresh8.json --resume fresh --threads 1 --quiet 2> resume.err
code=$?
[ $code -eq 2 ] && [ "$(wc -l < resume.err)" -eq 1 ] && grep -q "no checkpoint" resume.err &&
  grep -q "without --resume" resume.err || fail "--resume after a cleared start: exit $code: $(cat resume.err)"
"$bin" optimize fresh8.json --threads 1 --quiet 2>> out.log || fail "a fresh start after the crashes failed"
[ -f fresh/summary.json ] && [ -f fresh/final/floor.albedo.exr ] || fail "the fresh start did not finish"
for f in $mine; do [ -f "fresh/$f" ] || fail "a fresh start removed $f"; done
# 6. Checkpoints are on the disk before they are swapped in (a power cut, which no kill can stand
# for, could otherwise leave checkpoint/ with empty files and no checkpoint.old/): strace shows,
# before every rename of checkpoint.tmp/ to checkpoint/, an fsync of each of its files and of the
# folder, and after it one of the output folder.
strace -f -o /dev/null true 2> /dev/null || fail "strace cannot trace here (tools/deps installs it)"
# LeakSanitizer cannot run under ptrace (tools/check --sanitize): its leak check is off for this run
# alone, every other run keeps it.
ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_leaks=0" strace -f -y -qq -e trace=fsync,rename,renameat,renameat2 \
  -o trace.log "$bin" optimize ref.json --threads 1 --quiet 2>> out.log ||
  fail "the traced run failed: $(tail -n 1 out.log)"
python3 - "$dir/ref" trace.log <<'PY' || fail "checkpoint writes are not flushed before their swap (the lines above)"
import re, sys
out, lines = sys.argv[1], open(sys.argv[2]).read().splitlines()
synced, swaps, bad = set(), 0, []
for i, line in enumerate(lines):
    m = re.search(r"fsync\(\d+<([^>]*)>\) = 0", line)
    if m:
        synced.add(m.group(1))
        continue
    m = re.search(r'rename\w*\(.*"([^"]*checkpoint\.tmp)", .*"([^"]*/checkpoint)"', line)
    if not m:
        continue
    swaps += 1
    tmp = m.group(1)
    files = [p for p in synced if p.startswith(out + "/checkpoint.tmp/")]
    if out + "/checkpoint.tmp" not in synced: bad.append("swap %d: the folder was not flushed" % swaps)
    if not any(p.endswith("/state.json") for p in files): bad.append("swap %d: state.json was not flushed" % swaps)
    if not any(p.endswith(".value") for p in files): bad.append("swap %d: the values were not flushed" % swaps)
    after = [l for l in lines[i + 1:i + 40] if re.search(r"fsync\(\d+<%s>\) = 0" % re.escape(out), l)]
    if not after: bad.append("swap %d: the output folder was not flushed after it" % swaps)
    synced = set()
if swaps != 8: bad.append("%d checkpoint swaps traced, expected 8" % swaps)
for b in bad: print(b)
sys.exit(1 if bad else 0)
PY
echo "ok: 8 injected crashes and 3 kill -9, resumed to the uninterrupted result; a crash inside the target cache;" \
  "a fresh start over a finished folder, removing its outputs, killed in and after that clean-up;" \
  "checkpoints flushed to disk before their swap (8 traced)"
