#!/usr/bin/env bash
# Self-test of tools/smoke_regions: the truth scores 0 everywhere; an empty grid's error is the
# truth itself (holes 0, shells and plume all below it); a grid at 0.1 is biased +0.1 in the holes;
# a bad file is one line and exit 2.
# Usage: tests/cli/test_smoke_regions.sh [REPO_ROOT]
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "${1:-$here/../..}" && pwd)"
tool="$repo/tools/smoke_regions"
fail() { echo "test_smoke_regions: FAIL: $*" >&2; exit 1; }
[ -x "$tool" ] || fail "$tool is not executable"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

/usr/bin/python3 - "$tmp" "$repo" <<'PY' || fail "writing the grids"
import sys
import numpy as np
sys.path.insert(0, sys.argv[2] + "/scenes")
import make_assets
def vol(path, rho):
    open(path, "wb").write(make_assets.vol_bytes(rho, (-1.0, 0.0, -1.0, 1.0, 2.0, 1.0)))
vol(sys.argv[1] + "/truth.vol", make_assets.smoke_density())
vol(sys.argv[1] + "/zero.vol", np.zeros((4, 4, 4)))
vol(sys.argv[1] + "/tenth.vol", np.full((8, 8, 8), 0.1))
open(sys.argv[1] + "/bad.vol", "wb").write(b"VOL\x03 too short")
PY

out="$("$tool" "$tmp/truth.vol" "$tmp/zero.vol" "$tmp/tenth.vol")" || fail "exit $? on good grids"
echo "$out"
python3 - "$out" <<'PY' || fail "figures"
import re, sys
blocks = re.split(r"\n(?=\S)", sys.argv[1].strip())
assert len(blocks) == 3, blocks
def figures(block):
    rmse = float(re.search(r"RMSE (\S+) at", block).group(1))
    regions = {m.group(1): (float(m.group(2)), float(m.group(3)))
               for m in re.finditer(r"^\s+(\w+)\s+\d+ voxels\s+bias (\S+)\s+rms (\S+)", block, re.M)}
    return rmse, regions
rmse, r = figures(blocks[0])
assert rmse == 0 and all(b == 0 and s == 0 for b, s in r.values()), blocks[0]
rmse, r = figures(blocks[1])
assert rmse > 0.05 and r["holes"] == (0, 0) and r["empty"] == (0, 0), blocks[1]
assert r["shells"][0] < 0 and r["plume"][0] < 0, blocks[1]
rmse, r = figures(blocks[2])
assert abs(r["holes"][0] - 0.1) < 1e-4 and abs(r["empty"][0] - 0.1) < 1e-4, blocks[2]
PY

if "$tool" "$tmp/bad.vol" 2>"$tmp/err"; then fail "no error for a bad file"; fi
status=0; "$tool" "$tmp/bad.vol" 2>/dev/null || status=$?
[ "$status" -eq 2 ] || fail "exit $status for a bad file, expected 2"
[ "$(wc -l <"$tmp/err")" -eq 1 ] || fail "not one line: $(cat "$tmp/err")"
grep -q "bad.vol: not a Mitsuba .vol" "$tmp/err" || fail "message: $(cat "$tmp/err")"
echo "test_smoke_regions: OK"
