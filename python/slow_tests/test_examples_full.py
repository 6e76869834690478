"""The examples at full size (ctest -L slow): the texture optimization's validation loss drops at
least 5x in its 120 iterations. Its wall time (24 s on the development machine, against the 2 minutes
the issue allows) is reported in the README, not asserted: timings belong in bench/."""
import os
import re
import subprocess
import sys

ROOT = os.environ.get("BACKLIGHT_ROOT", os.path.join(os.path.dirname(__file__), "..", ".."))


def test_torch_texture_converges(tmp_path):
    script = os.path.join(ROOT, "python", "examples", "torch_texture.py")
    r = subprocess.run([sys.executable, script, "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    m = re.search(r"validation loss (\S+) -> (\S+) \((\S+)x lower\) in (\S+) s", r.stdout)
    assert m, r.stdout
    first, last = float(m.group(1)), float(m.group(2))
    assert first / last >= 5, r.stdout
    assert os.path.exists(tmp_path / "loss.png")
