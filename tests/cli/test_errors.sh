#!/usr/bin/env bash
# Command-line contract of tools/backlight.cpp.
# Usage: tests/cli/test_errors.sh BACKLIGHT_BIN [REPO_ROOT]
#
# Bad input: every user error exits with status 2, prints exactly ONE line on stderr starting
# with "backlight: ", names the file / flag / parameter at fault and the problem, never crashes
# (no signal) and writes no output.
# Good paths: --help texts, atomic image writes, `params --json/--dump`, `grad` outputs
# (gradients.json layout, per-parameter files; grids as .vdb, .vol and a PNG sheet), `grad
# --adjoint-image` and `check`.
# Runs every case and reports all failures at the end (exit 1 if any).
set -uo pipefail

bin="${1:?usage: test_errors.sh BACKLIGHT_BIN [REPO_ROOT]}"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "${2:-$here/../..}" && pwd)"
cornell="$repo/scenes/cornell/scene.json"
gltf_dir="$repo/scenes/gltf"
[ -x "$bin" ] || { echo "test_errors: $bin is not executable" >&2; exit 1; }
[ -f "$cornell" ] || { echo "test_errors: missing $cornell" >&2; exit 1; }

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
cd "$tmp" || exit 1
ulimit -c 0  # a crash shows as a signal exit status; leave no core files

# Cases run concurrently (process start-up dominates their cost); failures collect in a file.
jobs_max="$(nproc 2>/dev/null || echo 2)"
cases=0
fail() { printf 'FAIL: %s\n' "$*" >>"$tmp/failures"; }
throttle() { while [ "$(jobs -rp | wc -l)" -ge "$jobs_max" ]; do wait -n; done; }
in_background() { cases=$((cases + 1)); throttle; "$@" & }

# run_bin OUT ERR ARGS...: runs backlight, stdout to OUT and stderr to ERR, stdin from /dev/null,
# and returns its status.
run_bin() {
  local out="$1" err="$2"
  shift 2
  if [ -n "${run_timeout:-}" ]; then
    timeout -k 5 "$run_timeout" "$bin" "$@" >"$out" 2>"$err" </dev/null
  else
    "$bin" "$@" >"$out" 2>"$err" </dev/null
  fi
}

# expect_error NAME PATTERN... -- ARGS...
# A PATTERN is a fixed string the single stderr line must contain; "re:REGEX" is an extended regex.
expect_error() { in_background expect_error_now "$@"; }
expect_error_now() {
  local name="$1"; shift
  local patterns=()
  while [ "$#" -gt 0 ] && [ "$1" != "--" ]; do patterns+=("$1"); shift; done
  shift
  local err="$tmp/err.$name" rc=0
  run_bin "$tmp/out.$name" "$err" "$@" || rc=$?
  local lines; lines="$(awk 'END { print NR }' "$err")"  # counts an unterminated last line too
  local msg; msg="$(cat "$err")"
  if [ -n "${run_timeout:-}" ] && [ "$rc" -eq 124 ]; then fail "$name: hung (stopped after $run_timeout s): $msg"; return; fi
  if [ "$rc" -ge 128 ]; then fail "$name: crashed (status $rc, signal $((rc - 128))): $msg"; return; fi
  case "$msg" in *"internal error"*) fail "$name: input reached an internal error: $msg" ;; esac
  [ "$rc" -eq 2 ] || fail "$name: exit status $rc, expected 2: $msg"
  [ "$lines" -eq 1 ] || fail "$name: $lines stderr lines, expected 1:"$'\n'"$msg"
  case "$msg" in "backlight: "*) ;; *) [ "$lines" -ne 1 ] || fail "$name: message does not start with 'backlight: ': $msg" ;; esac
  local p
  for p in "${patterns[@]}"; do
    if [[ "$p" == re:* ]]; then
      grep -qE -- "${p#re:}" "$err" || fail "$name: message does not match /${p#re:}/: $msg"
    else
      grep -qF -- "$p" "$err" || fail "$name: message does not mention '$p': $msg"
    fi
  done
}

# expect_error_timed NAME PATTERN... -- ARGS...: expect_error for an input that hung: stopped
# after 60 s, a failure of its own (the suite ran on for ever).
expect_error_timed() { cases=$((cases + 1)); throttle; (run_timeout=60 && expect_error_now "$@") & }

# expect_error_small NAME PATTERN... -- ARGS...: expect_error with no room for a large allocation:
# an input whose header claims gigabytes must be refused before allocating them. The address space
# is limited (ulimit -v); under AddressSanitizer, which reserves terabytes of it, its allocation
# size cap does the same.
expect_error_small() {
  cases=$((cases + 1))
  throttle
  if [ -n "${ASAN_OPTIONS:-}" ]; then
    (export ASAN_OPTIONS="$ASAN_OPTIONS:max_allocation_size_mb=600:allocator_may_return_null=0" && expect_error_now "$@") &
  else
    (ulimit -v 800000 && expect_error_now "$@") &
  fi
}

# expect_ok NAME ARGS...: exit 0 (stdout in out.NAME, stderr in err.NAME).
expect_ok() {
  local name="$1"; shift
  local rc=0
  run_bin "$tmp/out.$name" "$tmp/err.$name" "$@" || rc=$?
  [ "$rc" -eq 0 ] || fail "$name: exit status $rc, expected 0: $(cat "$tmp/err.$name")"
  return "$rc"
}

# scene_variant SRC OUT PYTHON: OUT = SRC's JSON with the statement applied to `s`.
scene_variant() {
  python3 - "$1" "$2" "$3" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
exec(sys.argv[3])
json.dump(s, open(sys.argv[2], "w"), indent=1)
PY
}

# Image size from an EXR (dataWindow) or PNG (IHDR) header: prints "WxH".
image_size() {
  python3 - "$1" <<'PY'
import struct, sys
data = open(sys.argv[1], "rb").read()
if data[:8] == b"\x89PNG\r\n\x1a\n":
    w, h = struct.unpack(">II", data[16:24]); print(f"{w}x{h}"); sys.exit()
assert data[:4] == b"\x76\x2f\x31\x01", "not an EXR"
i = 8
while data[i] != 0:
    name_end = data.index(b"\0", i); name = data[i:name_end]
    type_end = data.index(b"\0", name_end + 1)
    size, = struct.unpack("<i", data[type_end + 1:type_end + 5])
    value = data[type_end + 5:type_end + 5 + size]
    if name == b"dataWindow":
        x0, y0, x1, y1 = struct.unpack("<iiii", value); print(f"{x1 - x0 + 1}x{y1 - y0 + 1}"); sys.exit()
    i = type_end + 5 + size
sys.exit("no dataWindow")
PY
}

# ---------------------------------------------------------------------------------------------
# Fixtures. "small" is the Cornell box with an 8x8 wall texture (the 1024² one costs load time).
"$bin" render "$cornell" -o "$tmp/img75.exr" --resolution 7x5 --spp 1 -q 2>/dev/null || fail "fixture img75.exr"
"$bin" render "$cornell" -o "$tmp/wall8.png" --resolution 8x8 --spp 1 -q 2>/dev/null || fail "fixture wall8.png"
mkdir -p small && cp "$tmp/wall8.png" small/wall.png
small="$tmp/small/scene.json"
scene_variant "$cornell" "$small" 's["cameras"][0]["resolution"] = [16, 16]'
"$bin" render "$small" -o "$tmp/t16.exr" --spp 2 --seed 9 -q --set white.albedo=0.5 2>/dev/null || fail "fixture t16.exr"
"$bin" render "$small" -o "$tmp/t64.exr" --resolution 64x64 --spp 1 -q 2>/dev/null || fail "fixture t64.exr"
v() { scene_variant "$small" "$tmp/small/$1.json" "$2"; echo "$tmp/small/$1.json"; }

# ---------------------------------------------------------------------------------------------
# Scene files.
expect_error missing_scene "nope.json" "not found" -- render "$tmp/nope.json" -o out_missing.exr
printf '{\n  "integrator": {"spp": 4},\n  "cameras": [}\n' >malformed.json
expect_error malformed_json "malformed.json" "re:malformed.json: 3:[0-9]+" "malformed JSON" -- \
  render malformed.json -o out_malformed.exr
expect_error unknown_top_key "/" "unknown key 'integratr'" -- render "$(v top 's["integratr"] = {}')" -o o.exr
expect_error unknown_nested_key "top2.json" "/materials/white" "unknown key 'albdo'" -- \
  render "$(v top2 's["materials"]["white"]["albdo"] = 1')" -o o.exr
expect_error unknown_camera_key "/cameras/1" "fovv" -- render "$(v cam 's["cameras"][1]["fovv"] = 1')" -o o.exr
expect_error unknown_deep_key "/shapes/2/transform/rotate" "angel" -- \
  render "$(v rot 's["shapes"][2]["transform"]["rotate"] = {"axis": [1, 0, 0], "angle": 90, "angel": 1}')" -o o.exr
expect_error unknown_material_type "mtype.json" "/materials/red/type" "lambert" -- \
  render "$(v mtype 's["materials"]["red"]["type"] = "lambert"')" -o o.exr
expect_error unknown_material_ref "/shapes/1/material" "nosuch" -- \
  render "$(v umat 's["shapes"][1]["material"] = "nosuch"')" -o o.exr
expect_error negative_radiance "/shapes/5/emitter/radiance" "light.radiance" "negative" -- \
  render "$(v negrad 's["shapes"][5]["emitter"]["radiance"] = [-1, 1, 1]')" -o o.exr
expect_error negative_albedo_json "/materials/red/albedo" "red.albedo" "negative" -- \
  render "$(v negalb 's["materials"]["red"]["albedo"] = [0.5, -0.1, 1]')" -o o.exr
expect_error albedo_above_one "red.albedo" "valid range" -- \
  render "$(v bigalb 's["materials"]["red"]["albedo"] = [0.5, 1.5, 1]')" -o o.exr
expect_error metallic_unknown_key "/materials/red" "unknown key 'ior'" -- \
  render "$(v mrior 's["materials"]["red"] = {"type": "metallic_roughness", "base_color": 0.5, "roughness": 0.3, "metallic": 0.5, "ior": 1.4}')" -o o.exr
expect_error metallic_above_one "red.metallic" "valid range" -- \
  render "$(v mrbig 's["materials"]["red"] = {"type": "metallic_roughness", "base_color": 0.5, "roughness": 0.3, "metallic": 1.5}')" -o o.exr
expect_error metallic_missing "/materials/red" "missing required key 'metallic'" -- \
  render "$(v mrmiss 's["materials"]["red"] = {"type": "metallic_roughness", "base_color": 0.5, "roughness": 0.3}')" -o o.exr
# JSON cannot spell NaN; 1e39 overflows float (→ inf) and 1e999 overflows double (nlohmann
# rejects it while parsing: out_of_range.406 "number overflow").
sed 's/"radiance": \[17, 12, 4\]/"radiance": [1e39, 12, 4]/' "$cornell" >small/inf_radiance.json
expect_error float_overflow_json "inf_radiance.json" "light.radiance" "re:NaN|infinite|finite" -- \
  render small/inf_radiance.json -o o.exr
sed 's/"albedo": \[0.570, 0.043, 0.044\]/"albedo": [1e999, 0.043, 0.044]/' "$cornell" >small/overflow.json
expect_error double_overflow_json "overflow.json" "re:overflow|finite|range" -- render small/overflow.json -o o.exr
# UVs are vertex data like positions and normals: an infinite one must not turn pixels into NaN.
expect_error mesh_uv_not_finite "/shapes/0/uvs" "finite" -- \
  render "$(v infuv 's["shapes"][0] = {"name": "t", "type": "mesh",
  "material": "wall", "positions": [[-1, -1, -1], [1, -1, -1], [0, 1, -1]], "indices": [[0, 1, 2]],
  "uvs": [[0, 0], [1, 0], [0, 1e39]]}')" -o o.exr --spp 1
# Shapes, cameras, materials and media sharing a name share parameter names: a camera named like
# a wall lost its rotate parameter to the wall's without a word.
expect_error pose_param_clash "camera 'main'" "'main.rotate' is already another object's" "rename one" -- \
  render "$(v clash 's["shapes"][0]["name"] = "main"')" -o o.exr --spp 1
# An emitter whose triangles are all degenerate has no area to sample: an image of NaN before.
expect_error emitter_zero_area "emitter 't'" "no area" -- \
  render "$(v zeroarea 's["shapes"].append({"name": "t", "type": "mesh", "material": "wall",
  "emitter": {"radiance": [1, 1, 1]}, "positions": [[0, 0.9, 0], [0.1, 0.9, 0], [0.2, 0.9, 0]],
  "indices": [[0, 1, 2]]})')" -o o.exr --spp 1
printf '{"integrator": {"spp": 4, "spp": 8}}\n' >dupkey.json
expect_error json_duplicate_key "dupkey.json" "key 'spp' appears twice" -- render dupkey.json -o o.exr
expect_error pose_beyond_coordinates "box" "beyond 1e18" -- render "$small" --set plastic_box.scale=1e29 -o o.exr -q
# Errors of a shape's transform or vertices name the shape, not its "type" key.
expect_error shape_degenerate_transform "/shapes/6 ('metal_cube')" "degenerate transform" -- \
  render "$(v zeroscale 's["shapes"][6]["transform"] = {"scale": 0}')" -o o.exr -q
mkdir -p adir.json
expect_error scene_is_directory "adir.json" -- render adir.json -o o.exr
expect_error bad_integrator_value "/integrator" "max_depth" -- \
  render "$(v depth 's["integrator"]["max_depth"] = 0')" -o o.exr

# Textures.
expect_error texture_missing "missing.png" "not found" -- \
  render "$(v texmiss 's["materials"]["wall"]["albedo"]["file"] = "missing.png"')" -o o.exr
head -c 2000 /dev/urandom >small/random.png
expect_error texture_random_bytes "random.png" "unsupported image format" -- \
  render "$(v texrand 's["materials"]["wall"]["albedo"]["file"] = "random.png"')" -o o.exr
head -c 3000 t64.exr >small/trunc.exr
expect_error texture_truncated_exr "trunc.exr" "re:cannot read|corrupt" -- \
  render "$(v textrunc 's["materials"]["wall"]["albedo"]["file"] = "trunc.exr"')" -o o.exr
