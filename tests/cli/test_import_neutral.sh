#!/usr/bin/env bash
# Self-test of tools/import-neutral.
# Usage: tests/cli/test_import_neutral.sh [REPO_ROOT] [SHARED_DIR]
#   REPO_ROOT  defaults to this script's ../..
#   SHARED_DIR defaults to REPO_ROOT/../shared (must contain reference/mitsuba3-cornell and
#              reference/mitsuba3-volume)
# Exits non-zero on the first failure.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "${1:-$here/../..}" && pwd)"
shared="${2:-$repo/../shared}"
ref="$shared/reference/mitsuba3-cornell"
tool="$repo/tools/import-neutral"

fail() { echo "test_import_neutral: FAIL: $*" >&2; exit 1; }
[ -x "$tool" ] || fail "$tool is not executable"
[ -f "$ref/scene.json" ] || fail "missing $ref/scene.json"
[ -f "$ref/scene_textured.json" ] || fail "missing $ref/scene_textured.json"

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

# 1. Both neutral scenes convert.
"$tool" "$ref/scene.json" "$tmp/plain" >/dev/null 2>"$tmp/plain.err" \
  || fail "conversion of scene.json failed: $(cat "$tmp/plain.err")"
"$tool" "$ref/scene_textured.json" "$tmp/textured" >/dev/null 2>"$tmp/textured.err" \
  || fail "conversion of scene_textured.json failed: $(cat "$tmp/textured.err")"

# 2. Structure of the outputs.
python3 - "$tmp/plain/scene.json" "$tmp/textured/scene.json" <<'PY' || fail "output checks"
import json, os, sys
plain, textured = sys.argv[1], sys.argv[2]
for path in (plain, textured):
    with open(path) as f:
        s = json.load(f)                       # parses
    assert len(s["shapes"]) == 8, (path, len(s["shapes"]))
    for sh in s["shapes"]:
        assert sh["type"] == "mesh" and "." not in sh["name"], sh["name"]
        assert sh["material"] in s["materials"], sh["material"]
    light = [sh for sh in s["shapes"] if sh["name"] == "light"]
    assert len(light) == 1, "no light shape"
    rad = light[0]["emitter"]["radiance"]
    assert [round(x, 4) for x in rad] == [18.387, 13.9873, 6.7536], rad
    assert sum("emitter" in sh for sh in s["shapes"]) == 1
    for m in s["materials"].values():
        assert m["type"] == "diffuse" and m["two_sided"] is False, m
    cam = s["cameras"][0]
    assert cam["resolution"] == [256, 256] and cam["fov_axis"] == "x", cam
    assert s["integrator"]["max_depth"] == 6 and s["integrator"]["rr_depth"] == 5
s = json.load(open(textured))
back = [sh for sh in s["shapes"] if sh["name"] == "back"][0]
alb = s["materials"][back["material"]]["albedo"]
assert isinstance(alb, dict) and alb["type"] == "bitmap", alb
assert alb["wrap"] == "repeat" and alb["color_space"] == "linear", alb
tex = os.path.join(os.path.dirname(textured), alb["file"])
assert os.path.isfile(tex), tex
PY
cmp -s "$ref/wall_texture.exr" "$tmp/textured/wall_texture.exr" || fail "texture not copied unchanged"

# 3. The volume reference (a grid medium behind a null box) converts into the committed
#    scenes/mitsuba-volume: the same scene JSON, the grid copied byte for byte.
vref="$shared/reference/mitsuba3-volume"
[ -f "$vref/scene.json" ] || fail "missing $vref/scene.json"
"$tool" "$vref/scene.json" "$tmp/volume" >/dev/null 2>"$tmp/volume.err" \
  || fail "conversion of the volume scene failed: $(cat "$tmp/volume.err")"
python3 - "$tmp/volume/scene.json" "$repo/scenes/mitsuba-volume/scene.json" <<'PY' || fail "volume scene differs from scenes/mitsuba-volume"
import json, sys
new, committed = (json.load(open(p)) for p in sys.argv[1:])
assert new == committed, "re-converted scene.json differs from the committed one"
m = new["media"]["smoke"]
assert m["type"] == "grid" and m["density"] == {"type": "vol", "file": "density.vol"} and m["scale"] == 6.0, m
box = [sh for sh in new["shapes"] if sh.get("interior") == "smoke"]
assert len(box) == 1 and new["materials"][box[0]["material"]]["type"] == "null", box
PY
cmp -s "$tmp/volume/density.vol" "$repo/scenes/mitsuba-volume/density.vol" || fail "density.vol not copied unchanged"

# 4. Errors: exit status 2 and exactly one stderr line.
expect_error() {  # name, args...
  local name="$1"; shift
  local rc=0
  "$tool" "$@" >/dev/null 2>"$tmp/$name.err" || rc=$?
  [ "$rc" -eq 2 ] || fail "$name: exit status $rc, expected 2"
  local n; n="$(wc -l <"$tmp/$name.err")"
  [ "$n" -eq 1 ] || fail "$name: $n stderr lines, expected 1: $(cat "$tmp/$name.err")"
  grep -q '^import-neutral: ' "$tmp/$name.err" || fail "$name: bad message: $(cat "$tmp/$name.err")"
}
printf '{"camera": {"type": "perspective",\n' >"$tmp/malformed.json"
expect_error malformed "$tmp/malformed.json" "$tmp/out_malformed"
grep -q 'malformed.json' "$tmp/malformed.err" || fail "malformed: message does not name the file"
expect_error missing "$tmp/does_not_exist.json" "$tmp/out_missing"
grep -q 'does_not_exist.json' "$tmp/missing.err" || fail "missing: message does not name the file"
[ ! -e "$tmp/out_malformed" ] && [ ! -e "$tmp/out_missing" ] || fail "output written on error"

echo "test_import_neutral: OK"
