"""Shared helpers of the benchmark drivers: run a command in a fresh process and measure its wall
time and peak resident memory (os.wait4's ru_maxrss, the same figure /usr/bin/time -v reports),
write results atomically, and find the build."""
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
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


def _sample_anon(pid, peak, stop):
    """Peak RssAnon (private anonymous memory: heap, buffers; no shared-library pages) of pid into
    peak[0] and its VmHWM into peak[1] (kB), sampled every 10 ms until stop is set. (getrusage's
    ru_maxrss of a child also counts the Python process it was forked from, before exec: wrong for
    processes smaller than this script.)"""
    while not stop.is_set():
        try:
            with open(f"/proc/{pid}/status") as f:
                for line in f:
                    if line.startswith("RssAnon:"):
                        peak[0] = max(peak[0], int(line.split()[1]))
                    elif line.startswith("VmHWM:"):
                        peak[1] = max(peak[1], int(line.split()[1]))
        except OSError:
            return
        stop.wait(0.01)


def run_measured(cmd, check=True, env=None):
    """Runs cmd in a fresh process; returns seconds, peak RSS (MB) of that process (getrusage), its
    peak private anonymous memory (MB, /proc RssAnon sampled every 10 ms), outputs."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env)
        peak, stop = [0, 0], threading.Event()
        sampler = threading.Thread(target=_sample_anon, args=(proc.pid, peak, stop), daemon=True)
        sampler.start()
        _, status, usage = os.wait4(proc.pid, 0)
        stop.set()
        sampler.join()
        seconds = time.perf_counter() - start
        code = os.waitstatus_to_exitcode(status)
        proc.returncode = code
        out.seek(0)
        err.seek(0)
        result = {"seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024.0, "peak_anon_mb": peak[0] / 1024.0,
                  "sampled_hwm_mb": peak[1] / 1024.0,
                  "stdout": out.read(),
                  "stderr": err.read(), "returncode": code}
    if check and code != 0:
        sys.stderr.write(result["stderr"])
        raise SystemExit(f"bench: command failed ({code}): {' '.join(cmd)}")
    return result


def parse_render_summary(stderr):
    """Parses 'render: WxH, N spp, T s, X samples/s, Y rays/s (S% shadow, C% camera)' (k/M/G
    suffixes; the ray mix as fractions of all rays)."""
    m = re.search(r"render: (\d+)x(\d+), (\d+) spp, ([0-9.]+) s, ([0-9.]+) ([kMG]?) ?samples/s, ([0-9.]+) ([kMG]?) ?rays/s"
                  r" \(([0-9.]+)% shadow, ([0-9.]+)% camera\)", stderr)
    if not m:
        raise SystemExit("bench: cannot parse the render summary:\n" + stderr[-500:])
    scale = {"": 1, "k": 1e3, "M": 1e6, "G": 1e9}
    return {"width": int(m.group(1)), "height": int(m.group(2)), "spp": int(m.group(3)), "seconds": float(m.group(4)),
            "samples_per_second": float(m.group(5)) * scale[m.group(6)],
            "rays_per_second": float(m.group(7)) * scale[m.group(8)],
            "shadow_fraction": float(m.group(9)) / 100, "camera_fraction": float(m.group(10)) / 100}


def write_json(name, data):
    """Writes bench/results/NAME atomically, unless the run started on a machine whose load
    average exceeded its core count (then the figures go to bench/results/tmp/ only, and the
    script exits non-zero)."""
    os.makedirs(RESULTS, exist_ok=True)
    refused = _START_LOAD is not None and _START_LOAD > (os.cpu_count() or 1)
    folder = TMP if refused else RESULTS
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, name)
    with tempfile.NamedTemporaryFile("w", dir=folder, delete=False, suffix=".tmp") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
    os.replace(f.name, path)
    if refused:
        raise SystemExit(f"bench: load average {_START_LOAD:.2f} > {os.cpu_count()} cores at start: results "
                         f"refused (kept in {path} for inspection); rerun on a quiet machine")
    return path


def plot_performance():
    """Redraws bench/results/performance.png (tools/plot_perf) from the latest results of
    bench/primal, bench/gradient, bench/volume and bench/profile."""
    # tools/plot_perf runs under /usr/bin/python3 (its #! line), whatever python runs the bench.
    if subprocess.run(["/usr/bin/python3", "-c", "import matplotlib"], stderr=subprocess.DEVNULL).returncode != 0:
        print("bench: python3-matplotlib missing, no plot (tools/deps installs it)")
        return
    subprocess.run([os.path.join(ROOT, "tools", "plot_perf"), RESULTS], check=True)


def write_text(name, text):
    """Like write_json, for CSV and tables; a refused run's text goes to bench/results/tmp/."""
    refused = _START_LOAD is not None and _START_LOAD > (os.cpu_count() or 1)
    folder = TMP if refused else RESULTS
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, name)
    with tempfile.NamedTemporaryFile("w", dir=folder, delete=False, suffix=".tmp") as f:
        f.write(text)
    os.replace(f.name, path)
    return path


_START_LOAD = None


def machine():
    """Machine facts and the run's name, recorded at the start of a benchmark. Prints the load
    average: results measured on a machine busier than its core count are noise, and
    write_json refuses them."""
    global _START_LOAD
    _START_LOAD = os.getloadavg()[0]
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "unknown"
    date = time.strftime("%Y-%m-%d %H:%M:%S")
    cores = os.cpu_count()
    print(f"bench: load average {_START_LOAD:.2f} on {cores} cores at start", file=sys.stderr)
    if _START_LOAD > cores:
        print(f"bench: the load exceeds the core count: results will not be written to {RESULTS}",
              file=sys.stderr)
    return {"cores": cores, "load_average_at_start": _START_LOAD, "date": date, "commit": commit,
            "run": f"{date[:10]} {commit}"}


def adjoint_image(path, width, height):
    """A fixed, smooth adjoint image (the weights of a linear functional), written with oiiotool."""
    if not os.path.exists(path):
        subprocess.run(["oiiotool", "--pattern", "fill:topleft=1e-3,-1e-3,5e-4:topright=-1e-3,1e-3,1e-3:"
                        "bottomleft=5e-4,1e-3,-1e-3:bottomright=1e-3,-5e-4,1e-3", f"{width}x{height}", "3",
                        "-d", "float", "-o", path], check=True)
    return path
