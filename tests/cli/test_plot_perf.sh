#!/usr/bin/env bash
# Self-test of tools/plot_perf (the performance targets as a picture): the committed bench results
# give a PNG; results of one benchmark alone give one; each kind of bad results folder (none, a
# malformed JSON, a result without a figure a panel needs) is one line naming the file, exit 2,
# and leaves no picture behind.
# Usage: tests/cli/test_plot_perf.sh [REPO_ROOT]
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "${1:-$here/../..}" && pwd)"
tool="$repo/tools/plot_perf"
fail() { echo "test_plot_perf: FAIL: $*" >&2; exit 1; }
[ -x "$tool" ] || fail "$tool is not executable"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

is_png() {  # a PNG signature and a width and height in the plausible range
  /usr/bin/python3 - "$1" <<'PY'
import struct, sys
data = open(sys.argv[1], "rb").read()
assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
w, h = struct.unpack(">II", data[16:24])
assert 800 <= w <= 4000 and 200 <= h <= 2000, (w, h)
PY
}

# The committed results.
mkdir "$tmp/all"
for f in gradient primal profile volume volume_no_big; do
  [ -f "$repo/bench/results/$f.json" ] || fail "bench/results/$f.json is missing"
  cp "$repo/bench/results/$f.json" "$tmp/all/"
done
"$tool" "$tmp/all" > "$tmp/out" 2> "$tmp/err" || fail "exit $? on the committed results: $(cat "$tmp/err")"
is_png "$tmp/all/performance.png" || fail "performance.png of the committed results"
[ -z "$(ls "$tmp/all" | grep tmp)" ] || fail "a temporary file was left: $(ls "$tmp/all")"

# One benchmark's results alone.
mkdir "$tmp/one"
cp "$repo/bench/results/primal.json" "$tmp/one/"
"$tool" "$tmp/one" > /dev/null 2> "$tmp/err" || fail "exit $? on primal.json alone: $(cat "$tmp/err")"
is_png "$tmp/one/performance.png" || fail "performance.png of primal.json alone"

# Bad folders: one line on stderr naming the problem (and the file), exit 2, no picture.
bad() {  # name, expected text in the message; the folder $tmp/$name is prepared by the caller
  local name="$1" expect="$2" rc=0
  "$tool" "$tmp/$name" > /dev/null 2> "$tmp/err" || rc=$?
  [ "$rc" = 2 ] || fail "$name: exit $rc, expected 2 ($(cat "$tmp/err"))"
  [ "$(wc -l < "$tmp/err")" = 1 ] || fail "$name: not one line: $(cat "$tmp/err")"
  grep -qF -- "$expect" "$tmp/err" || fail "$name: message '$(cat "$tmp/err")' lacks '$expect'"
  [ ! -e "$tmp/$name/performance.png" ] || fail "$name: a picture was written"
}
mkdir "$tmp/empty"
bad empty "no benchmark results in"
mkdir "$tmp/malformed"
printf '{"machine": {"run": "x", ' > "$tmp/malformed/gradient.json"
bad malformed "malformed/gradient.json"
# variant FOLDER FILE PYTHON: FOLDER/FILE = the committed bench/results/FILE with PYTHON applied to `data`.
variant() {
  mkdir "$tmp/$1"
  /usr/bin/python3 - "$repo/bench/results/$2" "$tmp/$1/$2" "$3" <<'PY'
import json, sys
data = json.load(open(sys.argv[1]))
exec(sys.argv[3])
json.dump(data, open(sys.argv[2], "w"))
PY
}
variant missing gradient.json 'del data["rb_backward_over_primal"]'
bad missing "no number 'rb_backward_over_primal'"
mkdir "$tmp/notbench"
echo '[1, 2, 3]' > "$tmp/notbench/profile.json"
bad notbench "notbench/profile.json: no machine.run"
variant shares profile.json 'data["prb"]["transport_shares_percent"]["ray queries (Embree)"] = "many"'
bad shares "no table of numbers 'prb.transport_shares_percent'"
echo "test_plot_perf: ok"
