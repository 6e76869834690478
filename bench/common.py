"""Shared helpers of the benchmark drivers: run a command in a fresh process and measure its wall
time and peak resident memory (os.wait4's ru_maxrss, the same figure /usr/bin/time -v reports),
write results atomically, and find the build."""
import json
import os
import re
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUILD = os.environ.get("BACKLIGHT_BUILD", os.path.join(ROOT, "build"))
BACKLIGHT = os.path.join(BUILD, "bin", "backlight")
RESULTS = os.path.join(ROOT, "bench", "results")
TMP = os.path.join(RESULTS, "tmp")


def ensure_build():
    if not os.path.exists(BACKLIGHT) or not os.path.exists(os.path.join(BUILD, "bin", "bench_rays")):
        subprocess.run(["cmake", "-S", ROOT, "-B", BUILD, "-DCMAKE_BUILD_TYPE=Release"], check=True,
                       stdout=subprocess.DEVNULL)
        subprocess.run(["cmake", "--build", BUILD, "-j2", "--target", "backlight", "bench_rays"], check=True)
    os.makedirs(TMP, exist_ok=True)


def run(cmd, check=True):
    """Runs cmd; returns dict(seconds, peak_rss_mb, stdout, stderr, returncode)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = proc.communicate()
    # communicate() already reaped the child; its rusage is in RUSAGE_CHILDREN only cumulatively,
    # so re-run through wait4 when we need the per-process peak (see run_measured).
    seconds = time.perf_counter() - start
    if check and proc.returncode != 0:
        sys.stderr.write(err)
        raise SystemExit(f"bench: command failed ({proc.returncode}): {' '.join(cmd)}")
    return {"seconds": seconds, "stdout": out, "stderr": err, "returncode": proc.returncode}


def run_measured(cmd, check=True):
    """Runs cmd in a fresh process; returns seconds, peak RSS (MB) of that process, outputs."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - start
        code = os.waitstatus_to_exitcode(status)
        proc.returncode = code
        out.seek(0)
        err.seek(0)
        result = {"seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024.0, "stdout": out.read(),
                  "stderr": err.read(), "returncode": code}
    if check and code != 0:
        sys.stderr.write(result["stderr"])
        raise SystemExit(f"bench: command failed ({code}): {' '.join(cmd)}")
    return result


def parse_render_summary(stderr):
    """Parses 'render: WxH, N spp, T s, X samples/s, Y rays/s' (k/M/G suffixes)."""
    m = re.search(r"render: (\d+)x(\d+), (\d+) spp, ([0-9.]+) s, ([0-9.]+) ([kMG]?) ?samples/s, ([0-9.]+) ([kMG]?) ?rays/s",
                  stderr)
    if not m:
        raise SystemExit("bench: cannot parse the render summary:\n" + stderr[-500:])
    scale = {"": 1, "k": 1e3, "M": 1e6, "G": 1e9}
    return {"width": int(m.group(1)), "height": int(m.group(2)), "spp": int(m.group(3)), "seconds": float(m.group(4)),
            "samples_per_second": float(m.group(5)) * scale[m.group(6)],
            "rays_per_second": float(m.group(7)) * scale[m.group(8)]}


def write_json(name, data):
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, name)
    with tempfile.NamedTemporaryFile("w", dir=RESULTS, delete=False, suffix=".tmp") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
    os.replace(f.name, path)
    return path


def write_text(name, text):
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, name)
    with tempfile.NamedTemporaryFile("w", dir=RESULTS, delete=False, suffix=".tmp") as f:
        f.write(text)
    os.replace(f.name, path)
    return path


def machine():
    return {"cores": os.cpu_count(), "load_average_at_start": os.getloadavg()[0],
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}


def adjoint_image(path, width, height):
    """A fixed, smooth adjoint image (the weights of a linear functional), written with oiiotool."""
    if not os.path.exists(path):
        subprocess.run(["oiiotool", "--pattern", "fill:topleft=1e-3,-1e-3,5e-4:topright=-1e-3,1e-3,1e-3:"
                        "bottomleft=5e-4,1e-3,-1e-3:bottomright=1e-3,-5e-4,1e-3", f"{width}x{height}", "3",
                        "-d", "float", "-o", path], check=True)
    return path
