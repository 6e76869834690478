#!/usr/bin/env bash
# report.html of `backlight optimize` in a real browser (headless Chromium):
#  - the finished report and one written mid-run (a run stopped by SIGINT) load; every inlined PNG
#    decodes in the browser to the size and mean colour Python decodes from the same base64;
#  - the screenshot has the requested size, is not blank, and shows each image where the page
#    laid it out (the screenshot's pixels there match the image); nothing overflows horizontally;
#  - negative control: the same check on a copy with one base64 payload made invalid and another
#    truncated reports exactly those two images;
#  - the finished report never reloads (30 s of the browser's virtual time); the mid-run one does.
# The screenshots are kept as report_browser.png and report_browser_running.png in the folder the
# test starts in (ctest: the build's tests/cli). Skipped (exit 77) without chromium.
# Usage: test_report_browser.sh BACKLIGHT_BIN      (KEEP=1 leaves the temporary folder)
set -euo pipefail
bin="$1"
chromium=""
for name in chromium chromium-browser; do
  if command -v "$name" > /dev/null; then
    chromium="$(command -v "$name")"
    break
  fi
done
[ -n "$chromium" ] || { echo "skipped: chromium not installed (apt-get install chromium)"; exit 77; }
py=python3
[ -x /usr/bin/python3 ] && py=/usr/bin/python3
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
keep_dir="$PWD"
dir="$(mktemp -d)"
server=""
optimizer=""
cleanup() {
  [ -n "$server" ] && kill "$server" 2> /dev/null
  [ -n "$optimizer" ] && kill -9 "$optimizer" 2> /dev/null
  [ -n "${KEEP:-}" ] || rm -rf "$dir"
}
trap cleanup EXIT
cd "$dir"
fail() {
  echo "FAIL: $*"
  exit 1
}
start=$(date +%s)

# --- two optimize runs of a 64×64 floor: one finished, one stopped mid-run -------------------------
. "$here/floor_scene.sh"
write_floor_scene 64
job() {  # job OUTPUT_DIR ITERATIONS
  cat << JSON
{"scene": "scene.json", "output": "$1",
 "parameters": {"floor.albedo": {"lr": 0.05, "bounds": [0, 1]}},
 "views": {"cameras": ["top"], "reference": {"set": {"floor.albedo": "truth.exr"}, "spp": 16}},
 "spp": 4, "iterations": $2, "checkpoint_every": 1000, "snapshot_every": 2}
JSON
}
job done 4 > done.json
job running 100000 > running.json
"$bin" optimize done.json --quiet 2> done.log || fail "optimize: $(tail -n 3 done.log)"
grep -q "<b>Finished</b>: 4 of 4 iterations" done/report.html || fail "the finished report does not say so"

# The mid-run report: a copy of the one of the latest snapshot.
"$bin" optimize running.json --quiet 2> running.log &
optimizer=$!
for _ in $(seq 1 1200); do  # up to 120 s: sanitizer builds and busy machines are slow
  [ -f running/report.html ] && break
  sleep 0.1
done
[ -f running/report.html ] || fail "no report.html after 120 s: $(tail -n 3 running.log)"
cp running/report.html running/report_mid.html  # written by rename: always a whole page
kill -INT "$optimizer"
code=0
wait "$optimizer" || code=$?
optimizer=""
[ $code -eq 0 ] || fail "optimize after SIGINT: exit $code ($(tail -n 3 running.log))"
grep -q "<b>Running</b>: " running/report_mid.html || fail "the mid-run report does not say it is running"
# SIGINT leaves a page that says so and no longer reloads.
grep -q "<b>Interrupted</b>: " running/report.html || fail "the interrupted run's report does not say so"

# --- the reload, as written ---------------------------------------------------------------------
refresh='<meta http-equiv="refresh" content="15">'
reloads='http-equiv="?refresh|location\.reload|setTimeout|setInterval'
grep -qiE "$reloads" done/report.html &&
  fail "the finished report still reloads: $(grep -oiE ".{0,40}($reloads).{0,40}" done/report.html)"
grep -qF "$refresh" running/report_mid.html || fail "the mid-run report has no $refresh"
grep -qiE "$reloads" running/report.html && fail "the interrupted run's report still reloads"