head -c 100 t64.exr >small/trunc_header.exr
expect_error texture_truncated_exr_header "trunc_header.exr" "re:cannot read|corrupt" -- \
  render "$(v textrunch 's["materials"]["wall"]["albedo"]["file"] = "trunc_header.exr"')" -o o.exr
# A PNG signature followed by garbage, and a PNG cut in its pixel data: libpng's own error
# output must not reach stderr as extra lines.
{ printf '\x89PNG\r\n\x1a\n'; head -c 500 /dev/urandom; } >small/badsig.png
expect_error texture_png_garbage_after_signature "badsig.png" "re:cannot read|corrupt" -- \
  render "$(v texsig 's["materials"]["wall"]["albedo"]["file"] = "badsig.png"')" -o o.exr
head -c 200 "$repo/scenes/cornell/wall.png" >small/cut.png
expect_error texture_png_truncated "cut.png" "re:cannot read|corrupt" -- \
  render "$(v texcut 's["materials"]["wall"]["albedo"]["file"] = "cut.png"')" -o o.exr
# A name with a NUL byte: the system would open "random.png" while the reader was chosen from
# the rest (".qt" once reached OpenImageIO's FFmpeg plugin, which leaked; found by fuzz_set).
expect_error texture_nul_in_file_name "random.png" "NUL byte" -- \
  render "$(v texnul 's["materials"]["wall"]["albedo"]["file"] = "random.png\x00.qt"')" -o o.exr
# Headers that claim more pixels than the file holds are refused before the allocation: a PFM of
# 16384² pixels in 768 bytes (3.2 GB allocated first), a PNG of 16000² in 71 bytes (768 MB), and
# the same PNG as a glTF image (tinygltf's decoder allocated for it); PFM magic and length exact.
python3 - <<'PY'
import struct, zlib
open("small/claim.pfm", "wb").write(b"PF\n16384 16384\n-1\n" + bytes(768))
open("small/pf4.pfm", "wb").write(b"PF4\n8 8\n-1\n" + bytes(768))
open("small/trailing.pfm", "wb").write(b"PF\n8 8\n-1\n" + bytes(768 + 5))
def chunk(t, d): return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))
png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 16000, 16000, 8, 2, 0, 0, 0)) +
       chunk(b"IDAT", zlib.compress(bytes(400))) + chunk(b"IEND", b""))
open("small/claim.png", "wb").write(png)
PY
expect_error_small texture_pfm_claims_gigabytes "claim.pfm" "shorter than its 16384 x 16384 pixels" -- \
  render "$small" --set wall.albedo=small/claim.pfm -o o.exr -q
expect_error texture_pfm_magic "pf4.pfm" "PFM magic" -- render "$small" --set wall.albedo=small/pf4.pfm -o o.exr -q
expect_error texture_pfm_trailing "trailing.pfm" "longer than its 8 x 8 pixels" -- \
  render "$small" --set wall.albedo=small/trailing.pfm -o o.exr -q
expect_error_small texture_png_claims_gigabytes "claim.png" "cannot hold a PNG of 16000 x 16000 pixels" -- \
  render "$small" --set wall.albedo=small/claim.png -o o.exr -q
expect_error_small target_png_claims_gigabytes "claim.png" "cannot hold" -- \
  grad "$small" --spp 1 --target small/claim.png --out g_claim -q

# Bytes no supported reader claims are refused before any OpenImageIO plugin sees them.
printf 'SIMPLE  =                    T' >small/fits.png
expect_error texture_unknown_format "fits.png" "unsupported image format" -- \
  render "$(v texfits 's["materials"]["wall"]["albedo"]["file"] = "fits.png"')" -o o.exr

# Mitsuba XML. A scene that warns and then fails prints its error alone (warnings are printed
# once the scene has loaded); references that lead back to themselves are errors, not a stack
# overflow.
xml_sensor='<sensor type="perspective"><float name="fov" value="40"/><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>'
printf '<scene version="3.0.0">\n%s\n<bsdf type="conductor" id="g"/>\n<shape type="disk"/>\n</scene>\n' "$xml_sensor" >warn_then_fail.xml
expect_error xml_warning_then_error "warn_then_fail.xml" "line 4" "unsupported shape type" -- \
  render warn_then_fail.xml -o o.exr -q
# --set with an 8-bit image into a texture declared "linear" keeps that colour space (it was
# sRGB-decoded whatever the texture said: a linear roughness 0.52 became 0.23). The render with
# the texture replaced by its own file is the render without --set, bit for bit.
oiiotool --pattern checker:width=2:height=2:color1=0.8,0.2,0.1:color2=0.1,0.5,0.8 8x8 3 -d uint8 -o "$tmp/lin8.png"
linear_scene="$(v linear_wall 's["materials"]["wall"]["albedo"] = {"type": "bitmap", "file": "'"$tmp"'/lin8.png", "color_space": "linear"}')"
expect_ok set_linear_a render "$linear_scene" -o "$tmp/lin_a.pfm" --spp 2 -q &&
  expect_ok set_linear_b render "$linear_scene" -o "$tmp/lin_b.pfm" --spp 2 -q --set "wall.albedo=$tmp/lin8.png" &&
  { cmp -s "$tmp/lin_a.pfm" "$tmp/lin_b.pfm" || fail "--set of a linear texture's own 8-bit file changed the render"; }
# An empty file name names the scene and the key (it was "backlight: : file not found").
expect_error empty_texture_file "/materials/wall/albedo/file" "file name is empty" -- \
  render "$(v empty_file 's["materials"]["wall"]["albedo"]["file"] = ""')" -o o.exr -q
# max_depth -1 with Russian roulette off in a closed room: the throughput underflows to 0 (albedo
# 0.01: after ~25 bounces) and the path went on for ever (render and grad never finished). Now it
# ends when nothing more can reach the film.
cat > closed_room.json <<'JSON'
{"integrator": {"spp": 1, "max_depth": -1, "rr_depth": 0},
 "cameras": [{"name": "c", "origin": [0, 0, 0.5], "target": [0, 0, 0], "fov": 60, "resolution": [4, 4]}],
 "materials": {"w": {"type": "diffuse", "albedo": [0.01, 0.01, 0.01]}},
 "shapes": [{"name": "box", "type": "cube", "material": "w"},
            {"name": "l", "type": "rectangle", "material": "w", "emitter": {"radiance": [1, 1, 1]},
             "transform": {"scale": 0.2, "rotate": {"axis": [1, 0, 0], "angle": 90}, "translate": [0, 0.9, 0]}}]}
JSON
for args in "render closed_room.json -o closed_room.exr" "grad closed_room.json --adjoint-image t16.exr --out g_closed --resolution 16x16" \
            "grad closed_room.json --adjoint-image t16.exr --out g_closed_t --resolution 16x16 --method taped"; do
  rc=0
  # shellcheck disable=SC2086
  timeout 60 "$bin" $args -q --threads 1 > /dev/null 2> err.closed_room || rc=$?
  [ $rc -eq 0 ] || fail "closed room, max_depth -1, rr_depth 0 ($args): exit $rc (124: did not finish): $(cat err.closed_room)"
done
# A Mitsuba conductor without eta/k (material "none": F = specular_reflectance at every angle) is
# rendered with Schlick's rise to 1 at grazing angles: said once, as a warning.
printf '<scene version="3.0.0">\n%s\n<shape type="rectangle"><bsdf type="conductor"><rgb name="specular_reflectance" value="0.3"/></bsdf></shape>\n</scene>\n' "$xml_sensor" >conductor_none.xml
expect_ok xml_conductor_none render conductor_none.xml -o "$tmp/conductor_none.exr" -q &&
  { grep -q "material \"none\" reflects specular_reflectance at every angle" "$tmp/err.xml_conductor_none" ||
      fail "xml_conductor_none: no warning: $(cat "$tmp/err.xml_conductor_none")"; }
# An emitter on a null-material shape: crossed without a vertex, its emission was left out (a lamp
# 24% too dark in JSON, all black from XML). Refused, in both formats.
printf '<scene version="3.0.0">\n%s\n<shape type="rectangle"><bsdf type="null"/><emitter type="area"><rgb name="radiance" value="3"/></emitter></shape>\n</scene>\n' "$xml_sensor" >null_emitter.xml
expect_error xml_null_emitter "null_emitter.xml" "line 3" "emitter on a shape whose material is null" -- \
  render null_emitter.xml -o o.exr -q
expect_error null_emitter "/shapes/" "emitter on a shape whose material is null" -- \
  render "$(v null_emitter 's["materials"]["nullmat"] = {"type": "null"}
for sh in s["shapes"]:
    if "emitter" in sh: sh["material"] = "nullmat"')" -o o.exr -q
printf '<scene version="3.0.0">\n%s\n<bsdf type="twosided" id="a"><ref id="b"/></bsdf>\n<bsdf type="twosided" id="b"><ref id="a"/></bsdf>\n</scene>\n' "$xml_sensor" >ref_cycle.xml
expect_error xml_reference_cycle "ref_cycle.xml" "twosided bsdf inside a twosided bsdf" -- params ref_cycle.xml
# A missing mesh names the XML file, line and element (it named only the mesh file); Mitsuba's
# path integrator ignores media, so a medium under it is an error; a far_clip that clips the scene
# is an error (backlight's camera rays are not clipped).
printf '<scene version="3.0.0">\n%s\n<shape type="obj"><string name="filename" value="nope.obj"/></shape>\n</scene>\n' \
  "$xml_sensor" >missing_mesh.xml
expect_error xml_missing_mesh "missing_mesh.xml: line 3: <string name=\"filename\">: file 'nope.obj' not found" -- \
  render missing_mesh.xml -o o.exr -q
printf '<scene version="3.0.0">\n<integrator type="path"/>\n%s\n<shape type="cube"><bsdf type="null"/><medium type="homogeneous" name="interior"/></shape>\n</scene>\n' \
  "$xml_sensor" >path_fog.xml
expect_error xml_path_ignores_media "path_fog.xml: line 2: <integrator type=\"path\">" \
  "integrator 'path' ignores media in Mitsuba 3: use volpath or prbvolpath" -- render path_fog.xml -o o.exr -q
printf '<scene version="3.0.0">\n<sensor type="perspective"><float name="fov" value="40"/><float name="far_clip" value="2"/><transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0"/></transform></sensor>\n<shape type="cube"/>\n</scene>\n' \
  >far_clip.xml
expect_error xml_far_clip "far_clip.xml: line 2: <float name=\"far_clip\">: far_clip 2 clips shape" -- \
  render far_clip.xml -o o.exr -q
# Approximations keep one warning each: a plastic's diffuse lobe lacks Mitsuba's internal
# scattering factor; a scene without an integrator is rendered as Mitsuba's path.
printf '<scene version="3.0.0">\n%s\n<shape type="cube"><bsdf type="plastic"/></shape>\n</scene>\n' "$xml_sensor" >plastic.xml
if expect_ok xml_plastic_warnings render plastic.xml -o plastic.exr -q; then
  grep -qF "line 3: <bsdf type=\"plastic\">: Mitsuba scales a plastic's diffuse lobe by 1/(η²(1 − F_dr))" err.xml_plastic_warnings ||
    fail "xml_plastic_warnings: no internal-scattering warning: $(cat err.xml_plastic_warnings)"
  grep -qF 'no <integrator>: rendered as <integrator type="path"/>' err.xml_plastic_warnings ||
    fail "xml_plastic_warnings: no missing-integrator warning: $(cat err.xml_plastic_warnings)"
fi

