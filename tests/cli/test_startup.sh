#!/usr/bin/env bash
# Start-up cost: OpenImageIO (~260 shared libraries) and OpenVDB are plugins opened on first use
# (engine/plugins/), so `backlight --help`, EXR/PNG renders and texture reads never load them.
# Checked through the dynamic loader's own log (LD_DEBUG=libs), with a negative control: a JPEG
# texture does load OpenImageIO, and a .vdb dump OpenVDB. Without the plugins (an empty
# BACKLIGHT_PLUGIN_DIR) those two are one-line errors naming the file, exit 2. Peak RSS of
# --help ≤ 40 MB (not under sanitizers: ASan's shadow memory alone is larger). Wall times are
# measured by bench/startup, not asserted (shared machines).
# Usage: test_startup.sh BACKLIGHT_BIN SOURCE_DIR SANITIZED(0|1)
set -u
bin="$1"
src="$2"
sanitized="$3"
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
cd "$dir"
fail() { echo "FAIL: $*"; exit 1; }
scene() {  # a lit floor at 64x64 with the given albedo JSON
  cat <<JSON
{"integrator": {"max_depth": 2, "rr_depth": 0},
 "cameras": [{"name": "top", "origin": [0, 3, 0.01], "target": [0, 0, 0], "fov": 45, "resolution": [64, 64]}],
 "materials": {"floor": {"type": "diffuse", "albedo": $1}},
 "shapes": [{"name": "floor", "type": "rectangle", "material": "floor",
             "transform": {"rotate": {"axis": [1, 0, 0], "angle": -90}}}],
 "environment": {"type": "constant", "radiance": [1, 1, 1]}}
JSON
}
oiiotool --pattern checker:width=8:height=8 64x64 3 -o checker.jpg || fail "oiiotool"
oiiotool --pattern checker:width=8:height=8 64x64 3 -o checker.png || fail "oiiotool"
scene '[0.5, 0.5, 0.5]' > plain.json
scene '{"type": "bitmap", "file": "checker.png"}' > png.json
scene '{"type": "bitmap", "file": "checker.jpg"}' > jpeg.json

# loaded LIB CMD...: whether the loader opened a library whose name contains LIB while running CMD.
loaded() {
  local lib="$1"
  shift
  LD_DEBUG=libs LD_DEBUG_OUTPUT="$dir/ld" "$@" > /dev/null 2> run.err || fail "$* failed: $(cat run.err)"
  local found=1
  grep -q "calling init: .*$lib" "$dir"/ld.* && found=0
  rm -f "$dir"/ld.*
  return $found
}
for lib in libOpenImageIO libopenvdb; do
  loaded $lib "$bin" --help && fail "--help loads $lib"
  loaded $lib "$bin" render plain.json --spp 1 -q -o o.exr && fail "a 64x64 EXR render loads $lib"
  loaded $lib "$bin" render png.json --spp 1 -q -o o.png && fail "a PNG texture and PNG output load $lib"
done
# Negative controls: the check sees the libraries when they are used.
loaded libOpenImageIO "$bin" render jpeg.json --spp 1 -q -o o.exr || fail "a JPEG texture did not load OpenImageIO"
loaded libopenvdb "$bin" params "$src/scenes/mitsuba-volume/scene.json" --dump dump -q ||
  fail "params --dump of a grid did not load OpenVDB"
[ -s dump/smoke.density.vdb ] || fail "no .vdb written"
# The plugins produce what OpenImageIO and OpenVDB wrote before: a JPEG texture reads, and the
# dumped .vdb reads back as the grid.
"$bin" render "$src/scenes/mitsuba-volume/scene.json" --resolution 16x16 --spp 1 -q -o v.exr \
  --set smoke.density=dump/smoke.density.vdb 2> err.txt || fail "the dumped .vdb does not read back: $(cat err.txt)"

# Without the plugins: one line naming the file, exit 2, no output written.
mkdir empty
one_line_error() {  # EXPECTED_SUBSTRING CMD...
  local want="$1"
  shift
  BACKLIGHT_PLUGIN_DIR="$dir/empty" "$@" > /dev/null 2> err.txt
  local code=$?
  [ $code -eq 2 ] || fail "$* without plugins: exit $code, expected 2 ($(cat err.txt))"
  [ "$(wc -l < err.txt)" -eq 1 ] || fail "$* without plugins: not one line: $(cat err.txt)"
  grep -q -- "$want" err.txt || fail "$* without plugins: '$want' not in: $(cat err.txt)"
}
one_line_error "checker.jpg: reading JPEG needs the oiio plugin (libbacklight_oiio.so not found" \
  "$bin" render jpeg.json --spp 1 -q -o none.exr
[ ! -e none.exr ] || fail "an output was written although the texture failed"
one_line_error "o.jpg: writing JPEG needs the oiio plugin" "$bin" render plain.json --spp 1 -q -o o.jpg
one_line_error "smoke.density.vdb: writing an OpenVDB file needs the openvdb plugin" \
  "$bin" params "$src/scenes/mitsuba-volume/scene.json" --dump dump2 -q
# EXR and PNG need no plugin.
BACKLIGHT_PLUGIN_DIR="$dir/empty" "$bin" render png.json --spp 1 -q -o p.png 2> err.txt ||
  fail "PNG without plugins: $(cat err.txt)"

if [ "$sanitized" = 0 ] && [ -x /usr/bin/time ]; then
  rss=$(/usr/bin/time -f %M "$bin" --help 2>&1 > /dev/null | tail -1)
  [ "$rss" -le 40960 ] || fail "--help peak RSS ${rss} KB > 40 MB"
  echo "--help peak RSS ${rss} KB"
fi
echo "ok: --help, EXR and PNG runs load neither OpenImageIO nor OpenVDB; JPEG and .vdb open their plugins"
