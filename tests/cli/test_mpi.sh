#!/usr/bin/env bash
# backlight under mpirun (loopback, --oversubscribe): the guarantees of engine/dist/dist.h.
#  - render: images bitwise equal for R = 1, 2, 4 (and for both tile splits);
#  - grad: image and loss bitwise equal, gradients equal to float rounding (|Δ| ≤ 1e-5·max|g|),
#    the memory of every rank in gradients.json;
#  - check: the finite-difference column bitwise equal, the adjoint one to float rounding;
#  - optimize: a few iterations on 2 ranks reach the parameters of one process (to rounding);
#    only rank 0 writes (no file is written twice);
#  - failures: bad input (also a checkpoint that does not fit) gives one line and exit 2; a rank failing mid-run prints one line naming
#    itself and ends every rank; a rank killed mid-run makes mpirun and every rank exit non-zero
#    within seconds; --resume with a different R finishes the run.
#  - taped gradients on 2 ranks equal one process's to rounding.
# Usage: test_mpi.sh BACKLIGHT_BIN MPI_BUILT(ON/OFF)
set -u
bin="$1"
if [ "${2:-OFF}" != "ON" ] && [ "${2:-OFF}" != "1" ]; then
  echo "skipped: this build has no MPI (configure with -DBACKLIGHT_MPI=ON; needs libopenmpi-dev)"
  exit 77
fi
command -v mpirun > /dev/null || { echo "skipped: mpirun not found (apt-get install openmpi-bin)"; exit 77; }
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1  # CI runs as root
export OMPI_MCA_rmaps_base_oversubscribe=1
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
dir="$(mktemp -d)"
cleanup() {
  [ -n "${launcher:-}" ] && kill -9 "$launcher" 2> /dev/null
  pkill -9 -f "$bin optimize k.json" 2> /dev/null
  [ -n "${KEEP:-}" ] || rm -rf "$dir"  # KEEP=1: leave the folder for a look
}
trap cleanup EXIT
cd "$dir"
fail() { echo "FAIL: $*"; exit 1; }
mpi() {  # mpi R COMMAND...: backlight on R ranks, one thread each
  local r="$1"
  shift
  mpirun -q --oversubscribe -n "$r" "$bin" "$@" 2> >(tee -a mpi_stderr.log >&2)
}
same_pixels() {  # same_pixels A B: every float equal (the files are not: EXR headers carry a date)
  idiff -fail 0 -warn 0 "$1" "$2" > /dev/null
}
py=python3
[ -x /usr/bin/python3 ] && py=/usr/bin/python3
. "$here/floor_scene.sh"
write_floor_scene 72  # 72×72: 25 tiles of 16×16, the last row and column partial
# A copy of the scene for a second "node" whose texture start.exr is stale (different content).
mkdir -p stale && cp scene.json truth.exr stale/ && cp truth.exr stale/start.exr
stale_line="backlight: the ranks loaded different scenes from the same command: a file the scene refers to (a texture, mesh or grid) differs between their machines (every rank must read the same files)"

# --- render: bitwise for R = 1, 2, 4 -------------------------------------------------------------
"$bin" render scene.json --spp 4 --threads 1 -q -o r1.exr 2> /dev/null || fail "render on one process"
for r in 2 4; do
  mpi $r render scene.json --spp 4 --threads 1 -q -o r$r.exr 2> /dev/null || fail "render on $r ranks"
  same_pixels r1.exr r$r.exr || fail "render on $r ranks differs from one process"
done
mpirun -q --oversubscribe -n 3 -x BACKLIGHT_MPI_SPLIT=blocks "$bin" render scene.json --spp 4 -q -o rb.exr \
  2> /dev/null || fail "render with the blocks split"
same_pixels r1.exr rb.exr || fail "render with the blocks split on 3 ranks differs from one process"

# --- grad: image and loss bitwise, gradients to float rounding -----------------------------------
"$bin" render scene.json --spp 16 --seed 9 -q -o target.exr --set floor.albedo=truth.exr 2> /dev/null
grad_args=(grad scene.json --spp 4 --threads 1 -q --target target.exr)
"$bin" "${grad_args[@]}" --out g1 2> /dev/null || fail "grad on one process"
"$bin" "${grad_args[@]}" --method taped --out t1 2> /dev/null || fail "taped grad on one process"
mpi 2 "${grad_args[@]}" --method taped --out t2 2> /dev/null || fail "taped grad on 2 ranks"
for r in 2 4; do
  mpi $r "${grad_args[@]}" --out g$r 2> /dev/null || fail "grad on $r ranks"
  same_pixels g1/image.exr g$r/image.exr || fail "grad on $r ranks: image differs"