# glTF.
head -c 1000 /dev/urandom >garbage.gltf
expect_error gltf_garbage "garbage.gltf" "invalid glTF" -- render garbage.gltf -o o.exr --resolution 8x8 --spp 1
mkdir -p nobin && cp "$gltf_dir/scene.gltf" "$gltf_dir/checker.png" nobin/
expect_error gltf_missing_bin "scene.gltf" "scene.bin" -- render nobin/scene.gltf -o o.exr --resolution 8x8 --spp 1
mkdir -p g && cp "$gltf_dir"/* g/
gv() { scene_variant "$tmp/g/scene.gltf" "$tmp/g/$1.gltf" "$2"; echo "$tmp/g/$1.gltf"; }
expect_error gltf_accessor_index "accessor.gltf" "accessor" -- \
  render "$(gv accessor 's["meshes"][1]["primitives"][0]["attributes"]["POSITION"] = 99')" \
    -o o.exr --resolution 8x8 --spp 1
expect_error gltf_accessor_past_end "count.gltf" "accessor" "past the end" -- \
  render "$(gv count 's["accessors"][4]["count"] = 100000')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_index_accessor_past_end "icount.gltf" "past the end" -- \
  render "$(gv icount 's["accessors"][7]["count"] = 10**6')" -o o.exr --resolution 8x8 --spp 1
# Negative or fractional offsets, strides and indices tinygltf read as 0 or as absent (a byteOffset
# of -48 read the data from 0; a material of -1 rendered the default material), and a mesh with no
# primitives, which drew nothing: each names the object and the property.
expect_error gltf_view_offset_negative "bvneg.gltf" "buffer view 1: byteOffset must be a non-negative integer" -- \
  render "$(gv bvneg 's["bufferViews"][1]["byteOffset"] = -48')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_view_offset_fraction "bvfrac.gltf" "buffer view 1: byteOffset" "48.5" -- \
  render "$(gv bvfrac 's["bufferViews"][1]["byteOffset"] = 48.5')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_view_stride_negative "bvstride.gltf" "buffer view 1: byteStride must be" -- \
  render "$(gv bvstride 's["bufferViews"][1]["byteStride"] = -12')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_primitive_material_negative "pmat.gltf" "primitive 0: material must be a non-negative integer" -- \
  render "$(gv pmat 's["meshes"][0]["primitives"][0]["material"] = -1')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_primitive_mode_negative "pmode.gltf" "primitive 0: mode must be" -- \
  render "$(gv pmode 's["meshes"][0]["primitives"][0]["mode"] = -1')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_mesh_no_primitives "noprim.gltf" "has no primitives" -- \
  render "$(gv noprim 's["meshes"][0]["primitives"] = []')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_texture_sampler_negative "tsamp.gltf" "texture 0: sampler must be" -- \
  render "$(gv tsamp 's["textures"][0]["sampler"] = -1')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_buffer_view_buffer "bvbuf.gltf" "re:buffer" -- \
  render "$(gv bvbuf 's["bufferViews"][0]["buffer"] = 5')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_node "node.gltf" "node" -- \
  render "$(gv node 's["scenes"][0]["nodes"] = [0, 77]')" -o o.exr --resolution 8x8 --spp 1
cp small/claim.png g/claim.png
# A JPEG's start-of-frame claiming 65535² pixels (4.3 G, over the limit) followed by garbage.
printf '\xff\xd8\xff\xc0\x00\x11\x08\xff\xff\xff\xff\x03\x01\x22\x00\x02\x11\x01\x03\x11\x01garbage' >g/claim.jpg
expect_error_small gltf_jpeg_claims_gigabytes "claimjpg.gltf" "exceeds the limit" -- \
  render "$(gv claimjpg 's["images"][0] = {"uri": "claim.jpg"}')" -o o.exr --resolution 8x8 --spp 1
expect_error_small gltf_image_claims_gigabytes "claimimg.gltf" "cannot hold a PNG of 16000 x 16000 pixels" -- \
  render "$(gv claimimg 's["images"][0] = {"uri": "claim.png"}')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_texture_index "texidx.gltf" "texture" -- \
  render "$(gv texidx 's["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"] = 42')" \
    -o o.exr --resolution 8x8 --spp 1
expect_error gltf_camera_index "camidx.gltf" "camera" -- \
  render "$(gv camidx 's["nodes"][5]["camera"] = 42')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_zero_fov "yfov0.gltf" "re:fov|yfov" -- \
  render "$(gv yfov0 's["cameras"][0]["perspective"]["yfov"] = 0')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_color_type "color.gltf" "COLOR_0 (accessor 6): expected VEC3 or VEC4" -- \
  render "$(gv color 's["meshes"][1]["primitives"][0]["attributes"]["COLOR_0"] = 6')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_shape_in_json "garbage.gltf" "invalid glTF" -- \
  render "$(v gshape 's["shapes"][0] = {"name": "g", "type": "gltf", "file": "../garbage.gltf", "material": "white"}')" \
    -o o.exr --resolution 8x8 --spp 1
# glTF constructs backlight cannot render as the specification says are refused by name.
expect_error gltf_morph_targets "morph.gltf" "mesh 'gold_cube' primitive 0: morph targets with weights other than 0" -- \
  render "$(gv morph 's["meshes"][1]["primitives"][0]["targets"] = [{"POSITION": 5}]; s["meshes"][1]["weights"] = [1]')" \
    -o o.exr --resolution 8x8 --spp 1
expect_error gltf_skin "skin.gltf" "node 2 ('gold_cube'): skins (skeletal animation) are not supported" -- \
  render "$(gv skin 's["accessors"].append({"componentType": 5126, "count": 1, "type": "MAT4"})
s["skins"] = [{"joints": [2], "inverseBindMatrices": 16}]; s["nodes"][2]["skin"] = 0')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_alpha_blend "blend.gltf" "material 'gold': alphaMode BLEND blends where alpha < 1" -- \
  render "$(gv blend 's["materials"][1]["alphaMode"] = "BLEND"
s["materials"][1]["pbrMetallicRoughness"]["baseColorFactor"][3] = 0.5')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_orthographic "ortho.gltf" "camera 0: orthographic cameras are not supported" -- \
  render "$(gv ortho 's["cameras"][0] = {"type": "orthographic",
"orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 100}}')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_zfar "zfar.gltf" "camera 0: zfar 5 clips shape 'ground'" -- \
  render "$(gv zfar 's["cameras"][0]["perspective"]["zfar"] = 5')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_nearest "nearest.gltf" "sampler 0: magFilter 9728 (NEAREST) is not supported" -- \
  render "$(gv nearest 's["samplers"][0]["magFilter"] = 9728')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_version "v1.gltf" "asset.version 1.0: backlight reads glTF 2.x files only" -- \
  render "$(gv v1 's["asset"]["version"] = "1.0"')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_missing_image "noimg.gltf" "image 0 'nope.png': file not found or unreadable" -- \
  render "$(gv noimg 's["images"][0]["uri"] = "nope.png"')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_index_count "icount5.gltf" "indices (accessor 3): count 5 is not a multiple of 3" -- \
  render "$(gv icount5 's["accessors"][3]["count"] = 5')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_camera_mirror "cammirror.gltf" "camera 0: its node's world transform mirrors" -- \
  render "$(gv cammirror 's["nodes"][5]["scale"] = [-1, 1, 1]')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_yfov_missing "noyfov.gltf" "camera 0: perspective.yfov is missing" -- \
  render "$(gv noyfov 'del s["cameras"][0]["perspective"]["yfov"]')" -o o.exr --resolution 8x8 --spp 1
expect_error gltf_negative_index "negcam.gltf" "node 5 ('camera'): camera must be a non-negative integer" -- \
  render "$(gv negcam 's["nodes"][5]["camera"] = -1')" -o o.exr --resolution 8x8 --spp 1
# What backlight ignores or skips gets one warning per file.
if expect_ok gltf_ignored_maps render "$(gv maps 's["materials"][0]["normalTexture"] = {"index": 0}
s["materials"][2]["occlusionTexture"] = {"index": 0}')" -o maps.exr --resolution 8x8 --spp 1 -q; then
  { [ "$(grep -c warning err.gltf_ignored_maps)" -eq 1 ] &&
    grep -qF "maps.gltf: warning: material 'ground': normalTexture (shading uses the mesh's normals) is ignored (so are those of 1 more materials)" err.gltf_ignored_maps; } ||
    fail "gltf_ignored_maps: expected one warning naming the normal texture: $(cat err.gltf_ignored_maps)"
fi
if expect_ok gltf_zero_scale render "$(gv scale0 's["nodes"][1]["scale"] = [0, 0, 0]')" -o scale0.exr \
  --resolution 8x8 --spp 1 -q; then
  { [ "$(grep -c warning err.gltf_zero_scale)" -eq 1 ] &&
    grep -qF "scale0.gltf: warning: node 2 ('gold_cube'): its world transform scales to 0 (determinant 0), so its mesh 'gold_cube' is not rendered (nor are the meshes of 1 more such nodes)" err.gltf_zero_scale; } ||
    fail "gltf_zero_scale: expected one warning naming the hidden nodes: $(cat err.gltf_zero_scale)"
fi

# Media.
mkdir -p vol && cp "$repo/scenes/mitsuba-volume/scene.json" "$repo/scenes/mitsuba-volume/density.vol" vol/
vv() { scene_variant "$tmp/vol/scene.json" "$tmp/vol/$1.json" "$2"; echo "$tmp/vol/$1.json"; }
expect_error medium_unknown_interior "/shapes/6" "unknown medium 'fgo'" -- \
  render "$(vv badint 's["shapes"][6]["interior"] = "fgo"')" -o o.exr --spp 1 -q
expect_error medium_camera_unknown "/cameras/0" "unknown medium 'air'" -- \
  render "$(vv badcam 's["cameras"][0]["medium"] = "air"')" -o o.exr --spp 1 -q
expect_error medium_homogeneous_grid "/media/smoke" "homogeneous medium takes a number" -- \
  render "$(vv homgrid 's["media"]["smoke"]["type"] = "homogeneous"; s["media"]["smoke"].pop("bbox")')" -o o.exr -q
expect_error medium_negative_density "smoke.density" "re:negative|range|below" -- \
  render "$(vv negdens 's["media"]["smoke"]["type"] = "homogeneous"; s["media"]["smoke"]["density"] = -1;
s["media"]["smoke"].pop("bbox")')" -o o.exr -q
expect_error medium_unknown_key "/media/smoke" "unknown key 'sigma'" -- \
  render "$(vv badkey 's["media"]["smoke"]["sigma"] = 1')" -o o.exr -q
expect_error medium_headroom "majorant_headroom" -- \
  render "$(vv headroom 's["media"]["smoke"]["majorant_headroom"] = 1.0')" -o o.exr -q
expect_error medium_light_derivatives "light_derivatives" -- \
  render "$(vv lightder 's["media"]["smoke"]["light_derivatives"] = 1.5')" -o o.exr -q
expect_error medium_light_derivatives_type "light_derivatives" "expected a number" -- \
  render "$(vv lightdertype 's["media"]["smoke"]["light_derivatives"] = "yes"')" -o o.exr -q
python3 - <<'PY'
import struct
head = open("vol/density.vol", "rb").read(48)
n = 64 * 64 * 64
vals = [0.5] * n
vals[1234] = float("nan")
open("vol/nan.vol", "wb").write(head + struct.pack("<%df" % n, *vals))
vals[1234] = -0.25
open("vol/negative.vol", "wb").write(head + struct.pack("<%df" % n, *vals))
small = bytearray(head)
small[8:20] = struct.pack("<3i", 8, 8, 8)
open("vol/small.vol", "wb").write(bytes(small) + struct.pack("<512f", *([0.5] * 512)))
huge = bytearray(head)  # 2048³ voxels (32 GB of floats) announced by a 48-byte file
huge[8:20] = struct.pack("<3i", 2048, 2048, 2048)
open("vol/huge.vol", "wb").write(bytes(huge))
PY
expect_error medium_nan_voxel "nan.vol" "re:finite|NaN" -- \
  render "$(vv nanvox 's["media"]["smoke"]["density"]["file"] = "nan.vol"')" -o o.exr -q
expect_error medium_negative_voxel "smoke.density" "re:negative|range|below" -- \
  render "$(vv negvox 's["media"]["smoke"]["density"]["file"] = "negative.vol"')" -o o.exr -q
expect_error set_grid_wrong_size "small.vol" "[8,8,8,1]" "[64,64,64,1]" -- \
  render vol/scene.json -o o.exr --spp 1 --set smoke.density=vol/small.vol -q
expect_error set_grid_nan "nan.vol" "re:finite|NaN" -- \
  render vol/scene.json -o o.exr --spp 1 --set smoke.density=vol/nan.vol -q
# Refused from the header, before anything is allocated (the grid would take 32 GB).
expect_error medium_grid_too_large "huge.vol" "exceeds the limit" -- \
  render "$(vv hugevox 's["media"]["smoke"]["density"]["file"] = "huge.vol"')" -o o.exr -q
expect_error set_grid_too_large "huge.vol" "exceeds the limit" -- \
  render vol/scene.json -o o.exr --spp 1 --set smoke.density=vol/huge.vol -q
# A grid box must have an extent whose reciprocal is finite: a denormal one (1e-40) gave NaN pixels.
expect_error medium_bbox_denormal "/media/smoke/bbox" "positive, finite extent" -- \
  render "$(vv bboxtiny 's["media"]["smoke"]["bbox"] = {"min": [0, -1, -1], "max": [1e-40, 1, 1]}')" -o o.exr -q
expect_error medium_bbox_inverted "/media/smoke/bbox" "positive, finite extent" -- \
  render "$(vv bboxinv 's["media"]["smoke"]["bbox"] = {"min": [1, -1, -1], "max": [0, 1, 1]}')" -o o.exr -q
# Extinction beyond float's range (each value within its own range) or optically solid: tracking
# never finished (a homogeneous majorant of inf steps by 0; steps of 1e-20 no longer advance t).
expect_error medium_extinction_overflow "medium 'smoke'" "exceeds float's range" -- \
  render "$(vv overflow 's["media"]["smoke"]["type"] = "homogeneous"; s["media"]["smoke"]["density"] = 1e30;
s["media"]["smoke"]["scale"] = 1e9; s["media"]["smoke"].pop("bbox")')" -o o.exr --spp 1 -q
expect_error medium_optically_solid "medium 'smoke'" "one majorant block" "beyond the limit of 1e+06" -- \
  render vol/scene.json -o o.exr --spp 1 -q --set smoke.scale=1e20
# A box 2e30 wide: the block's diagonal overflowed float and the message said "~inf tracking steps".
expect_error medium_huge_box "medium 'smoke'" "re:~[0-9.e+]+ tracking steps" "size of its box" -- \
  render "$(vv hugebox 's["media"]["smoke"]["bbox"] = {"min": [-1e30, -1e30, -1e30], "max": [1e30, 1e30, 1e30]}')" -o o.exr -q
# g outside (-0.999, 0.999) below 0 is not "(negative)": g may be negative.
expect_error_now medium_g_range "smoke.g" "valid range" -- render vol/scene.json -o o.exr -q --set smoke.g=-1
! grep -q "(negative)" "$tmp/err.medium_g_range" || fail "medium_g_range: g = -1 called negative: $(cat "$tmp/err.medium_g_range")"
expect_error rb_with_media "scene.json" "rb does not support scenes with media" -- \
  grad vol/scene.json --method rb --spp 1 --adjoint-image "$repo/tests/data/mitsuba3-volume/adjoint.exr" --out g_rb -q

# --set.
expect_error set_unknown_param "unknown.param" "unknown parameter" -- render "$small" -o o.exr --set unknown.param=1
expect_error set_image_wrong_size "img75.exr" "7x5" "wall.albedo" "[8,8,3]" -- \
  render "$small" -o o.exr --set wall.albedo=img75.exr
expect_error set_nan "white.albedo" "re:NaN|not a (finite )?number" -- render "$small" -o o.exr --set white.albedo=nan
expect_error set_inf "white.albedo" "re:NaN|infinite|finite" -- render "$small" -o o.exr --set white.albedo=1e999
expect_error set_negative "white.albedo" "negative" -- render "$small" -o o.exr --set white.albedo=-0.5,0.5,0.5
# Geometry parameters (scenes/pose: a diffuse box on a floor under a square light).
pose="$repo/scenes/pose/scene.json"
pose_ones="$tmp/pose_adjoint.exr" cornell_ones="$tmp/cornell_adjoint.exr"
"$bin" render "$pose" -o "$pose_ones" --spp 1 -q 2>/dev/null || fail "render of the pose scene failed"
"$bin" render "$cornell" -o "$cornell_ones" --resolution 32x32 --spp 1 -q 2>/dev/null || fail "render of cornell failed"
expect_error set_positions_count "box.positions" "got 5 values" "[24,3]" -- \
  render "$pose" -o o.exr --set box.positions=1,2,3,4,5
# A number list longer than a file name may be (255 bytes) was refused as an unusable file name;
# the box's own 72 coordinates, 12 digits each, render.
expect_error set_long_number_list "white.albedo" "got 24 values" -- \
  render "$small" -o o.exr --set "white.albedo=$(python3 -c 'print(",".join(["0.123456789"] * 24))')"
"$bin" params "$pose" --dump pose_dump -q >/dev/null 2>&1 || fail "params --dump of the pose scene failed"
box_positions="$(python3 -c '
import json, sys
v = json.load(open(sys.argv[1]))
v = v.get("box.positions", v)
v = v["value"] if isinstance(v, dict) else v
flat = [x for row in v for x in (row if isinstance(row, list) else [row])]
print(",".join(f"{x:.10f}" for x in flat))' pose_dump/params.json)"
[ "${#box_positions}" -gt 300 ] || fail "set_long_positions: the list of box.positions is ${#box_positions} bytes"
expect_ok set_long_positions render "$pose" -o o_long.exr --spp 1 --resolution 8x8 -q --set "box.positions=$box_positions"
expect_error set_positions_ply_count "sphere.ply" "2562 vertices" "box.positions" "[24,3]" -- \
  render "$pose" -o o.exr --set "box.positions=$repo/scenes/deform/sphere.ply"
expect_error set_pose_nan "box.rotate" "re:NaN|not a (finite )?number" -- render "$pose" -o o.exr --set box.rotate=0,nan,0
expect_error set_degenerate "box" "triangle 0" "degenerate" -- render "$pose" -o o.exr --set box.positions=0.5
expect_error set_pose_far "box" "triangle 4 became degenerate" "magnitude 1e+16 float cannot resolve it" -- \
  render "$pose" -o o.exr --set box.translate=1e16,0,0
expect_error set_camera_nan "front.origin" "re:NaN|finite" -- render "$pose" -o o.exr --set front.origin=1,inf,0
expect_error grad_geometry_unsupported "cornell/scene.json" "geometry gradients" "only diffuse surfaces are supported yet" "metal_cube" -- \
  grad "$cornell" --adjoint-image "$cornell_ones" --param metal_cube.translate --resolution 32x32 --spp 1 --out gglossy
expect_error set_count "white.albedo" "2 values" "[3]" -- render "$small" -o o.exr --set white.albedo=0.5,0.5
# Views whose geometry gradient no term estimates were silently wrong (helper-27 audit): refused.
scene_variant "$pose" pose_near.json "s['cameras'][0]['near_clip'] = 3.3"
expect_error grad_geometry_near_cut "pose_near.json" "near plane of camera 'front'" "near_clip 3.3" "cuts shape" -- \
  grad pose_near.json --adjoint-image "$pose_ones" --param box.translate --spp 1 --out g_near
scene_variant "$pose" "$tmp/pose_envmap.json" \
  "s['environment'] = {'type': 'envmap', 'file': '$repo/scenes/smoke/sky.pfm'}"
expect_error grad_geometry_env_rotate "pose_envmap.json" "rotation of camera 'front'" "environment map in view" -- \
  grad "$tmp/pose_envmap.json" --adjoint-image "$pose_ones" --param front.rotate --spp 1 --out g_envrot
expect_ok grad_geometry_env_origin grad "$tmp/pose_envmap.json" --adjoint-image "$pose_ones" --param front.origin \
  --spp 1 --out g_envorigin -q
# Mitsuba's bilinear lookup has a direction gradient: the rotation is estimated (test_geometry_params).
scene_variant "$pose" "$tmp/pose_envmap_bilinear.json" \
  "s['environment'] = {'type': 'envmap', 'file': '$repo/scenes/smoke/sky.pfm', 'convention': 'mitsuba'}"
expect_ok grad_geometry_env_rotate_bilinear grad "$tmp/pose_envmap_bilinear.json" --adjoint-image "$pose_ones" \
  --param front.rotate --spp 1 --out g_envrot_bilinear -q
# An environment's "transform" must be a rotation: the rest is refused by name.
for bad in "translate|{'translate': [1, 0, 0]}|a translation would do nothing" \
           "mirror|{'scale': [-1, 1, 1]}|must be a rotation" "scale|{'scale': 2}|must be a rotation" \
           "shear|{'matrix': [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}|must be a rotation"; do
  IFS='|' read -r name transform message <<<"$bad"
  scene_variant "$pose" "$tmp/pose_env_$name.json" \
    "s['environment'] = {'type': 'envmap', 'file': '$repo/scenes/smoke/sky.pfm', 'transform': $transform}"
  expect_error "env_transform_$name" "pose_env_$name.json" "/environment/transform" "$message" -- \
    render "$tmp/pose_env_$name.json" -o o.exr --spp 1
done
expect_error set_syntax "--set" "white.albedo" -- render "$small" -o o.exr --set white.albedo
expect_error set_corrupt_image "random.png" "unsupported image format" -- \
  render "$small" -o o.exr --set wall.albedo=small/random.png
expect_error set_truncated_exr "trunc.exr" "re:cannot read|corrupt" -- \
  render "$small" -o o.exr --set wall.albedo=small/trunc.exr

# Flags.
expect_error resolution_garbage "--resolution" "garbage" -- render "$small" -o o.exr --resolution garbage
expect_error resolution_zero "--resolution" "0x5" -- render "$small" -o o.exr --resolution 0x5
expect_error resolution_trailing "--resolution" -- render "$small" -o o.exr --resolution 16x16x
# Names that become file names: a scene's camera, shape, material or medium named with a path
# separator or a control character (gradients, targets and snapshots are files named after them).
expect_error camera_name_slash "/cameras/0/name" "path separator" -- \
  render "$(v camera_slash 's["cameras"][0]["name"] = "up/x"')" -o o.exr -q
expect_error shape_name_slash "/name" "path separator" -- \
  render "$(v shape_slash 's["shapes"][0]["name"] = "a/b"')" -o o.exr -q
expect_error material_name_control "material name" 'w\x01' -- \
  render "$(v material_control 's["materials"]["w\x01"] = s["materials"]["white"]')" -o o.exr -q
# An environment map whose texels and scale are each within range but whose product overflows
# float wrote inf pixels with exit 0 (helper-43).
python3 -c 'import struct; open("small/env_huge.pfm", "wb").write(b"PF\n8 4\n-1.0\n" + struct.pack("<96f", *[1e30] * 96))'
expect_error env_overflow "environment" "exceeds float's range" -- \
  render "$(v env_overflow 's["environment"] = {"type": "envmap", "file": "env_huge.pfm", "scale": 1e30}')" -o o.exr -q
# More memory than the process can get is a one-line exit 2, not "internal error: std::bad_alloc"
# (exit 3). Not under AddressSanitizer, whose allocator reports such a request instead of throwing.
if [ -z "${ASAN_OPTIONS:-}" ]; then
  cases=$((cases + 1))
  (ulimit -v 800000 && expect_error_now out_of_memory "out of memory" -- render "$small" -o o.exr --resolution 16384x16384 --spp 1 -q --threads 1) &
fi
# Sides past 2^32 wrapped around to small numbers (4294967304 read as 8) and rendered with exit 0.
expect_error resolution_wrap "--resolution" "4294967304x4294967300" -- render "$small" -o o.exr --resolution 4294967304x4294967300
expect_error resolution_sign "--resolution" -- render "$small" -o o.exr --resolution +8x8
expect_error resolution_empty_side "--resolution" -- render "$small" -o o.exr --resolution 8x
expect_error camera_out_of_range "--camera 99" "5 camera" -- render "$small" -o o.exr --camera 99
expect_error camera_negative "--camera" -- render "$small" -o o.exr --camera -1
expect_error spp_zero "--spp" -- render "$small" -o o.exr --spp 0
expect_error spp_not_a_number "--spp" -- render "$small" -o o.exr --spp abc
expect_error max_depth_zero "--max-depth" -- render "$small" -o o.exr --max-depth 0
expect_error rr_depth_negative "--rr-depth" -- render "$small" -o o.exr --rr-depth -1
expect_error threads_negative "--threads" -- render "$small" -o o.exr --threads -1
expect_error unknown_flag "--bogus" -- render "$small" -o o.exr --bogus
expect_error flag_twice "--spp is given 2 times" "give it once" -- render "$small" -o o.exr --spp 1 --spp 2
expect_error optimize_missing_config "nope.json" "not found" -- optimize nope.json
expect_error no_subcommand "subcommand" --
expect_error unknown_subcommand "frobnicate" -- frobnicate
expect_error output_format "o.bmp" "re:format|\.bmp" -- render "$small" -o o.bmp --spp 1 -q
expect_error output_dir_missing "o.exr" -- render "$small" -o "$tmp/no/such/dir/o.exr" --spp 1 -q

# grad / check.
expect_error grad_target_size "img75.exr" "7x5" "16x16" -- grad "$small" --spp 1 --target img75.exr --out g_err1
expect_error grad_target_missing "nosuch.exr" "not found" -- grad "$small" --spp 1 --target nosuch.exr --out g_err2
expect_error grad_unknown_param "nosuch.param" "unknown parameter" -- \
  grad "$small" --spp 1 --target t16.exr --param nosuch.param --out g_err3
expect_error grad_unknown_method "bogus" "method" -- grad "$small" --spp 1 --target t16.exr --method bogus --out g_err4
expect_error grad_unknown_loss "bogus" "loss" -- grad "$small" --spp 1 --target t16.exr --loss bogus --out g_err5
expect_error grad_no_target "--target" "--adjoint-image" -- grad "$small" --spp 1 --out g_err6
expect_error grad_adjoint_size "img75.exr" "16x16" -- grad "$small" --spp 1 --adjoint-image img75.exr --out g_err7
expect_error grad_memory_budget_syntax "--memory-budget" "lots" -- \
  grad "$small" --spp 1 --target t16.exr --method taped --memory-budget lots --out g_err8
# The taped mode must refuse a tape it cannot hold, stating the projected size and the budget.
# Without -q: a progress line left behind on stderr would break the one-line contract.
expect_error taped_memory_budget "re:[0-9]+ MB" "budget" "re:budget of 1 MB" -- \
  grad "$cornell" --resolution 64x64 --target t64.exr --method taped --memory-budget 1MB --out g_err9
# A budget under a megabyte is stated as such (it was "the memory budget of 0 MB").
expect_error taped_memory_budget_small "budget of 0.001 MB" -- \
  grad "$small" --spp 1 --target t16.exr --method taped --memory-budget 1KB --out g_err9b -q
# The budget holds within a tile: the guard looked only after each 16x16 tile, so one tile at
# 4096 spp recorded ~1.7 GB before a 10 MB budget was compared (a helper-34 audit: 423 MB at 1024
# spp). With no room for that, it must stop on the recorded size after a few samples.
expect_error_small taped_budget_within_tile "already needs" "re:after [0-9.]+% of the samples" "budget of 10 MB" -- \
  grad "$small" --spp 4096 --target t16.exr --method taped --memory-budget 10MB --out g_err9c -q
expect_error check_unknown_param "nosuch" "unknown parameter" -- check "$small" --spp 1 --target t16.exr --param nosuch
expect_error check_directions "--directions" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --directions 0 --rr-depth 0
# Overflow: a radiance near float's limit (inside its valid range) and an adjoint of 3e38 gave inf
# and NaN gradients, written with exit 0.
expect_error grad_overflow_radiance "the gradient of" "not finite" -- \
  grad "$small" --spp 1 --target t16.exr --set light.radiance=1e30 --out g_overflow -q
python3 -c "
import struct
w, h = 16, 16
open('big_adjoint.pfm', 'wb').write(b'PF\\n%d %d\\n-1\\n' % (w, h) + struct.pack('<%df' % (w * h * 3), *([3e38] * (w * h * 3))))"
expect_error grad_overflow_adjoint "not finite" -- \
  grad "$small" --spp 1 --adjoint-image big_adjoint.pfm --out g_overflow2 -q
# A grad whose writing fails half-way (here: a folder where a gradient image goes) leaves no
# gradients.json from an earlier run naming a mix of old and new files.
grad_partial() {
  expect_ok grad_partial_first grad "$small" --spp 1 --target t16.exr --out g_partial -q --param wall.albedo || return
  [ -f g_partial/gradients.json ] || { fail "grad wrote no gradients.json"; return; }
  rm g_partial/wall.albedo.grad.exr && mkdir g_partial/wall.albedo.grad.exr
  expect_error_now grad_partial_second "wall.albedo.grad.exr" "is a folder" -- \
    grad "$small" --spp 1 --target t16.exr --out g_partial -q --param wall.albedo
  [ ! -e g_partial/gradients.json ] || fail "a grad that failed half-way left the earlier gradients.json"
}
in_background grad_partial
# Seeds are non-negative integers within 64 bits (-1 and 10^23 both became 2^64 - 1).
expect_error seed_negative "--seed" "not a non-negative integer" -- render "$small" --seed -1 -o o.exr --spp 1 -q
expect_error seed_overflow "--seed" "exceeds 2^64" -- render "$small" --seed 99999999999999999999999 -o o.exr -q
expect_error adjoint_seed_negative "--adjoint-seed" -- \
  grad "$small" --spp 1 --target t16.exr --adjoint-seed -5 --out g_seed -q
expect_error memory_budget_tiny "--memory-budget" "less than one byte" -- \
  grad "$small" --spp 1 --target t16.exr --method taped --memory-budget 1e-9MB --out g_tiny -q
expect_error resume_empty "--resume" "empty" -- optimize small/opt.json --resume "" -q
# Output and flag problems named at once: -o naming a folder (found by the rename after the whole
# render), -o under a file, an empty --set value, a list with an empty item, an unknown --loss.
mkdir -p out_folder.exr
expect_error output_is_folder "out_folder.exr" "is a folder" -- render "$small" -o out_folder.exr --spp 1 -q
: >plain_file
expect_error output_parent_is_file "plain_file" "is not a folder" -- render "$small" -o plain_file/o.exr -q
expect_error set_empty_value "--set white.albedo" "no value" -- render "$small" --set white.albedo= -o o.exr -q
expect_error set_empty_item "--set white.albedo" "neither numbers nor" -- \
  render "$small" --set white.albedo=0.5,,0.5 -o o.exr -q
expect_error loss_unknown "--loss" "l3" -- grad "$small" --spp 1 --target t16.exr --loss l3 --out g_l3 -q
expect_error check_directions_limit "--directions" "exceeds the limit of" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --directions 2000000000 --rr-depth 0
expect_error check_eps_inf "--eps" "finite" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --eps inf --rr-depth 0
expect_error check_eps_huge "--eps" "not smaller than the width of the valid range [0, 1] of 'white.albedo'" -- \
  check "$small" --spp 1 --target t16.exr --param white.albedo --eps 1e30 --rr-depth 0
# Steps are clamped into the valid range, but a step as wide as the range rendered scenes --set
# refuses (|g| > 1, albedos above 1).
expect_error check_eps_range_width "--eps 1" "not smaller than the width" "white.albedo" -- \
  check "$small" --spp 1 --target t16.exr --param white.albedo --eps 1 --rr-depth 0
expect_error check_seeds_zero "--seeds" "1 .. 65536" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --seeds 0 --rr-depth 0
expect_error check_seeds_huge "--seeds" "1 .. 65536" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --seeds 1000000 --rr-depth 0
expect_error check_tolerance_nan "--tolerance" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --tolerance nan --rr-depth 0
expect_error check_tolerance_negative "--tolerance" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --tolerance -1 --rr-depth 0
# ---------------------------------------------------------------------------------------------
# Hostile inputs: every file of tests/data/bad/ (crafted to crash, hang or exhaust memory in earlier
# versions; see its README.md) through the command that reads it. Each gives one line, status 2,
# no "internal error", no signal, and within the test's time limit (no exponential traversal).
bad="$repo/tests/data/bad"
for f in "$bad"/*; do
  base="$(basename "$f")"
  case "$base" in
    gltf_*|scene_*) expect_error "bad_$base" "$base" -- render "$f" -o "bad_$base.exr" --spp 1 -q ;;
    image_*) expect_error "bad_$base" "$base" -- render "$cornell" --set "wall.albedo=$f" -o "bad_$base.exr" --spp 1 -q ;;
    config_*) expect_error "bad_$base" "$base" -- optimize "$f" -q ;;
    # The OpenVDB reader process gets 1 GB here (default 4 GB): the same verdicts, less memory.
    vdb_*) BACKLIGHT_VDB_MEMORY_MB=1024 expect_error "bad_$base" "$base" -- \
      render "$tmp/vol/scene.json" --set "smoke.density=$f" -o "bad_$base.exr" --spp 1 -q ;;
    make_bad_inputs.py|README.md) ;;
    *) fail "tests/data/bad/$base: no rule says which command reads it (see its README.md)" ;;
  esac
done
long="$(printf 'x%.0s' $(seq 1 300))"  # one path component over NAME_MAX (255)
expect_error long_scene_path "File name too long" -- render "$tmp/$long.json" -o o.exr -q
expect_error long_set_path "white.albedo" -- render "$small" --set "white.albedo=$tmp/$long.png" -o o.exr -q
expect_error long_config_path "File name too long" -- optimize "$tmp/$long.json" -q
expect_error long_output_path "File name too long" -- render "$small" -o "$tmp/$long/o.exr" --spp 1 -q
expect_error render_spp_limit "--spp" "exceeds the limit of" -- render "$small" --spp 2147483647 -o o.exr -q
expect_error grad_spp_limit "--spp" "exceeds the limit of" -- \
  grad "$small" --spp 2147483647 --target t16.exr --out g_err10 -q
: > not_a_folder
expect_error grad_out_is_file "not_a_folder" "not a folder" -- grad "$small" --spp 1 --target t16.exr --out not_a_folder
expect_error grad_out_unwritable "/proc/backlight" "cannot create" -- \
  grad "$small" --spp 1 --target t16.exr --out /proc/backlight/g -q
expect_error params_dump_is_file "not_a_folder" "not a folder" -- params "$small" --dump not_a_folder
# An image output in a folder that takes no new files failed after the render, naming the
# temporary file (write failed ... .x.tmpNNN.exr); it is found before the work now.
expect_error render_output_uncreatable "/proc/self/x.exr" "cannot create files in its folder" -- \
  render "$small" -o /proc/self/x.exr --spp 1 -q
expect_error camera_index_int_range "--camera" -- render "$small" --camera 99999999999 -o o.exr -q
# Files that never end or never open: a FIFO blocked forever, /dev/zero read until memory ran out.
mkfifo fifo.json
expect_error config_fifo "fifo.json" "not a regular file" -- optimize fifo.json -q
expect_error config_dev_zero "/dev/zero" "not a regular file" -- optimize /dev/zero -q
expect_error scene_dev_zero "/dev/zero" "not a regular file" -- render /dev/zero -o o.exr -q
expect_error memory_budget_huge "--memory-budget" "exceeds the limit of" -- \
  grad "$small" --spp 1 --target t16.exr --method taped --memory-budget 1e300GB --out g_err11 -q

# ---------------------------------------------------------------------------------------------
# Corrupt checkpoints: --resume checks every number of state.json and every value and moment
# file (a huge next_iteration ran for ever writing snapshots; NaN values or moments, a negative
# second moment or a negative adam_t made every later loss and value NaN and exited 0).
cat >small/opt.json <<'JSON'
{"scene": "scene.json", "output": "opt_base", "parameters": {"wall.albedo": {"lr": 0.05, "bounds": [0, 1], "init": 0.5}},
 "views": {"cameras": ["main"], "reference": {"set": {"wall.albedo": "wall.png"}, "spp": 1}}, "resolution": [8, 8], "spp": 1, "iterations": 4,
 "checkpoint_every": 2, "snapshot_every": 100, "rmse_resolution": [8, 8]}
JSON
if run_bin out.opt_base err.opt_base optimize small/opt.json -q && [ -f small/opt_base/checkpoint/state.json ]; then
  # corrupt NAME PYTHON: a copy of the finished run with PYTHON applied (d: its checkpoint folder,
  # s: state.json as a dict, written back unless the statement deletes it).
  corrupt() {
    rm -rf "small/opt_$1" && cp -r small/opt_base "small/opt_$1"
    python3 - "small/opt_$1/checkpoint" "$2" <<'PY'
import json, os, struct, sys
d = sys.argv[1]; s = json.load(open(d + "/state.json"))
def put(name, values): open(d + "/" + name, "wb").write(struct.pack("<%df" % len(values), *values))
def size(name): return os.path.getsize(d + "/" + name) // 4
exec(sys.argv[2])
if os.path.isfile(d + "/state.json"): json.dump(s, open(d + "/state.json", "w"))
PY
  }
  resume_error() {  # resume_error NAME PYTHON PATTERN...
    local name="$1" stmt="$2"; shift 2
    corrupt "$name" "$stmt"
    expect_error "resume_$name" "$@" -- optimize small/opt.json --resume "small/opt_$name" -q
  }
  # The finished run's own checkpoint resumes (and finishes at once); its validation losses may be
  # negative (an unbiased estimate near zero).
  rm -rf small/opt_intact && cp -r small/opt_base small/opt_intact
  run_bin out.resume_intact err.resume_intact optimize small/opt.json --resume small/opt_intact -q ||
    fail "resume of an intact checkpoint: $(cat err.resume_intact)"
  resume_error validation_string 's["validation"][0][1] = "x"' "state.json" "validation loss is not a number"
  resume_error next_huge 's["next_iteration"] = 10**15' "state.json" "next_iteration" "outside 0..4"
  resume_error next_negative 's["next_iteration"] = -5' "state.json" "next_iteration"
  resume_error next_float 's["next_iteration"] = 2.5' "state.json" "next_iteration" "not an integer"
  resume_error adam_t_negative 's["parameters"]["wall.albedo"]["adam_t"] = -1' "state.json" "adam_t"
  resume_error adam_t_huge 's["parameters"]["wall.albedo"]["adam_t"] = 10**30' "state.json" "adam_t"
  resume_error seconds_negative 's["seconds"] = -100' "state.json" "seconds"
  resume_error log_row 's["log"][0] = [1, 2]' "state.json" "log"
  # A key missing: the message had nlohmann's "[json.exception.out_of_range.403] " in front of the key.
  resume_error seconds_missing 'del s["seconds"]' "state.json" "checkpoint does not match this config (key 'seconds' not found)"
  resume_error value_nan 'put("wall.albedo.value", [float("nan")] * size("wall.albedo.value"))' \
    "wall.albedo.value" "wall.albedo" "re:NaN|finite"
  resume_error value_range 'put("wall.albedo.value", [-3.0] * size("wall.albedo.value"))' \
    "wall.albedo.value" "wall.albedo"
  resume_error adam_v_negative 'put("wall.albedo.adam_v", [-1.0] * size("wall.albedo.adam_v"))' \
    "wall.albedo.adam_v" "element 0"
  resume_error adam_m_inf 'put("wall.albedo.adam_m", [float("inf")] * size("wall.albedo.adam_m"))' \
    "wall.albedo.adam_m" "element 0"
  resume_error state_fifo 'os.remove(d + "/state.json"); os.mkfifo(d + "/state.json")' "state.json" "not a regular file"
  resume_error state_directory 'os.remove(d + "/state.json"); os.mkdir(d + "/state.json")' "state.json" \
    "not a regular file"
  # What the checkpoint was made from (config, scene, targets) is recorded in state.json and read
  # like the rest of it; a checkpoint of another scene file with other content is refused.
  resume_error made_from_string 's["made_from"] = "x"' "state.json" "/made_from" "expected an object"
  resume_error made_from_config 's["made_from"]["config"] = [1]' "state.json" "/made_from/config"
  resume_error made_from_hash 's["made_from"]["scene"]["content"] = 12' "state.json" "/made_from/scene/content"
  resume_error made_from_target 's["made_from"]["targets"]["main"] = "xyz"' "state.json" "/made_from/targets/main"
  resume_error made_from_file 'del s["made_from"]["scene"]["file"]' "state.json" "/made_from/scene/file"
  resume_error other_scene \
    's["made_from"]["scene"] = {"file": "/elsewhere/scene.json", "bytes": "0123456789abcdef", "content": "0123456789abcdef"}' \
    "state.json" "/elsewhere/scene.json" "small/scene.json" "--resume-any-scene"
  # No checkpoint where a run started: a start without --resume removed the previous run's.
  resume_error no_checkpoint 'import shutil; shutil.rmtree(d)' "no checkpoint" "without --resume"
  # Config errors found before anything is written: no output folder is left behind (the folder
  # and its rendered targets used to be made first), and messages name the config's pointer, not
  # a --set nobody gave.
  config_error() {  # config_error NAME PYTHON PATTERN...: small/opt.json with PYTHON applied to `s`
    local name="$1" stmt="$2"; shift 2
    scene_variant small/opt.json "small/cfg_$name.json" "$stmt; s[\"output\"] = \"cfg_out_$name\""
    expect_error "config_$name" "$@" -- optimize "small/cfg_$name.json" -q
  }
  config_error init_range 's["parameters"]["wall.albedo"]["init"] = 2' "cfg_init_range.json: /parameters/wall.albedo/init" \
    "valid range"
  config_error init_missing_file 's["parameters"]["wall.albedo"]["init"] = "nope.png"' \
    "/parameters/wall.albedo/init" "nope.png"
  config_error reference_set_missing 's["views"]["reference"]["set"]["wall.albedo"] = "nope.png"' \
    "/views/reference/set/wall.albedo" "nope.png"
  config_error set_unknown 's["set"] = {"nosuch.p": 1}' "/set/nosuch.p" "unknown parameter"
  config_error target_missing 's["views"]["targets"] = {"main": "nope.exr"}' "nope.exr"
  config_error target_size 's["views"]["targets"] = {"main": "../img75.exr"}' "img75.exr" "7x5"
  config_error loss_downsample 's["loss_downsample"] = 3' "/loss_downsample" "does not divide"
  config_error image_schedule 's["image_schedule"] = [{"until": 2, "downsample": 3}]' \
    "/image_schedule/0/downsample" "does not divide"
  # Settings that were ignored without a word.
  config_error target_not_a_view 's["views"]["targets"] = {"left": "../img75.exr"}' "/views/targets/left" "not a view"
  config_error schedule_vector 's["parameters"]["light.radiance"] = {"lr": 0.1, "schedule": [{"until": 2, "resolution": [4, 4]}]}' \
    "/parameters/light.radiance/schedule/0/resolution" "only image and grid"
  config_error schedule_xyz_on_image 's["parameters"]["wall.albedo"]["schedule"] = [{"until": 2, "resolution": [4, 4, 4]}]' \
    "/parameters/wall.albedo/schedule/0/resolution" "takes [w, h]"
  config_error decay_every_zero 's["parameters"]["wall.albedo"]["decay"] = {"type": "step", "rate": 0.5, "every": 0}' \
    "/parameters/wall.albedo/decay" "every"
  scene_variant small/opt.json small/cfg_output_empty.json 's["output"] = ""'
  expect_error config_output_empty "/output" "empty folder name" -- optimize small/cfg_output_empty.json -q
  # A view's target is written as targets/NAME.exr: a camera named "../../x" put it outside the
  # output folder (exit 0), "a/b" failed only after the folder was made (helper-43).
  config_error view_traversal \
    's["views"]["cameras"] = [{"name": "../../ESCAPED", "origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 40}]' \
    "/views/cameras/0/name" "ESCAPED"
  config_error view_slash 's["views"]["cameras"] = [{"name": "a/b", "origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 40}]' \
    "/views/cameras/0/name" "path separator"
  config_error view_nul 's["views"]["cameras"] = [{"name": "a\0b", "origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 40}]' \
    "/views/cameras/0/name" 'a\x00b' "NUL"
  # The folder named by the part before a NUL byte was made, then an internal error (exit 3).
  scene_variant small/opt.json small/cfg_output_nul.json 's["output"] = "cfg_nul\0x"'
  expect_error config_output_nul "/output" "NUL byte" -- optimize small/cfg_output_nul.json -q
  # Numbers reach the scene as written (std::to_string kept six decimals: 1.5e-7 became 0).
  scene_variant small/opt.json small/opt_tiny.json \
    's["parameters"]["wall.albedo"]["init"] = 1.5e-7; s["parameters"]["wall.albedo"]["lr"] = 0; s["output"] = "opt_tiny"; s["iterations"] = 2'
  if run_bin out.opt_tiny err.opt_tiny optimize small/opt_tiny.json -q; then
    python3 - small/opt_tiny/checkpoint/wall.albedo.value <<'PY' || fail "init 1.5e-7 did not reach the parameter"
import struct, sys
data = open(sys.argv[1], "rb").read()
v = set(struct.unpack("<%df" % (len(data) // 4), data))
assert v == {struct.unpack("<f", struct.pack("<f", 1.5e-7))[0]}, v
PY
  else
    fail "optimize small/opt_tiny.json: $(cat err.opt_tiny)"
  fi
  # A texture declared linear is written to its PNG linearly, so the PNG read back in its colour
  # space gives its values to 8 bits (a linear roughness of 0.2 was written sRGB-encoded, code 124,
  # and --set of the file gave 0.49).
  scene_variant small/scene.json small/scene_lin.json 's["materials"]["wall"]["albedo"]["color_space"] = "linear"'
  sed -e 's/"scene.json"/"scene_lin.json"/' -e 's/opt_base/opt_lin/' -e 's/"iterations": 4/"iterations": 2/' small/opt.json >small/opt_lin.json
  if run_bin out.opt_lin err.opt_lin optimize small/opt_lin.json -q &&
    run_bin out.lin_dump err.lin_dump params small/scene_lin.json --set wall.albedo=small/opt_lin/final/wall.albedo.png --dump small/lin_dump &&
    oiiotool --dumpdata small/lin_dump/wall.albedo.exr >small/lin_dump.txt; then
    python3 - small/opt_lin/checkpoint/wall.albedo.value small/lin_dump.txt <<'PY' || fail "a linear texture's PNG does not read back as its values"
import struct, sys
data = open(sys.argv[1], "rb").read()
want = struct.unpack("<%df" % (len(data) // 4), data)
got = [float(v) for line in open(sys.argv[2]) if "Pixel (" in line for v in line.split(":")[1].split()]
assert len(got) == len(want) and min(want) < max(want), (len(got), len(want))
err = max(abs(a - b) for a, b in zip(got, want))
assert err <= 0.5 / 255 + 1e-6, err
PY
  else
    fail "optimize small/opt_lin.json: $(cat err.opt_lin err.lin_dump 2>/dev/null)"
  fi
  # A cached target is rendered again when a file of its reference variant changed in place (the
  # cache was keyed on the file's name: the old target stayed).
  cp small/wall.png small/ref.png
  sed -e 's/"wall.png"/"ref.png"/' -e 's/opt_base/opt_cache/' small/opt.json >small/opt_cache.json
  cache_md5() { md5sum small/opt_cache/targets/main.exr | cut -d' ' -f1; }
  if run_bin out.opt_cache err.opt_cache optimize small/opt_cache.json -q; then
    before="$(cache_md5)"
    python3 - small/ref.png <<'PY'
import struct, sys, zlib
def chunk(t, d): return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))
rows = b"".join(b"\0" + bytes([200, 40, 40]) * 8 for _ in range(8))
open(sys.argv[1], "wb").write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 8, 8, 8, 2, 0, 0, 0)) +
                              chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
PY
    run_bin out.opt_cache2 err.opt_cache2 optimize small/opt_cache.json -q || fail "rerun: $(cat err.opt_cache2)"
    [ "$(cache_md5)" != "$before" ] || fail "a changed reference file reused the cached target"
  else
    fail "optimize small/opt_cache.json: $(cat err.opt_cache)"
  fi
  # Steps stay in the parameter's valid range without bounds (an albedo went to [-10, 8]).
  sed -e 's/"lr": 0.05, "bounds": \[0, 1\], "init": 0.5/"lr": 3, "init": 0.5/' -e 's/opt_base/opt_unbounded/' \
    small/opt.json >small/opt_unbounded.json
  if run_bin out.opt_unbounded err.opt_unbounded optimize small/opt_unbounded.json -q; then
    python3 - small/opt_unbounded/checkpoint/wall.albedo.value <<'PY' || fail "unbounded steps left the valid range"
import struct, sys
data = open(sys.argv[1], "rb").read()
v = struct.unpack("<%df" % (len(data) // 4), data)
assert min(v) >= 0 and max(v) <= 1 and min(v) < max(v), (min(v), max(v))
PY
  else
    fail "optimize small/opt_unbounded.json: $(cat err.opt_unbounded)"
  fi
  # Bounds that miss the valid range, and a start outside the bounds (rendered once, then
  # clamped): a box scale bounded to [-5, -1] ran and ended at 1e-6.
  sed -e 's/"bounds": \[0, 1\]/"bounds": [-5, -1]/' -e 's/opt_base/opt_bounds_out/' small/opt.json >small/opt_bounds_out.json
  expect_error optimize_bounds_outside_range "/parameters/wall.albedo/bounds" "[-5, -1] lies outside the valid range [0, 1]" -- \
    optimize small/opt_bounds_out.json -q
  sed -e 's/"bounds": \[0, 1\], "init": 0.5/"bounds": [0.2, 0.6], "init": 0.9/' -e 's/opt_base/opt_init_out/' \
    small/opt.json >small/opt_init_out.json
  cases=$((cases + 1))  # in the foreground: the folder is looked for after the run
  expect_error_now optimize_init_outside_bounds "/parameters/wall.albedo/init" "0.9 is outside the bounds [0.2, 0.6]" -- \
    optimize small/opt_init_out.json -q
  [ ! -e small/opt_init_out ] || fail "optimize_init_outside_bounds: the output folder was created"
else
  fail "fixture: optimize small/opt.json: $(cat err.opt_base)"
fi

# ---------------------------------------------------------------------------------------------
# Help.
good_help() {
  expect_ok help --help || return
  local w
  for w in render params grad check optimize --help-all; do grep -qF -- "$w" out.help || fail "--help does not mention $w"; done
}
common=(--set --resolution --camera --spp --seed --max-depth --rr-depth --threads --quiet)
good_command_help() {  # COMMAND FLAG...
  local cmd="$1"; shift
  expect_ok "help_$cmd" "$cmd" --help || return
  local f
  for f in "${common[@]}" "$@"; do grep -qE -- "(^|[ ,])$f([ ,=]|$)" "out.help_$cmd" || fail "$cmd --help does not mention $f"; done
}
good_command_help_only() {  # COMMAND FLAG...: commands without the scene flags
  local saved=("${common[@]}"); common=(); good_command_help "$@"; common=("${saved[@]}")
}
in_background good_help
in_background good_command_help render --output
in_background good_command_help params --json --dump
in_background good_command_help grad --target --adjoint-image --out --method --loss --adjoint-seed --param --memory-budget
in_background good_command_help_only optimize --resume --resume-any-scene --threads --quiet
in_background good_command_help check --target --adjoint-image --param --directions --eps --tolerance --method --loss \
  --direction-seed

# render: .exr and .png, written atomically (nothing else left in the folder).
good_render() {
  mkdir -p renders
  expect_ok render_exr render "$small" -o renders/a.exr --spp 1 --resolution 12x10 || return
  expect_ok render_png render "$small" -o renders/b.png --spp 1 --resolution 12x10 -q || return
  grep -q 'render: 12x10' err.render_exr || fail "render: no summary line on stderr: $(cat err.render_exr)"
  [ "$(ls -A renders | tr '\n' ' ')" = "a.exr b.png " ] || fail "render left other files: $(ls -A renders)"
  [ "$(image_size renders/a.exr)" = 12x10 ] || fail "a.exr is $(image_size renders/a.exr), expected 12x10"
  [ "$(image_size renders/b.png)" = 12x10 ] || fail "b.png is $(image_size renders/b.png), expected 12x10"
  # Overwriting goes through the same temp+rename path.
  expect_ok render_overwrite render "$small" -o renders/a.exr --spp 1 --resolution 12x10 -q || return
  [ "$(ls -A renders | tr '\n' ' ')" = "a.exr b.png " ] || fail "overwrite left other files: $(ls -A renders)"
}
in_background good_render

# params --json / --dump.
good_params_json() {
  expect_ok params_json params "$cornell" --json || return
  python3 - out.params_json <<'PY' || fail "params --json output: $(head -c 300 out.params_json)"
import json, math, sys
arr = json.load(open(sys.argv[1]))
assert isinstance(arr, list) and arr, arr
names = set()
for e in arr:
    assert set(e) >= {"name", "shape", "size", "lower", "upper"}, e
    assert e["size"] == math.prod(e["shape"]), e
    assert e["lower"] <= e["upper"], e
    names.add(e["name"])
assert {"wall.albedo", "light.radiance", "metal.roughness"} <= names, names
wall = [e for e in arr if e["name"] == "wall.albedo"][0]
assert wall["shape"] == [1024, 1024, 3], wall
assert (wall["lower"], wall["upper"]) == (0, 1), wall  # an albedo's valid range (README: Optimization config)
rough = [e for e in arr if e["name"] == "metal.roughness"][0]
assert rough["lower"] == 0 and rough["upper"] >= 1, rough
PY
  expect_ok params_text params "$cornell" || return
  grep -Eq "^wall\.albedo +\[1024, ?1024, ?3\] +3145728 +\[0, 1\]$" out.params_text ||
    fail "params: no valid range on the wall.albedo line: $(grep wall.albedo out.params_text)"
}
in_background good_params_json
good_params_dump() {
  expect_ok params_dump params "$cornell" --dump dump || return
  [ -f dump/wall.albedo.exr ] || fail "params --dump: no dump/wall.albedo.exr"
  [ "$(image_size dump/wall.albedo.exr)" = 1024x1024 ] || fail "dump/wall.albedo.exr is $(image_size dump/wall.albedo.exr)"
  python3 - dump/params.json <<'PY' || fail "params --dump params.json"
import json, sys
j = json.load(open(sys.argv[1]))
assert j["light.radiance"]["value"] == [17.0, 12.0, 4.0], j["light.radiance"]
assert j["metal.roughness"]["shape"] == [1], j["metal.roughness"]
assert "wall.albedo" not in j or "file" in j["wall.albedo"], j.get("wall.albedo")
PY
  [ -z "$(ls -A dump | grep -v -e '^params.json$' -e '^wall.albedo.exr$')" ] || fail "params --dump left: $(ls -A dump)"
}
in_background good_params_dump

# grad: outputs and their layout (the real Cornell box: wall.albedo is 1024x1024).
good_grad() {
  "$bin" render "$cornell" -o t32.exr --resolution 32x32 --spp 2 --seed 4 -q --set white.albedo=0.5 2>/dev/null
  expect_ok grad grad "$cornell" --resolution 32x32 --spp 1 --target t32.exr --out gout -q || return
  local f
  for f in image.exr gradients.json wall.albedo.grad.exr; do [ -f "gout/$f" ] || fail "grad: no gout/$f"; done
  [ "$(image_size gout/image.exr)" = 32x32 ] || fail "grad image.exr is $(image_size gout/image.exr)"
  [ "$(image_size gout/wall.albedo.grad.exr)" = 1024x1024 ] ||
    fail "wall.albedo.grad.exr is $(image_size gout/wall.albedo.grad.exr), expected 1024x1024"
  [ -z "$(ls -A gout | grep -v -e '^image.exr$' -e '^gradients.json$' -e '\.grad\.exr$')" ] || fail "grad left: $(ls -A gout)"
  python3 - gout/gradients.json <<'PY' || fail "grad gradients.json"
import json, math, os, sys
j = json.load(open(sys.argv[1]))
assert isinstance(j["loss"], float) and math.isfinite(j["loss"]) and j["loss"] > 0, j.get("loss")
assert j["loss_type"] == "l2" and j["method"] == "prb" and j["spp"] == 1, j
t = j["timings"]
for k in ("primal_seconds", "adjoint_seconds", "total_seconds"):
    assert isinstance(t[k], (int, float)) and t[k] >= 0, t
params = j["parameters"]
assert {"wall.albedo", "light.radiance", "metal.roughness", "white.albedo"} <= set(params), params.keys()
for name, e in params.items():
    assert e["size"] == math.prod(e["shape"]), (name, e)
    assert math.isfinite(e["grad_norm"]) and e["grad_norm"] >= 0, (name, e)
    if e["size"] <= 64:
        assert len(e["grad"]) == e["size"], (name, e)
        assert ("file" in e) == (len(e["shape"]) == 3), (name, e)  # images also as EXR
        norm = math.sqrt(sum(g * g for g in e["grad"]))
        assert abs(norm - e["grad_norm"]) <= 1e-5 * norm + 1e-30, (name, norm, e["grad_norm"])
    else:
        assert "grad" not in e and e["file"] == name + ".grad.exr", (name, e)
        assert os.path.isfile(os.path.join(os.path.dirname(sys.argv[1]), e["file"])), e["file"]
assert params["wall.albedo"]["shape"] == [1024, 1024, 3]
assert params["wall.albedo"]["grad_norm"] > 0 and params["light.radiance"]["grad_norm"] > 0
PY
}
in_background good_grad
# --param restricts the output; --adjoint-image gives a functional instead of a loss.
good_grad_param() {
  expect_ok grad_param grad "$small" --spp 1 --target t16.exr --param light.radiance --out gparam -q || return
  python3 -c "import json,sys; p=json.load(open(sys.argv[1]))['parameters']; assert list(p)==['light.radiance'], p" \
    gparam/gradients.json || fail "grad --param: other parameters in gradients.json"
}
in_background good_grad_param
good_grad_adjoint() {
  expect_ok grad_adjoint grad "$small" --spp 1 --adjoint-image t16.exr --out gadj -q || return
  python3 - gadj/gradients.json <<'PY' || fail "grad --adjoint-image gradients.json"
import json, math, sys
j = json.load(open(sys.argv[1]))
assert "loss" not in j and math.isfinite(j["functional"]) and j["functional"] > 0, j
assert j["parameters"]["light.radiance"]["grad_norm"] > 0
PY
  [ -f gadj/image.exr ] || fail "grad --adjoint-image: no image.exr"
}
in_background good_grad_adjoint

# Grids: params --dump and grad write each grid as .vdb, .vol and a PNG sheet (mid-slices and a
# maximum projection); the .vol holds the values, the .vdb reads back as the grid.
good_grid_files() {
  local vol="$repo/scenes/mitsuba-volume/scene.json" f
  expect_ok params_dump_grid params "$vol" --dump gdump || return
  for f in smoke.density.vdb smoke.density.vol smoke.density.png; do
    [ -s "gdump/$f" ] || fail "params --dump of a grid: no gdump/$f"
  done
  run_bin "$tmp/out.tvol" "$tmp/err.tvol" render "$vol" --resolution 16x16 --spp 2 --seed 3 -q -o tvol.exr \
    --set smoke.scale=4 || fail "the grid target did not render: $(cat "$tmp/err.tvol")"
  expect_ok grad_grid grad "$vol" --resolution 16x16 --spp 1 --target tvol.exr --param smoke.density --out ggrid -q ||
    return
  for f in smoke.density.grad.vdb smoke.density.grad.vol smoke.density.grad.png; do
    [ -s "ggrid/$f" ] || fail "grad of a grid: no ggrid/$f"
  done
  python3 - "$repo/scenes/mitsuba-volume/density.vol" gdump ggrid <<'PY' || fail "grid files of params --dump / grad"
import json, math, struct, sys
def vol(path):
    data = open(path, "rb").read()
    assert data[:4] == b"VOL\x03", path
    enc, nx, ny, nz, ch = struct.unpack("<5i", data[4:24])
    assert enc == 1 and len(data) == 48 + 4 * nx * ny * nz * ch, (path, enc, nx, ny, nz, ch, len(data))
    return (nx, ny, nz, ch), struct.unpack(f"<{nx * ny * nz * ch}f", data[48:])
src, dump, grad = sys.argv[1:]
shape, truth = vol(src)
dshape, dumped = vol(dump + "/smoke.density.vol")
assert dshape == shape == (64, 64, 64, 1) and dumped == truth, "the dumped .vol is not the scene's grid"
gshape, g = vol(grad + "/smoke.density.grad.vol")
assert gshape == shape, gshape
e = json.load(open(grad + "/gradients.json"))["parameters"]["smoke.density"]
assert e["file"] == "smoke.density.grad.vdb" and e["shape"] == [64, 64, 64, 1], e
norm = math.sqrt(sum(v * v for v in g))
assert norm > 0 and abs(norm - e["grad_norm"]) <= 1e-4 * norm, (norm, e["grad_norm"])
for f in (dump + "/smoke.density.vdb", grad + "/smoke.density.grad.vdb"):
    assert open(f, "rb").read(4) == b" BDV", f + ": not an OpenVDB file"  # magic 0x56444220
PY
  for f in gdump/smoke.density.png ggrid/smoke.density.grad.png; do
    [[ "$(image_size "$f")" =~ ^[0-9]+x[0-9]+$ ]] || fail "$f is not a PNG"
  done
  expect_ok render_dumped_vdb render "$vol" --resolution 8x8 --spp 1 -q -o vdb_back.exr \
    --set smoke.density=gdump/smoke.density.vdb || return
  # The dumped file holds one float grid, named smoke.density: asking for another is an error.
  cp gdump/smoke.density.vdb vol/dumped.vdb
  expect_error_now vdb_grid_missing "dumped.vdb" "density" -- \
    render "$(vv vdbgrid 's["media"]["smoke"]["density"] = {"type": "vdb", "file": "dumped.vdb", "grid": "density"}')" \
    -o o.exr --spp 1 -q
  # A .vdb write cut short (a full disk; here a file size limit) was renamed into place as if
  # complete, since OpenVDB does not check its writes: now one line, exit 2, the old file kept.
  cp gdump/smoke.density.vdb vol/good_dump.vdb
  local rc=0
  (trap '' XFSZ; ulimit -f 200; "$bin" params "$vol" --dump gdump -q --set smoke.scale=2 >/dev/null 2>err.vdbfull) ||
    rc=$?
  [ "$rc" -eq 2 ] || fail "vdb_write_cut_short: exit $rc, expected 2: $(cat err.vdbfull)"
  grep -qF "smoke.density.vdb: write failed" err.vdbfull || fail "vdb_write_cut_short: $(cat err.vdbfull)"
  cmp -s gdump/smoke.density.vdb vol/good_dump.vdb || fail "vdb_write_cut_short: the .vdb was replaced"
  [ -z "$(find gdump -name '.*.tmp*')" ] || fail "vdb_write_cut_short: temporaries left: $(find gdump -name '.*.tmp*')"
  # Temporaries of dumps killed before their rename piled up (8 MB per grid): a dump removes those of
  # processes no longer running that are named after the scene's parameters or params.json.
  : > gdump/.smoke.density.tmp999999999.vol
  : > gdump/.params.tmp999999998.json
  : > gdump/.unrelated.tmp999999997.txt
  expect_ok params_dump_stale params "$vol" --dump gdump -q || return
  [ ! -e gdump/.smoke.density.tmp999999999.vol ] && [ ! -e gdump/.params.tmp999999998.json ] ||
    fail "params --dump left stale temporaries: $(ls -a gdump | grep tmp)"
  [ -e gdump/.unrelated.tmp999999997.txt ] || fail "params --dump removed a temporary not of its own names"
  # A run killed while its OpenVDB reader ran left the reader's folder in $TMPDIR for ever (up to the
  # dense grid): folders are named backlight-vdb-<pid>-XXXXXX, and those of processes gone are
  # removed by the next reader's run; a living process's folder stays.
  mkdir -p "tmpvdb/backlight-vdb-999999999-AbC123" "tmpvdb/backlight-vdb-$$-XyZ789"
  : > "tmpvdb/backlight-vdb-999999999-AbC123/grid.vol"
  TMPDIR="$tmp/tmpvdb" expect_ok vdb_abandoned_folder render "$vol" --resolution 8x8 --spp 1 -q -o o_ab.exr \
    --set smoke.density=gdump/smoke.density.vdb || return
  [ ! -e "tmpvdb/backlight-vdb-999999999-AbC123" ] || fail "vdb_abandoned_folder: a dead process's folder stayed"
  [ -d "tmpvdb/backlight-vdb-$$-XyZ789" ] || fail "vdb_abandoned_folder: a living process's folder was removed"
  [ "$(ls tmpvdb | wc -l)" -eq 1 ] || fail "vdb_abandoned_folder: the run left its folder: $(ls tmpvdb)"
  # The reader stops at once when the process that started it is not its parent (gone before the
  # reader asked to die with it).
  rc=0
  BACKLIGHT_VDB_PARENT=1 "$(dirname "$bin")/backlight-vdb-read" gdump/smoke.density.vdb "" orphan.vol 512 \
    2>/dev/null || rc=$?
  [ "$rc" -eq 3 ] && [ ! -e orphan.vol ] || fail "vdb reader without its parent: exit $rc, expected 3 and no output"
  # A file cut short by up to 7 bytes loaded (the last voxel's float partly read, garbage where it
  # was not: OpenVDB does not check its reads); each cut is now a one-line error.
  local cut size
  size=$(stat -c %s gdump/smoke.density.vdb)
  for cut in 1 2 4 5 7 8 64; do
    head -c $((size - cut)) gdump/smoke.density.vdb > "vol/cut$cut.vdb"
    expect_error_now "vdb_cut_$cut" "cut$cut.vdb" "re:cut short|cannot read OpenVDB file" -- \
      render "$vol" --resolution 8x8 --spp 1 -q -o o.exr --set "smoke.density=vol/cut$cut.vdb"
  done
}
in_background good_grid_files

# Names become file names: a material named with a '/' (or an absolute path) wrote its gradient
# outside --out. (The scene reader refuses the name itself; ParamStore::add keeps refusing such
# parameter names from any reader.)
scene_variant "$small" "$tmp/small/slash.json" 's["materials"]["a/b"] = s["materials"].pop("white")'
expect_error name_with_slash "/materials/a/b" "material name 'a/b'" "path separator" -- params "$tmp/small/slash.json" -q
# params took --threads -5 without a word (it never applied the thread limit).
expect_error params_threads_negative "--threads" -- params "$small" --threads -5 -q
# An adjoint image is its own functional: a --loss next to it was ignored without a word.
expect_error grad_loss_with_adjoint "--adjoint-image excludes --loss" -- \
  grad "$small" --spp 1 --adjoint-image t16.exr --loss l1 --out g_loss_adjoint -q
expect_error check_loss_with_adjoint "--adjoint-image excludes --loss" -- \
  check "$small" --spp 1 --adjoint-image t16.exr --loss l1 --param light.radiance -q
# check: an --eps whose steps round back to θ compared 0 with 0 and passed; so did a parameter that
# does not reach the image (a camera that is not rendered): "nothing compared", exit 1. Its
# errors are one line even when a note would precede the run.
expect_error check_eps_rounds "rounds to θ in float" -- \
  check "$small" --spp 1 --target t16.exr --param white.albedo --eps 1e-9 --rr-depth 0
expect_error check_eps_range_before_notes "--eps 4 is not smaller than the width" -- \
  check "$small" --spp 1 --target t16.exr --param metal.roughness --eps 4
# A step that breaks the scene is found by the renders, after which the notes are printed: the
# error was the sixth line of stderr, under the geometry note.
expect_error check_step_breaks_scene_before_notes "box" "vertex 0 is not finite" -- \
  check "$pose" --spp 1 --target "$pose_ones" --param box.translate --eps 1e30 -q
check_nothing_compared() {
  local pose="$repo/scenes/pose/scene.json" rc=0
  "$bin" render "$pose" -o tpose.exr --spp 1 --resolution 16x16 -q 2>/dev/null || { fail "check_nothing_compared: render"; return; }
  "$bin" check "$pose" --resolution 16x16 --spp 1 --rr-depth 0 --target tpose.exr --param left.origin \
    >out.nothing 2>/dev/null || rc=$?
  [ "$rc" -eq 1 ] || fail "check of a camera that is not rendered: exit $rc, expected 1: $(cat out.nothing)"
  grep -q "^nothing compared: neither the adjoint nor the renders change with 'left.origin'" out.nothing ||
    fail "check of a camera that is not rendered printed: $(cat out.nothing)"
}
in_background check_nothing_compared
# An albedo at exactly (0, 0, 0) gets no gradient (README "Zero factors") while its finite
# differences step off 0: FAIL, exit 1, with a note saying why (helper-48: the table alone showed an
# adjoint of 0 in every direction, and the "nothing compared" message named albedos as a cause).
check_zero_albedo() {
  local rc=0
  "$bin" check "$small" --spp 1 --rr-depth 0 --target t16.exr --set white.albedo=0 --param white.albedo \
    >out.zero_albedo 2>err.zero_albedo || rc=$?
  [ "$rc" -eq 1 ] && grep -q "^FAILED" out.zero_albedo &&
    grep -q "^note: the adjoint is 0 in every direction while the renders change: 'white.albedo'" err.zero_albedo ||
    fail "check of an albedo at 0: exit $rc: $(cat out.zero_albedo err.zero_albedo)"
}
in_background check_zero_albedo
# check --adjoint-seed, as backlight.check's adjoint_seed (the CLI had none, helper-48): the
# scene's seed gives the default table, another seed another adjoint column, the same finite
# differences.
check_adjoint_seed() {
  local a
  for a in none 0 5; do
    "$bin" check "$small" --spp 1 --rr-depth 0 --target t16.exr --param white.albedo --directions 2 \
      $([ $a = none ] || echo --adjoint-seed $a) >out.adjoint_seed_$a 2>/dev/null
    [ -s out.adjoint_seed_$a ] || { fail "check --adjoint-seed $a printed nothing"; return; }
  done
  local seed
  seed=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['integrator'].get('seed', 0))" "$small")
  [ "$seed" = 0 ] || { fail "check_adjoint_seed: the small scene's seed is $seed, expected 0"; return; }
  cmp -s out.adjoint_seed_none out.adjoint_seed_0 || fail "check --adjoint-seed of the scene's seed changed the table"
  [ "$(awk 'NR>1 && NR<4 {print $2}' out.adjoint_seed_none)" != "$(awk 'NR>1 && NR<4 {print $2}' out.adjoint_seed_5)" ] ||
    fail "check --adjoint-seed 5 left the adjoint column as it was"
  [ "$(awk 'NR>1 && NR<4 {print $3}' out.adjoint_seed_none)" = "$(awk 'NR>1 && NR<4 {print $3}' out.adjoint_seed_5)" ] ||
    fail "check --adjoint-seed 5 changed the finite differences"
}
in_background check_adjoint_seed
# check --seeds: a pass that could not have seen a 25% error is INCONCLUSIVE, exit 1 (helper-39: a
# sign error passed 16 seeds; two seeds accept |z| up to 10050, Student's t of the 4σ tail).
check_inconclusive() {
  local rc=0
  "$bin" check "$small" --spp 1 --rr-depth 0 --adjoint-image t16.exr --param metal.roughness --seeds 2 \
    --directions 1 >out.inconclusive 2>err.inconclusive || rc=$?
  [ "$rc" -eq 1 ] || fail "check --seeds 2: exit $rc, expected 1: $(cat out.inconclusive)"
  grep -q "^INCONCLUSIVE: 1 direction(s), 2 seeds, |z| < 1.01e+04" out.inconclusive ||
    fail "check --seeds 2 printed: $(cat out.inconclusive)"
  grep -q "note: 'metal.roughness' moves sampling" err.inconclusive ||
    fail "check of a roughness: no note on sampling: $(cat err.inconclusive)"
}
in_background check_inconclusive
# check --method rb at one seed: its adjoint follows paths of its own, so it agrees in expectation
# only; the check said FAIL without a word (helper-41). prb gets no such note.
check_rb_note() {
  "$bin" check "$small" --spp 1 --rr-depth 0 --adjoint-image t16.exr --param white.albedo --method rb \
    --directions 1 >out.rb_note 2>err.rb_note || true
  grep -q "note: rb carries the adjoint along paths of its own" err.rb_note ||
    fail "check --method rb: no note: $(cat err.rb_note)"
  "$bin" check "$small" --spp 1 --rr-depth 0 --adjoint-image t16.exr --param white.albedo \
    --directions 1 >out.prb_note 2>err.prb_note || true
  ! grep -q "note: rb" err.prb_note || fail "check --method prb printed the rb note: $(cat err.prb_note)"
}
in_background check_rb_note
# grad --out: an earlier run's gradient files that this run does not write, and temporaries of
# killed runs (pid no longer running), are removed; other files and live temporaries stay.
grad_cleans_its_folder() {
  expect_ok grad_clean_first grad "$small" --spp 1 --target t16.exr --out g_clean -q --param wall.albedo || return
  touch g_clean/.image.tmp999999.exr g_clean/.wall.albedo.grad.tmp999999.exr g_clean/keep.txt \
    "g_clean/.image.tmp$$.exr"
  expect_ok grad_clean_second grad "$small" --spp 1 --target t16.exr --out g_clean -q --param light.radiance || return
  for f in wall.albedo.grad.exr .image.tmp999999.exr .wall.albedo.grad.tmp999999.exr; do
    [ ! -e "g_clean/$f" ] || fail "grad left g_clean/$f"
  done
  for f in keep.txt ".image.tmp$$.exr" gradients.json image.exr; do
    [ -e "g_clean/$f" ] || fail "grad removed or did not write g_clean/$f"
  done
}
in_background grad_cleans_its_folder
# A list of vectors [N, 3] (a mesh's positions) is an N×1 RGB gradient image; it was a 3N×1
# single-channel one.
grad_positions_layout() {
  local pose="$repo/scenes/pose/scene.json"
  "$bin" render "$pose" -o tpose16.exr --spp 1 --resolution 16x16 -q 2>/dev/null || { fail "grad_positions: render"; return; }
  expect_ok grad_positions grad "$pose" --resolution 16x16 --spp 1 --target tpose16.exr --param box.positions \
    --out g_positions -q || return
  [ "$(image_size g_positions/box.positions.grad.exr)" = 24x1 ] ||
    fail "box.positions.grad.exr is $(image_size g_positions/box.positions.grad.exr), expected 24x1 (24 vertices)"
}
in_background grad_positions_layout
# render -o: temporaries of its output name left by a killed render (pid no longer running) go.
render_cleans_temporaries() {
  touch .r_clean.tmp999999.png .r_clean_other.tmp999999.png
  expect_ok render_clean render "$small" -o r_clean.png --spp 1 -q || return
  [ ! -e .r_clean.tmp999999.png ] || fail "render left its stale temporary .r_clean.tmp999999.png"
  [ -e .r_clean_other.tmp999999.png ] || fail "render removed another name's temporary"
}
in_background render_cleans_temporaries

# check: a table, exit 0.
good_check() {
  expect_ok check check "$cornell" --rr-depth 0 --resolution 16x16 --spp 2 --param light.radiance --target t16.exr || return
  grep -qE '^dir +adjoint +finite_diff +rel_error +error/rms$' out.check || fail "check: no table header: $(cat out.check)"
  # Columns: adjoint, finite difference, relative error, error against the RMS over the directions.
  [ "$(grep -cE '^[0-9]+ +-?[0-9.]+e[-+][0-9]+ +-?[0-9.]+e[-+][0-9]+ +[0-9.]+e[-+][0-9]+ +[0-9.]+e[-+][0-9]+$' out.check)" -eq 4 ] ||
    fail "check: expected 4 table rows: $(cat out.check)"
  grep -q '^ok: 4 direction' out.check || fail "check: no ok line: $(cat out.check)"
  # One progress bar over the check's passes (1 gradient + 2 renders per direction), ending with
  # its elapsed time; there was none.
  grep -qE '^check \[=+\] +100\.0% .* elapsed' err.check || fail "check: no progress line: $(cat err.check)"
}
in_background good_check

# Every pass of a gradient shows its progress: the geometry passes (primary boundary, paths) and
# the taped mode's reverse sweep ran for seconds after the last bar without a line.
pass_progress() {
  expect_ok grad_geometry_progress grad "$pose" --adjoint-image "$pose_ones" --param box.translate --spp 1 \
    --out g_progress || return
  for bar in prb boundary geometry; do
    grep -qE "^$bar \[=+\] +100\.0% .* elapsed" err.grad_geometry_progress ||
      fail "grad: no '$bar' progress line: $(cat err.grad_geometry_progress)"
  done
  expect_ok grad_taped_progress grad "$small" --target t16.exr --method taped --spp 1 --out g_progress_taped || return
  for bar in "taped record" "taped sweep"; do
    grep -qE "^$bar \[=+\] +100\.0% .* elapsed" err.grad_taped_progress ||
      fail "grad: no '$bar' progress line: $(cat err.grad_taped_progress)"
  done
}
in_background pass_progress

# A flag of one method given to another was ignored without a word: a one-line warning now.
ignored_method_flags() {
  expect_ok grad_budget_prb grad "$small" --target t16.exr --spp 1 --memory-budget 1GB --out g_budget_prb -q || return
  grep -q "^warning: --memory-budget .*--method prb .*(ignored)$" err.grad_budget_prb ||
    fail "grad: no warning for --memory-budget with prb: $(cat err.grad_budget_prb)"
  expect_ok grad_whole_taped grad "$small" --target t16.exr --spp 1 --method taped --replay-whole-paths \
    --out g_whole_taped -q || return
  grep -q "^warning: --replay-whole-paths .*taped .*(ignored)$" err.grad_whole_taped ||
    fail "grad: no warning for --replay-whole-paths with taped: $(cat err.grad_whole_taped)"
  expect_ok grad_budget_taped grad "$small" --target t16.exr --spp 1 --method taped --memory-budget 1GB \
    --out g_budget_taped -q || return
  ! grep -q "warning" err.grad_budget_taped || fail "grad: a warning for taped's own flag: $(cat err.grad_budget_taped)"
}
in_background ignored_method_flags

# ---------------------------------------------------------------------------------------------
# Thread counts: --threads 1000000000 printed "Embree error 4: out of memory" and hung. Every
# command that takes --threads refuses a count above the limit (65536, as backlight.set_threads);
# the limit itself still runs.
expect_error_timed threads_huge_render "--threads" "thread count 1000000000 exceeds the limit of 65536" -- \
  render "$small" -o o.exr --spp 1 -q --threads 1000000000
expect_error_timed threads_huge_grad "--threads" "exceeds the limit of 65536" -- \
  grad "$small" --spp 1 --target t16.exr --out g_threads -q --threads 65537
expect_error_timed threads_huge_check "--threads" "exceeds the limit of 65536" -- \
  check "$small" --spp 1 --target t16.exr --param light.radiance --threads 1000000000
expect_error_timed threads_huge_params "--threads" "exceeds the limit of 65536" -- params "$small" -q --threads 1000000000
expect_error_timed threads_huge_optimize "--threads" "exceeds the limit of 65536" -- \
  optimize small/opt.json -q --threads 1000000000
threads_at_limit() {
  expect_ok threads_at_limit render "$small" -o threads_limit.exr --spp 1 -q --threads 65536 ||
    fail "render --threads 65536 (the limit) failed"
}
in_background threads_at_limit

# Integer flags take decimal digits (and a '-' where negatives mean something): CLI11 read 0x10
# as 16 and 010 as 8 (octal), took " 16", and refused 1e1 with "Could not convert", while
# --seed refused 0x1F. One message for all: the flag, the value and what it should be.
int_flag_cases() {  # int_flag_cases COMMAND_ARGS...: every integer flag of that command, hex
  local command="$1"; shift
  local flag
  for flag in "$@"; do
    expect_error "int_hex_${command}_${flag#--}" "$flag: '0x1' is not a non-negative integer (decimal digits only)" -- \
      "$command" $(case "$command" in
        optimize) echo small/opt.json ;;
        render) echo "$small" -o o.exr ;;
        params) echo "$small" ;;
        grad) echo "$small" --target t16.exr --out g_int ;;
        check) echo "$small" --target t16.exr --param light.radiance ;;
      esac) -q "$flag" 0x1
  done
}
int_flag_cases render --camera --spp --seed --rr-depth --threads
int_flag_cases params --camera --spp --seed --rr-depth --threads
int_flag_cases grad --camera --spp --seed --rr-depth --threads --adjoint-seed
int_flag_cases check --camera --spp --seed --rr-depth --threads --directions --seeds --direction-seed
int_flag_cases optimize --threads
expect_error int_max_depth_hex "--max-depth: '0x6' is not an integer (decimal digits, after an optional '-')" -- \
  render "$small" -o o.exr -q --max-depth 0x6
expect_error int_spp_space "--spp: ' 16' is not a non-negative integer" -- render "$small" -o o.exr -q --spp " 16"
expect_error int_spp_exponent "--spp: '1e1' is not a non-negative integer" -- render "$small" -o o.exr -q --spp 1e1
expect_error int_spp_plus "--spp: '+16' is not a non-negative integer" -- render "$small" -o o.exr -q --spp +16
expect_error int_spp_fraction "--spp: '16.0' is not a non-negative integer" -- render "$small" -o o.exr -q --spp 16.0
expect_error int_max_depth_minus_only "--max-depth: '-' is not an integer" -- render "$small" -o o.exr -q --max-depth=-
expect_error int_spp_overflow "--spp: '99999999999' exceeds 2^31 - 1" -- render "$small" -o o.exr -q --spp 99999999999
expect_error int_max_depth_underflow "--max-depth: '-99999999999' is below -2^31" -- \
  render "$small" -o o.exr -q --max-depth -99999999999
expect_error int_seed_hex "--seed: '0x1F' is not a non-negative integer (decimal digits only)" -- \
  render "$small" -o o.exr -q --seed 0x1F
# Decimal inputs keep working, leading zeros as decimal: --spp 010 is 10 samples, --seed 010 seed 10.
int_decimal() {
  expect_ok int_spp_leading_zero render "$small" -o int_spp.exr -q --spp 010 --max-depth -1 --rr-depth 00 &&
    { grep -q " 10 spp," err.int_spp_leading_zero || fail "--spp 010 is not 10 samples: $(cat err.int_spp_leading_zero)"; }
  expect_ok int_seed_010 render "$small" -o int_seed_010.exr -q --spp 1 --seed 010 &&
    expect_ok int_seed_10 render "$small" -o int_seed_10.exr -q --spp 1 --seed 10 &&
    { cmp -s int_seed_010.exr int_seed_10.exr || fail "--seed 010 renders another image than --seed 10"; }
}
in_background int_decimal

# --set lists: a trailing comma was dropped without a word (an item missing, or one too many
# typed); an empty item anywhere is named.
expect_error set_trailing_comma "--set white.albedo" "'0.5,0.5,0.5,'" "neither numbers nor" -- \
  render "$small" --set white.albedo=0.5,0.5,0.5, -o o.exr -q
expect_error set_leading_comma "--set white.albedo" "neither numbers nor" -- \
  render "$small" --set white.albedo=,0.5,0.5,0.5 -o o.exr -q
expect_error set_trailing_commas "--set white.albedo" "neither numbers nor" -- \
  render "$small" --set white.albedo=0.5,0.5,0.5,, -o o.exr -q
expect_error set_only_comma "--set light.radiance" "neither numbers nor" -- render "$small" --set light.radiance=, -o o.exr -q

# Writes that fail (a full disk; here a file size limit of 0) name the cause: PFM said only "write
# failed", PNG "write failed (Write Error)"; a cut HDR was renamed into place with exit 0, and
# libjpeg exit()ed with status 1 and its own message, leaving its temporary file. The old image
# stays, and no temporary file.
write_limit() {  # write_limit NAME: renders NAME (over an older one) under ulimit -f 0
  local name="$1" rc=0 err
  echo old >"$name"
  # stderr through a pipe: the limit applies to its file too.
  err="$( (trap '' XFSZ; ulimit -f 0; "$bin" render "$small" -o "$name" --spp 1 -q 2>&1 >/dev/null) )" || rc=$?
  printf '%s\n' "$err" >"err.limit_$name"
  [ "$rc" -eq 2 ] || fail "write_limit $name: exit $rc, expected 2: $(cat "err.limit_$name")"
  [ "$(wc -l <"err.limit_$name")" -eq 1 ] || fail "write_limit $name: not one line: $(cat "err.limit_$name")"
  case "$(cat "err.limit_$name")" in *" plugin ("*) return ;; esac  # built without OpenImageIO
  grep -qF "$name: write failed (" "err.limit_$name" && grep -qF "File too large" "err.limit_$name" ||
    fail "write_limit $name: the cause is not named: $(cat "err.limit_$name")"
  [ "$(cat "$name")" = old ] || fail "write_limit $name: the old file was replaced"
  [ -z "$(find . -maxdepth 1 -name ".${name%.*}.tmp*")" ] || fail "write_limit $name: temporaries left"
}
for ext in pfm png exr hdr jpg; do in_background write_limit "limit_$ext.$ext"; done
# Text outputs the same (JSON, CSV, checkpoints' raw values: "write failed" without a cause): the
# params.json of a dump of a scene without textures.
text_write_limit() {
  local scene; scene="$(v notex 's["materials"]["wall"]["albedo"] = 0.5')"
  local rc=0 err
  err="$( (trap '' XFSZ; ulimit -f 0; "$bin" params "$scene" --dump limit_dump -q 2>&1 >/dev/null) )" || rc=$?
  [ "$rc" -eq 2 ] || fail "text_write_limit: exit $rc, expected 2: $err"
  case "$err" in
    "backlight: limit_dump/params.json: write failed (File too large)") ;;
    *) fail "text_write_limit: $err" ;;
  esac
  [ -z "$(find limit_dump -name '.*.tmp*')" ] || fail "text_write_limit: temporaries left"
}
mkdir -p limit_dump
in_background text_write_limit

wait
# Error cases write nothing.
for f in o.exr o.bmp; do [ ! -e "$f" ] || fail "an error case wrote $f"; done
[ ! -e "$bad/out-must-not-exist" ] || fail "a config in tests/data/bad created its output folder"
for d in small/cfg_out_*; do [ ! -e "$d" ] || fail "a config error left its output folder $d"; done
for d in g_err1 g_err2 g_err3 g_err4 g_err5 g_err6 g_err7 g_err8 g_err9 g_err10 g_threads g_int; do
  [ ! -e "$d" ] || fail "an error case created output directory $d"
done

if [ -s "$tmp/failures" ]; then
  cat "$tmp/failures"
  echo "test_errors: $(grep -c '^FAIL:' "$tmp/failures") failure(s) in $cases cases"
  exit 1
fi
echo "test_errors: OK ($cases cases)"
