#!/usr/bin/env bash
# backlight optimize --resume and what a checkpoint was made from. A checkpoint records the config
# (as parsed JSON), the scene file and the targets. Configs are changed on purpose between a run
# and its resume (more views per iteration, another learning rate): such a resume goes on after
# one stderr line naming what differs. A checkpoint of another scene (another scene file, with
# other content) is refused unless --resume-any-scene is given: its parameters of the same names
# and shapes are another scene's values. A checkpoint without the record (an older backlight's)
# resumes with a note. Usage: test_optimize_resume.sh BACKLIGHT_BIN
set -u
bin="$1"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
cd "$dir"
fail() { echo "FAIL: $*"; exit 1; }
. "$here/floor_scene.sh"
write_floor_scene 16
export BACKLIGHT_PLOTS=builtin
job() {  # job ITERATIONS [SCENE [EXTRA_KEYS]] > config
  cat <<JSON
{"scene": "${2:-scene.json}", "output": "base",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 8}},
 "spp": 8, "iterations": $1, "checkpoint_every": 2, "snapshot_every": 4${3:-}}
JSON
}
job 4 > base.json
"$bin" optimize base.json --threads 1 --quiet 2> base.log || fail "the run to resume failed: $(cat base.log)"
[ -f base/checkpoint/state.json ] || fail "the run to resume left no checkpoint"
# resume CASE CONFIG [FLAGS]: --resume of a copy of the base run; stderr in CASE.err, exit status in $code.
resume() {
  local name="$1" config="$2"
  shift 2
  rm -rf "$name" && cp -r base "$name"
  "$bin" optimize "$config" --resume "$name" --threads 1 --quiet "$@" 2> "$name.err"
  code=$?
}
notes() { grep -c "^optimize: resuming" "$1.err"; }
cases=0
expect_note() {  # expect_note CASE PATTERN...: resumed (exit 0) after one note naming every PATTERN
  local name="$1" p
  shift
  cases=$((cases + 1))
  [ $code -eq 0 ] || fail "$name: exit $code: $(cat "$name.err")"
  [ "$(notes "$name")" -eq 1 ] || fail "$name: expected one note line: $(cat "$name.err")"
  for p in "$@"; do
    grep "^optimize: resuming" "$name.err" | grep -qF -- "$p" || fail "$name: the note does not say '$p': $(cat "$name.err")"
  done
  [ -f "$name/summary.json" ] || fail "$name: the resumed run did not finish"
}

# The same config: no note.
resume same base.json
cases=$((cases + 1))
[ $code -eq 0 ] || fail "same: exit $code: $(cat same.err)"
[ "$(notes same)" -eq 0 ] || fail "same: a note for an unchanged config: $(cat same.err)"

# A changed config is resumed, with the keys that differ named by their path in the config.
job 6 > more.json
sed -i 's/"lr": 0.02/"lr": 0.03/' more.json
resume changed more.json
expect_note changed "changed/checkpoint" "the config differs in iterations, parameters.floor.albedo.lr"
rows=$(($(wc -l < changed/loss.csv) - 1))
[ "$rows" -eq 6 ] || fail "changed: loss.csv has $rows rows, expected 6"
! grep -q "scene" changed.err || fail "changed: the note speaks of the scene: $(cat changed.err)"

# Many keys: the list is capped (nine differ: the iterations, eight others).
job 6 scene.json ', "seed": 3, "adjoint_spp": 4, "decorrelate": false, "rmse_resolution": [8, 8],
 "validation": {"every": 3}, "loss": "l1", "views_per_iteration": 1' > many.json
sed -i 's/"checkpoint_every": 2/"checkpoint_every": 3/' many.json
resume many many.json
expect_note many "rmse_resolution and 3 more"

# The scene file edited in place: the same scene, changed on purpose (a light, the integrator).
cp scene.json scene.orig
sed -i 's/"max_depth": 2/"max_depth": 3/' scene.json
grep -q '"max_depth": 3' scene.json || fail "edited: the scene was not changed"
resume edited base.json
expect_note edited "scene file changed"
cp scene.orig scene.json

# The same scene under another name: no word about the scene, only the config's key.
cp scene.json copy.json
job 4 copy.json > copy_scene.json
resume copy copy_scene.json
expect_note copy "the config differs in scene"
! grep -q "scene file changed\|another scene" copy.err || fail "copy: the same scene content is reported: $(cat copy.err)"

# Another scene: another file with other content. Refused with one line naming both, nothing written.
sed 's/"radiance": \[1, 1, 1\]/"radiance": [2, 2, 2]/' scene.json > other.json
grep -q '"radiance": \[2, 2, 2\]' other.json || fail "other: the scene was not changed"
job 4 other.json > other_scene.json
resume other other_scene.json
cases=$((cases + 1))
[ $code -eq 2 ] || fail "other: exit $code, expected 2: $(cat other.err)"
[ "$(wc -l < other.err)" -eq 1 ] || fail "other: expected one line: $(cat other.err)"
for p in "backlight: " "/scene.json" "/other.json" "--resume-any-scene"; do
  grep -qF -- "$p" other.err || fail "other: the error does not say '$p': $(cat other.err)"
done
cmp -s base/checkpoint/state.json other/checkpoint/state.json || fail "other: the refused resume changed the checkpoint"
cmp -s base/targets/top.exr other/targets/top.exr || fail "other: the refused resume rendered the other scene's target"
# ... and resumed with --resume-any-scene, saying so.
resume other_any other_scene.json --resume-any-scene
expect_note other_any "another scene" "/scene.json"
# The flag without --resume is refused.
"$bin" optimize base.json --resume-any-scene --quiet 2> flag.err
code=$?
cases=$((cases + 1))
[ $code -eq 2 ] && grep -qF -- "--resume" flag.err || fail "--resume-any-scene alone: exit $code: $(cat flag.err)"

# A target file changed: named by its view.
"$bin" render scene.json --set floor.albedo=truth.exr --spp 4 -o t.exr -q 2> t.err || fail "render: $(cat t.err)"
cat > files.json <<'JSON'
{"scene": "scene.json", "output": "base",
 "parameters": {"floor.albedo": {"lr": 0.02, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "targets": {"top": "t.exr"}},
 "spp": 8, "iterations": 4, "checkpoint_every": 2, "snapshot_every": 4}
JSON
sed 's/"output": "base"/"output": "files"/; s/"iterations": 4/"iterations": 2/' files.json > files2.json
"$bin" optimize files2.json --threads 1 --quiet 2> files2.err || fail "files2: $(cat files2.err)"
"$bin" render scene.json --set floor.albedo=truth.exr --spp 8 -o t.exr -q 2> t.err || fail "render: $(cat t.err)"
"$bin" optimize files.json --resume files --threads 1 --quiet 2> files.err
code=$?
expect_note files "targets of top changed" "the config differs in iterations"

# A checkpoint of an older backlight, without the record: resumed, with a note.
rm -rf old && cp -r base old
python3 - old/checkpoint/state.json <<'PY' || fail "old: the record could not be removed"
import json, sys
s = json.load(open(sys.argv[1]))
del s["made_from"]
json.dump(s, open(sys.argv[1], "w"))
PY
"$bin" optimize more.json --resume old --threads 1 --quiet 2> old.err
code=$?
expect_note old "records nothing of what it was made from"
echo "ok: $cases resumes: unchanged, changed config, many keys, scene edited, the same scene elsewhere," \
  "another scene refused and forced, a changed target file, a checkpoint without a record"