done
"$py" - <<'PY' || fail "grad gradients differ beyond float rounding"
import json, subprocess, struct, sys
def grad(d):
    j = json.load(open(f"{d}/gradients.json"))
    out = {}
    for name, e in j["parameters"].items():
        if "grad" in e:
            out[name] = e["grad"]
        else:  # an EXR: its floats through oiiotool's FITS (2880-byte header blocks, big-endian)
            fits = f"{d}/{name}.fits"
            subprocess.run(["oiiotool", f"{d}/{e['file']}", "-d", "float", "-o", fits], check=True)
            raw = open(fits, "rb").read()
            cards = [raw[i:i + 80] for i in range(0, len(raw), 80)]
            end = next(i for i, c in enumerate(cards) if c.startswith(b"END "))
            start = ((end * 80) // 2880 + 1) * 2880
            n = 1
            for c in cards[:end]:
                if c.startswith(b"NAXIS") and c[5:6].isdigit():
                    n *= int(c.split(b"=")[1].split(b"/")[0])
            out[name] = list(struct.unpack(f">{n}f", raw[start:start + 4 * n]))
    return j, out
j1, g1 = grad("g1")
for d, r in (("g2", 2), ("g4", 4), ("t2", 2)):
    if d == "t2":
        j1, g1 = grad("t1")
    jr, gr = grad(d)
    assert jr["loss"] == j1["loss"], (r, jr["loss"], j1["loss"])
    assert len(jr["ranks"]) == r and all(x["peak_rss_mb"] > 1 for x in jr["ranks"]), jr["ranks"]
    for name, a in g1.items():
        b = gr[name]
        scale = max(abs(x) for x in a) or 1.0
        worst = max(abs(x - y) for x, y in zip(a, b))
        print(f"{d}: {name}: max |diff| = {worst:.3g} of max |g| = {scale:.3g}")
        assert len(a) == len(b) and worst <= 1e-5 * scale, (r, name, worst, scale)
        assert any(x != 0 for x in b), (r, name, "all zero")
PY

# --- check: FD column bitwise, adjoint to rounding --------------------------------------------------
check_args=(check scene.json --spp 4 --threads 1 --target target.exr --param floor.albedo --directions 2 --eps 0.05
            --tolerance 0.1)
"$bin" "${check_args[@]}" > c1.txt 2> /dev/null
c1=$?
mpi 2 "${check_args[@]}" > c2.txt 2> /dev/null
c2=$?
[ $c1 -eq $c2 ] || fail "check: exit $c2 on 2 ranks, $c1 on one process"
"$py" - <<'PY' || fail "check on 2 ranks differs from one process: $(cat c1.txt c2.txt)"
rows = lambda f: [l.split() for l in open(f) if l[:1].isdigit()]
a, b = rows("c1.txt"), rows("c2.txt")
assert len(a) == len(b) == 2, (a, b)
for x, y in zip(a, b):
    assert x[2] == y[2], ("finite differences", x, y)
    assert abs(float(x[1]) - float(y[1])) <= 1e-5 * abs(float(x[1])), ("adjoint", x, y)
PY

# --- optimize: 2 ranks reach one process's parameters; only rank 0 writes --------------------------
job() {  # job OUTPUT_DIR ITERATIONS SNAPSHOT_EVERY
  cat <<JSON
{"scene": "scene.json", "output": "$1",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 8}},
 "spp": 4, "iterations": $2, "checkpoint_every": 2, "snapshot_every": $3}
JSON
}
job o1 6 3 > o1.json
job o2 6 3 > o2.json
"$bin" optimize o1.json --threads 1 --quiet 2> o1.log || fail "optimize on one process: $(tail -n 2 o1.log)"
# A texture that differs on one rank's "node" (see "Ranks started with different commands" below).
job ostale 2 1 > ostale.json
cp ostale.json stale/
out=$(mpirun -q --oversubscribe -n 1 "$bin" optimize ostale.json --threads 1 --quiet : \
  -n 1 -wdir stale "$bin" optimize ostale.json --threads 1 --quiet 2>&1)
code=$?
[ $code -eq 2 ] && [ "$out" = "$stale_line" ] || fail "ranks loading different textures (optimize): exit $code, printed: $out"
[ ! -e ostale ] && [ ! -e stale/ostale ] || fail "ranks loading different textures (optimize) wrote output"
mpi 2 optimize o2.json --threads 1 --quiet 2> o2.log || fail "optimize on 2 ranks: $(tail -n 2 o2.log)"
close() {  # close A B: the float files agree to 1e-5
  "$py" - "$1" "$2" <<'PY'
import struct, sys
a, b = (open(p, "rb").read() for p in sys.argv[1:3])
x, y = (struct.unpack(f"{len(d) // 4}f", d) for d in (a, b))
worst = max(abs(p - q) for p, q in zip(x, y))
print(f"{sys.argv[2]}: max |diff| = {worst:.3g} over {len(x)} values")
sys.exit(0 if len(x) == len(y) and worst <= 1e-5 else 1)
PY
}
close o1/checkpoint/floor.albedo.value o2/checkpoint/floor.albedo.value ||
  fail "optimize on 2 ranks: parameters differ from one process"
