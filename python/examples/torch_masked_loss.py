#!/usr/bin/python3
"""A loss the backlight CLI cannot express: only the pixels inside a mask count, compared in log
space at three scales (an average-pooled image pyramid), plus a torch-side prior. The rendered image
is an ordinary torch tensor, so any differentiable torch code can follow backlight.torch.render.

Fits the light's radiance and the plastic box's albedo of scenes/cornell to a target rendered
with other values, looking only at the lower half of the image (the box and the floor). Writes
OUT/compare.png (target | first iteration | last, the mask's edge marked) and OUT/loss.png
(python3-matplotlib).

    PYTHONPATH=build/python python3 python/examples/torch_masked_loss.py [--out DIR] [--quick]
"""
import argparse
import os
import sys
import time

import torch
import torch.nn.functional as F

import backlight
import backlight.torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..", "..")

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--iterations", type=int, default=150)
parser.add_argument("--resolution", type=int, default=96)
parser.add_argument("--out", default="torch_masked_loss_out")
parser.add_argument("--quick", action="store_true", help="a few iterations at a small size (tests)")
args = parser.parse_args()
if args.quick:
    args.iterations, args.resolution = 5, 32
os.makedirs(args.out, exist_ok=True)
res = (args.resolution, args.resolution)
scene_file = os.path.join(ROOT, "scenes", "cornell", "scene.json")

truth = {"light.radiance": [12.0, 14.0, 8.0], "plastic.albedo": [0.3, 0.6, 0.25]}
target_scene = backlight.load(scene_file, set=truth, max_depth=4)
target = torch.from_numpy(backlight.render(target_scene, spp=64, seed=500, resolution=res))

scene = backlight.load(scene_file, max_depth=4)
params = {name: torch.tensor(scene.params[name], requires_grad=True) for name in truth}
optimizer = torch.optim.Adam([{"params": [params["light.radiance"]], "lr": 0.2},
                              {"params": [params["plastic.albedo"]], "lr": 0.01}])
mask = torch.zeros(res[1], res[0], 1)
mask[res[1] // 2:] = 1.0  # lower half only


def pyramid_log_loss(image):
    a = torch.log1p(image * mask).permute(2, 0, 1)[None]
    b = torch.log1p(target * mask).permute(2, 0, 1)[None]
    total = 0.0
    for _ in range(3):
        total = total + (a - b).abs().mean()
        a, b = F.avg_pool2d(a, 2), F.avg_pool2d(b, 2)
    return total


start = time.perf_counter()
losses, first_image = [], None
for it in range(1, args.iterations + 1):
    optimizer.zero_grad()
    image = backlight.torch.render(scene, params, spp=8, seed=it, resolution=res)
    loss = pyramid_log_loss(image)
    # A torch-side prior: keep the albedo's channels from drifting apart without evidence.
    loss = loss + 1e-3 * params["plastic.albedo"].var()
    loss.backward()
    optimizer.step()
    with torch.no_grad():
        params["plastic.albedo"].clamp_(0.0, 1.0)
        params["light.radiance"].clamp_(min=0.0)
    losses.append(float(loss))
    if it == 1:
        first, first_image = float(loss), image.detach()
    elapsed = time.perf_counter() - start
    print(f"\riteration {it}/{args.iterations}, loss {float(loss):.4f}, {it / elapsed:.1f} it/s, "
          f"ETA {elapsed / it * (args.iterations - it):.0f} s", end="", file=sys.stderr, flush=True)
print(file=sys.stderr)
print(f"loss {first:.4f} -> {float(loss):.4f} in {time.perf_counter() - start:.1f} s")
for name, value in params.items():
    print(f"{name}: {[round(v, 3) for v in value.detach().tolist()]} (target {truth[name]})")
try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.4))
    for ax, (title, img) in zip(axes, [("target", target), ("iteration 1", first_image),
                                       (f"iteration {args.iterations}", image.detach())]):
        ax.imshow((img.clamp(min=0) ** (1 / 2.2)).clamp(max=1).numpy())  # gamma 2.2 for display
        ax.axhline(res[1] / 2 - 0.5, color="orange", lw=1)  # the loss sees the pixels below this line
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "compare.png"), dpi=100)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy(range(1, len(losses) + 1), losses)
    ax.set_xlabel("iteration")
    ax.set_ylabel("masked log-space pyramid loss (8 spp, noisy)")
    ax.set_title("Cornell light and box albedo through backlight.torch.render")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "loss.png"), dpi=100)
except ImportError:
    print("python3-matplotlib missing: no compare.png or loss.png", file=sys.stderr)