# --- the browser ----------------------------------------------------------------------------------
profiles=0
chrome() {  # chrome ARGS...: cmd=(headless Chromium with a fresh profile, ARGS)
  profiles=$((profiles + 1))
  cmd=(timeout -k 5 60 "$chromium" --headless=new --disable-gpu)
  [ "$(id -u)" -eq 0 ] && cmd+=(--no-sandbox)  # Chromium refuses to run as root with its sandbox
  cmd+=(--user-data-dir="$dir/profile$profiles" --no-first-run --force-device-scale-factor=1 "$@")
}
browser() {  # browser ARGS... URL: runs chrome ARGS... URL; its messages go to browser.log
  chrome "$@"
  "${cmd[@]}" 2>> browser.log
}

# What the browser made of a page: a copy with a script that, once everything has loaded, writes
# into the page (as JSON, for --dump-dom) each <img>'s decoded size, mean RGBA (through a canvas)
# and place, the table's rows, the page's width and how often the page has been loaded.
cat > probe.js << 'JS'
<script>
window.name = String(Number(window.name || 0) + 1);  // survives a reload
addEventListener("load", () => {
  const page = {loads: Number(window.name), title: document.title, scroll_width: document.documentElement.scrollWidth,
                inner_width: innerWidth, images: [], rows: []};
  for (const img of document.images) {
    let mean = null;
    if (img.naturalWidth > 0) {
      const canvas = document.createElement("canvas");
      canvas.width = img.naturalWidth;
      canvas.height = img.naturalHeight;
      const context = canvas.getContext("2d");
      context.drawImage(img, 0, 0);
      const rgba = context.getImageData(0, 0, canvas.width, canvas.height).data;
      mean = [0, 0, 0, 0];
      for (let i = 0; i < rgba.length; ++i) mean[i % 4] += rgba[i] / (rgba.length / 4);
    }
    const box = img.getBoundingClientRect();
    page.images.push({alt: img.alt, width: img.naturalWidth, height: img.naturalHeight, mean: mean,
                      x: box.left + scrollX + img.clientLeft, y: box.top + scrollY + img.clientTop,
                      shown_width: img.clientWidth, shown_height: img.clientHeight});
  }
  for (const row of document.querySelectorAll("tr")) page.rows.push([...row.cells].map(cell => cell.textContent));
  const out = document.createElement("pre");
  out.id = "probe";
  out.textContent = JSON.stringify(page);
  document.body.append(out);
});
</script>
JS
size=(1200 1600)  # the window of every page load, so the probe sees the screenshot's layout
probe() {  # probe PAGE.html COPY.html: COPY.dom, the DOM of PAGE with the probe after load
  "$py" -c "
import sys
page = open(sys.argv[1]).read()
assert page.count('</body>') == 1
open(sys.argv[2], 'w').write(page.replace('</body>', open('probe.js').read() + '</body>'))" "$1" "$2"
  browser --window-size="${size[0]},${size[1]}" --dump-dom "file://$dir/$2" > "${2%.html}.dom" ||
    fail "chromium --dump-dom $2: $(tail -n 3 browser.log)"
}

cat > check.py << 'PY'
"""What Chromium made of a report (the probe's JSON in a --dump-dom, and a screenshot) against the
report itself. With --expect-bad, a negative control: exactly these images must be found broken."""
import argparse, base64, html, io, json, re, sys
import matplotlib.image
import numpy as np

parser = argparse.ArgumentParser()
parser.add_argument("report", help="the report as written (its images are the reference)")
parser.add_argument("dom", help="--dump-dom of the page with the probe")
parser.add_argument("shot", help="screenshot of the page, in the probe's window size")
parser.add_argument("--size", type=int, nargs=2, required=True, help="the window's width and height")
parser.add_argument("--alts", nargs="*", help="the images' captions, in order (prefixes)")
parser.add_argument("--expect-bad", help="negative control: the broken images, comma-separated")
args = parser.parse_args()
problems = []

# The report's images as Python decodes them (a payload Python cannot decode fails here).
report = open(args.report).read()
reference = []
for alt, payload in re.findall(r'<img alt="([^"]*)" src="data:image/png;base64,([^"]*)"', report):
    pixels = matplotlib.image.imread(io.BytesIO(base64.b64decode(payload, validate=True)), format="png")
    if pixels.shape[2] == 3:
        pixels = np.dstack([pixels, np.ones(pixels.shape[:2], np.float32)])
    reference.append((html.unescape(alt), np.round(pixels * 255)))
if args.alts is not None:
    alts = [alt for alt, _ in reference]
    if len(alts) != len(args.alts) or not all(a.startswith(b) for a, b in zip(alts, args.alts)):
        problems.append(f"images {alts}, expected {args.alts}")

found = re.search(r'<pre id="probe">(.*?)</pre>', open(args.dom).read(), re.S)
if not found:
    sys.exit(f"FAIL: {args.dom}: the probe wrote nothing (the page did not finish loading?)")