same_pixels o1/targets/top.exr o2/targets/top.exr || fail "optimize on 2 ranks: target render differs"
[ "$(wc -l < o2/loss.csv)" -eq 7 ] || fail "optimize on 2 ranks: loss.csv has $(wc -l < o2/loss.csv) lines"
[ -f o2/summary.json ] && [ -f o2/report.html ] || fail "optimize on 2 ranks: outputs missing: $(ls o2)"
"$py" -c "
import json, sys
r = json.load(open('o2/summary.json'))['ranks']
sys.exit(0 if len(r) == 2 and r[0]['parameter_hash'] == r[1]['parameter_hash'] else 1)" ||
  fail "optimize on 2 ranks: the ranks' parameters differ: $(grep -A30 ranks o2/summary.json)"

# --- failures -----------------------------------------------------------------------------------
out=$(mpi 2 render missing.json -o x.exr 2>&1)
code=$?
[ $code -eq 2 ] || fail "bad input on 2 ranks: exit $code, expected 2 ($out)"
[ "$out" = "backlight: missing.json: file not found" ] || fail "bad input on 2 ranks printed: $out"

# A bad "init" (applied by every rank after the first collective): one line, exit 2.
sed 's/"bounds": \[0, 1\]}/"bounds": [0, 1], "init": "missing.exr"}/' o2.json | sed 's/"output": "o2"/"output": "o3"/' > o3.json
out=$(mpi 2 optimize o3.json --threads 1 --quiet 2>&1)
code=$?
[ $code -eq 2 ] && [ "$(echo "$out" | wc -l)" -eq 1 ] && echo "$out" | grep -q "missing.exr" ||
  fail "bad init on 2 ranks: exit $code, printed: $out"

# A checkpoint that does not fit the config: read by every rank, reported once.
sed 's/"bounds": \[0, 1\]}/"bounds": [0, 1], "moments": "bfloat16"}/' o2.json > o2b.json
out=$(mpi 2 optimize o2b.json --resume o2 --threads 1 --quiet 2>&1)
code=$?
[ $code -eq 2 ] || fail "bad checkpoint on 2 ranks: exit $code, expected 2 ($out)"
[ "$(echo "$out" | wc -l)" -eq 1 ] && echo "$out" | grep -q "^backlight: o2/checkpoint/state.json: checkpoint moments" ||
  fail "bad checkpoint on 2 ranks printed: $out"

# Ranks started with different commands (an MPMD launch; a stale copy of a file on one node looks
# the same): different film sizes corrupted the image gather's heap (malloc abort, exit 134) and
# different spp mixed two renders into one image with exit 0. One line, exit 2, nothing written.
out=$(mpirun -q --oversubscribe -n 1 "$bin" render scene.json --spp 2 --threads 1 -q -o mix.exr : \
  -n 1 "$bin" render scene.json --spp 3 --threads 1 -q -o mix.exr 2>&1)
code=$?
[ $code -eq 2 ] && [ "$out" = "backlight: the ranks were started with different command lines, or read different copies of the files they name (every rank must run the same command on the same files)" ] ||
  fail "ranks with different commands: exit $code, printed: $out"
[ ! -e mix.exr ] || fail "ranks with different commands wrote mix.exr"
cp scene.json scene_b.json
echo " " >> scene_b.json
mkdir -p other && cp scene_b.json other/scene.json && cp start.exr truth.exr other/
out=$(mpirun -q --oversubscribe -n 1 "$bin" render scene.json --spp 2 --threads 1 -q -o mix.exr : \
  -n 1 -wdir other "$bin" render scene.json --spp 2 --threads 1 -q -o mix.exr 2>&1)
code=$?
[ $code -eq 2 ] || fail "ranks reading different copies of scene.json: exit $code, printed: $out"
# The same command and scene file, but a texture the scene refers to differs on one "node" (the
# files a scene names are not on the command line): the two ranks rendered their tiles with
# different textures into one image, exit 0. Compared after loading (what every rank loaded):
# one line, exit 2, nothing written; for render here, for optimize (the job loads the scene
# itself) with the optimize tests above.
out=$(mpirun -q --oversubscribe -n 1 "$bin" render scene.json --spp 2 --threads 1 -q -o mix.exr : \
  -n 1 -wdir stale "$bin" render scene.json --spp 2 --threads 1 -q -o mix.exr 2>&1)
