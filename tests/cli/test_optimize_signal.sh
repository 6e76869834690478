#!/usr/bin/env bash
# backlight optimize: SIGINT writes a checkpoint and exits 0; --resume then finishes the run and
# writes the summary. Usage: test_optimize_signal.sh BACKLIGHT_BIN
set -u
bin="$1"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
cd "$dir"
. "$here/floor_scene.sh"
write_floor_scene 32
cat > job.json <<'JSON'
{"scene": "scene.json", "output": "out",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 16}},
 "spp": 64, "iterations": 100000, "checkpoint_every": 5, "snapshot_every": 100000}
JSON
fail() { echo "FAIL: $*"; exit 1; }
"$bin" optimize job.json --quiet 2> log.txt &
pid=$!
for _ in $(seq 1 1200); do  # up to 120 s: sanitizer builds and busy machines are slow
  [ -f out/checkpoint/state.json ] && break
  sleep 0.1
done
[ -f out/checkpoint/state.json ] || { kill -9 $pid 2>/dev/null; fail "no checkpoint after 120 s: $(cat log.txt)"; }
kill -INT $pid
wait $pid
code=$?
[ $code -eq 0 ] || fail "SIGINT exit code $code, expected 0 ($(cat log.txt))"
grep -q "interrupted; checkpoint" log.txt || fail "no interruption message: $(cat log.txt)"
done_iterations=$(python3 -c "import json; print(json.load(open('out/checkpoint/state.json'))['next_iteration'])")
[ "$done_iterations" -ge 5 ] || fail "checkpoint records $done_iterations iterations"
[ ! -e out/checkpoint.tmp ] || fail "temporary checkpoint left behind"
# Resume with a config that ends soon after the interruption point.
sed "s/\"iterations\": 100000/\"iterations\": $((done_iterations + 3))/" job.json > job2.json
"$bin" optimize job2.json --resume out --quiet 2> log2.txt || fail "resume failed: $(cat log2.txt)"
rows=$(($(wc -l < out/loss.csv) - 1))
[ "$rows" -eq $((done_iterations + 3)) ] || fail "loss.csv has $rows rows, expected $((done_iterations + 3))"
[ -f out/summary.json ] || fail "no summary.json after resume"
echo "ok: interrupted after $done_iterations iterations, resumed to $((done_iterations + 3))"
