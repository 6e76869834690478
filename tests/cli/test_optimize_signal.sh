#!/usr/bin/env bash
# backlight optimize: SIGINT writes a checkpoint and exits 0; --resume then finishes the run and
# writes the summary. Usage: test_optimize_signal.sh BACKLIGHT_BIN
set -u
bin="$1"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
cd "$dir"
oiiotool --pattern checker:width=8:height=8:color1=0.8,0.2,0.1:color2=0.1,0.5,0.8 32x32 3 -d float -o truth.exr
oiiotool --pattern constant:color=0.5,0.5,0.5 32x32 3 -d float -o start.exr
cat > scene.json <<'JSON'
{"integrator": {"max_depth": 2, "rr_depth": 0},
 "cameras": [{"name": "top", "origin": [0, 3, 0.01], "target": [0, 0, 0], "fov": 45, "resolution": [32, 32]}],
 "materials": {"floor": {"type": "diffuse", "albedo": {"type": "bitmap", "file": "start.exr"}}},
 "shapes": [{"name": "floor", "type": "rectangle", "material": "floor",
             "transform": {"rotate": {"axis": [1, 0, 0], "angle": -90}}}],
 "environment": {"type": "constant", "radiance": [1, 1, 1]}}
JSON
cat > job.json <<'JSON'
{"scene": "scene.json", "output": "out",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 16}},
 "spp": 64, "iterations": 100000, "checkpoint_every": 5, "snapshot_every": 100000}
JSON
fail() { echo "FAIL: $*"; exit 1; }
"$bin" optimize job.json --quiet 2> log.txt &
pid=$!
for _ in $(seq 1 300); do
  [ -f out/checkpoint/state.json ] && break
  sleep 0.1
done
[ -f out/checkpoint/state.json ] || { kill -9 $pid 2>/dev/null; fail "no checkpoint after 30 s: $(cat log.txt)"; }
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
