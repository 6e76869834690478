# Sourced by the optimize CLI tests: writes, into the current folder, a floor seen from above with
# a bitmap albedo (start.exr, uniform grey) and the checkerboard truth.exr it is fitted to, both
# SIZE×SIZE, and scene.json rendering it at SIZE×SIZE.   Usage: write_floor_scene SIZE
write_floor_scene() {
  local n="$1"
  oiiotool --pattern checker:width=8:height=8:color1=0.8,0.2,0.1:color2=0.1,0.5,0.8 "${n}x${n}" 3 -d float -o truth.exr
  oiiotool --pattern constant:color=0.5,0.5,0.5 "${n}x${n}" 3 -d float -o start.exr
  cat > scene.json <<JSON
{"integrator": {"max_depth": 2, "rr_depth": 0},
 "cameras": [{"name": "top", "origin": [0, 3, 0.01], "target": [0, 0, 0], "fov": 45, "resolution": [$n, $n]}],
 "materials": {"floor": {"type": "diffuse", "albedo": {"type": "bitmap", "file": "start.exr"}}},
 "shapes": [{"name": "floor", "type": "rectangle", "material": "floor",
             "transform": {"rotate": {"axis": [1, 0, 0], "angle": -90}}}],
 "environment": {"type": "constant", "radiance": [1, 1, 1]}}
JSON
}