page = json.loads(html.unescape(found.group(1)))
if len(page["images"]) != len(reference):
    problems.append(f"the browser has {len(page['images'])} images, the report inlines {len(reference)}")

shot = matplotlib.image.imread(args.shot)
height, width = shot.shape[:2]
if [width, height] != args.size:
    problems.append(f"screenshot {width}x{height}, requested {args.size[0]}x{args.size[1]}")
rgb = np.round(shot[..., :3] * 255)
colours = len(np.unique(rgb.astype(np.int64).reshape(-1, 3) @ np.array([65536, 256, 1])))
if colours < 500 or rgb.std() < 10:
    problems.append(f"screenshot nearly blank: {colours} colours, standard deviation {rgb.std():.1f}")


def cell_means(image, n=8):
    """The means of an n×n grid of cells over the image: what survives scaling it down."""
    ys = np.linspace(0, image.shape[0], n + 1).round().astype(int)
    xs = np.linspace(0, image.shape[1], n + 1).round().astype(int)
    return np.array([[image[ys[j]:ys[j + 1], xs[i]:xs[i + 1]].reshape(-1, 3).mean(axis=0) for i in range(n)]
                     for j in range(n)])


def decoded(shown, pixels):
    """Why the browser's decoding of an image differs from Python's, or None."""
    if shown["width"] == 0:
        return "not decoded (naturalWidth 0)"
    if (shown["width"], shown["height"]) != (pixels.shape[1], pixels.shape[0]):
        return f"decoded as {shown['width']}x{shown['height']}, the PNG is {pixels.shape[1]}x{pixels.shape[0]}"
    expected = pixels.reshape(-1, 4).mean(axis=0)
    if np.abs(np.array(shown["mean"]) - expected).max() > 1.0:
        return f"mean RGBA {np.round(shown['mean'], 1)} in the browser, {np.round(expected, 1)} in the PNG"
    return None


def painted(shown, pixels):
    """Why the screenshot does not show the image where the page laid it out, or None. The PNGs are
    opaque. At natural size the very pixels (fractional layout positions round either way: ±1 px is
    searched); scaled down, the means of an 8×8 grid of cells."""
    x, y, w, h = round(shown["x"]), round(shown["y"]), shown["shown_width"], shown["shown_height"]
    if w < 8 or h < 8 or x < 1 or y < 1 or x + w + 1 > width or y + h + 1 > height:
        return f"not inside the screenshot: {w}x{h} at ({x}, {y})"
    if (w, h) == (pixels.shape[1], pixels.shape[0]):
        worst = min(np.abs(rgb[y + dy:y + dy + h, x + dx:x + dx + w] - pixels[..., :3]).max()
                    for dx in (-1, 0, 1) for dy in (-1, 0, 1))
        if worst > 2:
            return f"the screenshot at ({x}, {y}) differs from the image by up to {worst:.0f} levels"
    else:
        worst = np.abs(cell_means(rgb[y:y + h, x:x + w]) - cell_means(pixels[..., :3])).max()
        if worst > 8:
            return f"shown at {w}x{h}, ({x}, {y}): the screenshot's cell means differ by up to {worst:.0f} levels"
    return None


bad_decoded, bad_painted = [], []
for i, (shown, (alt, pixels)) in enumerate(zip(page["images"], reference)):
    for why, bad in ((decoded(shown, pixels), bad_decoded), (painted(shown, pixels), bad_painted)):
        if why:
            bad.append(i)
            print(f"image {i} ({alt}): {why}")

if args.expect_bad is not None:
    expected = [int(i) for i in args.expect_bad.split(",")]
    print(f"negative control: images {bad_decoded} found undecoded and {bad_painted} unpainted, {expected} broken")
    sys.exit(0 if bad_decoded == bad_painted == expected and not problems else 1)
problems += [f"image {i} is broken in the browser" for i in sorted(set(bad_decoded + bad_painted))]
if page["loads"] != 1:
    problems.append(f"the page loaded {page['loads']} times")
if not page["title"].startswith("backlight optimize: "):
    problems.append(f"title {page['title']!r}")
if page["scroll_width"] > page["inner_width"]:
    problems.append(f"the page is {page['scroll_width']} px wide in a {page['inner_width']} px window")
rows = page["rows"]
if len(rows) < 4 or rows[0] != ["quantity", "start", "now"] or any(len(r) not in (2, 3) or not all(r) for r in rows):
    problems.append(f"summary table {rows}")
for p in problems:
    print(f"FAIL: {args.report}: {p}")