code=$?
[ $code -eq 2 ] && [ "$out" = "$stale_line" ] || fail "ranks loading different textures (render): exit $code, printed: $out"
[ ! -e mix.exr ] || fail "ranks loading different textures wrote mix.exr"

# A gradient that overflows float (environment radiance 1e30; the separate loss and adjoint passes
# of adjoint_spp ≠ spp): one process ran on with NaN parameters and exit 0, two ranks the same or,
# where only the ranks' sum overflowed, checkpointed NaN; an error every rank meets mid-run
# printed one line per rank. Now one line, exit 2, no checkpoint, on 1 and on 2 ranks.
sed 's/"spp": 4,/"spp": 4, "adjoint_spp": 2, "set": {"environment.radiance": [1e30, 1e30, 1e30]},/' o1.json |
  sed 's/"output": "o1"/"output": "ov"/' > ov.json
grep -q '"adjoint_spp": 2' ov.json || fail "ov.json: the config edit did not apply"
for r in 1 2; do
  rm -rf ov
  if [ $r -eq 1 ]; then out=$("$bin" optimize ov.json --threads 1 --quiet 2>&1); else out=$(mpi 2 optimize ov.json --threads 1 --quiet 2>&1); fi
  code=$?
  [ $code -eq 2 ] && [ "$(echo "$out" | wc -l)" -eq 1 ] && echo "$out" | grep -q "the gradient of 'floor.albedo' is not finite" ||
    fail "an overflowing gradient on $r rank(s): exit $code, printed: $out"
  [ ! -e ov/checkpoint ] || fail "an overflowing gradient on $r rank(s) left a checkpoint"
done

# A rank failing mid-run (fault injection at its 40th collective operation): its one line, and
# every rank ends, non-zero.
out=$(mpirun -q --oversubscribe -n 2 -x BACKLIGHT_MPI_FAIL=1:40 "$bin" optimize o1.json --threads 1 --quiet 2>&1)
code=$?
[ $code -ne 0 ] || fail "a rank failing mid-run: mpirun exited 0"
echo "$out" | grep -qx "backlight: rank 1: internal error: injected failure (BACKLIGHT_MPI_FAIL) at collective operation 40" ||
  fail "a rank failing mid-run printed: $out"

# A rank killed mid-run: every rank exits, non-zero, within seconds.
job k 80 1000 > k.json
mpirun --oversubscribe -n 2 "$bin" optimize k.json --threads 1 --quiet > k.log 2>&1 &
launcher=$!
for _ in $(seq 1 600); do [ -f k/checkpoint/state.json ] && break; sleep 0.1; done
[ -f k/checkpoint/state.json ] || fail "the 2-rank run wrote no checkpoint: $(tail -n 3 k.log)"
victim=""
for p in $(pgrep -f "$bin optimize k.json"); do
  tr '\0' '\n' < /proc/$p/environ 2> /dev/null | grep -qx OMPI_COMM_WORLD_RANK=1 && victim=$p
done
[ -n "$victim" ] || fail "rank 1's process not found"
kill -9 "$victim"
start=$(date +%s)
for _ in $(seq 1 600); do kill -0 $launcher 2> /dev/null || break; sleep 0.1; done
kill -0 $launcher 2> /dev/null && fail "mpirun still running 60 s after rank 1 was killed (a hang)"
wait $launcher
code=$?
took=$(($(date +%s) - start))
[ $code -ne 0 ] || fail "mpirun exited 0 after a rank was killed"
grep -q "rank 1" k.log || fail "no line names rank 1: $(cat k.log)"
pgrep -f "$bin optimize k.json" > /dev/null && fail "a rank survived"
# --resume on 4 ranks (a different R) finishes the run.
done_before=$("$py" -c "import json; print(json.load(open('k/checkpoint/state.json'))['next_iteration'])" 2> /dev/null ||
              echo "?")
mpi 4 optimize k.json --resume k --threads 1 --quiet 2> k2.log || fail "--resume on 4 ranks: $(tail -n 2 k2.log)"
[ -f k/summary.json ] || fail "--resume on 4 ranks did not finish"
[ "$(wc -l < k/loss.csv)" -eq 81 ] || fail "--resume on 4 ranks: loss.csv has $(wc -l < k/loss.csv) lines"
echo "ok: render/grad/check/optimize on 1, 2, 4 ranks; a killed rank ended the run in ${took} s" \
     "(mpirun exit $code); --resume on 4 ranks finished it from iteration $done_before"