print(f"{args.report}: {len(reference)} images decoded and shown, {len(rows)} table rows, {colours} colours")
sys.exit(1 if problems else 0)
PY

shoot() {  # shoot PAGE.html: PAGE.png
  browser --screenshot="$dir/${1%.html}.png" --window-size="${size[0]},${size[1]}" "file://$dir/$1" > /dev/null ||
    fail "chromium --screenshot $1: $(tail -n 3 browser.log)"
  [ -s "${1%.html}.png" ] || fail "no screenshot of $1: $(tail -n 3 browser.log)"
}
check_report() {  # check_report REPORT NAME CAPTION...: probe, screenshot and checks of one report
  local report="$1" name="$2"
  shift 2
  cp "$report" "$name.html"
  probe "$name.html" "$name.probe.html"
  shoot "$name.html"
  "$py" check.py "$name.html" "$name.probe.dom" "$name.png" --size "${size[@]}" --alts "$@" ||
    fail "$name.html in Chromium (above)"
}
check_report done/report.html done "loss of each iteration" "parameter RMSE" "target | initial | final" \
  "floor.albedo (final)"
check_report running/report_mid.html running "loss of each iteration" "parameter RMSE" "first view after iteration" \
  "floor.albedo (iteration "
cp done.png "$keep_dir/report_browser.png"
cp running.png "$keep_dir/report_browser_running.png"

# --- negative control: a corrupted copy must fail the same check ------------------------------------
# Image 0: a character outside base64 (the data: URL does not decode); the last image: its payload
# cut in half (a truncated PNG, which Chromium shows partly).
"$py" - << 'PY'
import re
page = open("done.html").read()
payloads = [m.span(1) for m in re.finditer(r'src="data:image/png;base64,([^"]*)"', page)]
(a0, b0), (a1, b1) = payloads[0], payloads[-1]
middle = (a0 + b0) // 2
half = a1 + (b1 - a1) // 8 * 4
page = page[:middle] + "!" + page[middle + 1:half] + page[b1:]
open("corrupt.html", "w").write(page)
PY
probe corrupt.html corrupt.probe.html
shoot corrupt.html
last=$(($(grep -o '<img ' done.html | wc -l) - 1))
"$py" check.py done.html corrupt.probe.dom corrupt.png --size "${size[@]}" --expect-bad "0,$last" ||
  fail "the check did not catch the corrupted images 0 and $last (above)"

# --- the reload, in the browser -------------------------------------------------------------------
# Each page over a local HTTP server that logs every request, in 30 s of Chromium's virtual time:
# the finished report must be requested once; the mid-run one (content="15") again.
"$py" - "$dir" << 'PY' &
import functools, http.server, os, sys
class Handler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):
        with open("requests.log", "a") as log:
            log.write(self.path + "\n")
server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=sys.argv[1]))
with open("port.tmp", "w") as f:
    f.write(str(server.server_address[1]))
os.rename("port.tmp", "port")
server.serve_forever()
PY
server=$!
for _ in $(seq 1 100); do
  [ -f port ] && break
  sleep 0.1
done
[ -f port ] || fail "the HTTP server did not start"
port=$(cat port)
loads() {  # loads PAGE: sets count to how often Chromium requests PAGE in 30 s of virtual time
  local before pid
  touch requests.log
  before=$(grep -c "^/$1$" requests.log || true)
  chrome --virtual-time-budget=30000 --dump-dom "http://127.0.0.1:$port/$1"
  "${cmd[@]}" > /dev/null 2>> browser.log &
  pid=$!
  for _ in $(seq 1 600); do  # a page that reloads keeps this Chromium busy: stopped at 3 requests
    count=$(($(grep -c "^/$1$" requests.log || true) - before))
    [ "$count" -ge 3 ] && break
    kill -0 $pid 2> /dev/null || break
    sleep 0.1
  done
  kill $pid 2> /dev/null || true
  wait $pid 2> /dev/null || true
  count=$(($(grep -c "^/$1$" requests.log || true) - before))
}
loads done.html
[ "$count" -eq 1 ] || fail "the finished report was loaded $count times in 30 s (it must not reload)"
loads running.html
[ "$count" -ge 2 ] || fail "the mid-run report was loaded $count times in 30 s (it must reload every 15 s)"

echo "ok: finished and mid-run report.html in $("$chromium" --version 2> /dev/null | head -n 1):" \
  "images decoded and shown, table, no reload once finished; a corrupted copy fails; $(($(date +%s) - start)) s"
echo "screenshots: $keep_dir/report_browser.png $keep_dir/report_browser_running.png"
