#!/usr/bin/python3
"""Recovers the Cornell box's back-wall texture (scenes/cornell, 1024² RGB) from a rendered image
with torch.optim.Adam, through backlight.torch.render.

The texture starts grey. Each iteration renders the current texture with a fresh seed, compares
it with the target in torch (L2) and steps Adam on the gradient backlight's adjoint pass (path
replay) returns. Every few iterations a validation loss compares the current texture and the true
one rendered with the same random numbers (fixed seed, more samples), so Monte Carlo noise cancels
and the curve shows progress; it is printed and drawn to OUT/loss.png (python3-matplotlib).

    PYTHONPATH=build/python python3 python/examples/torch_texture.py [--out DIR] [--quick]
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

import backlight
import backlight.torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..", "..")

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--iterations", type=int, default=120)
parser.add_argument("--resolution", type=int, default=128, help="square film side")
parser.add_argument("--spp", type=int, default=8, help="samples per pixel of each iteration")
parser.add_argument("--lr", type=float, default=0.04)
parser.add_argument("--out", default="torch_texture_out")
parser.add_argument("--quick", action="store_true", help="a few iterations at a small size (tests)")
args = parser.parse_args()
if args.quick:
    args.iterations, args.resolution = 6, 32
os.makedirs(args.out, exist_ok=True)
res = (args.resolution, args.resolution)

scene = backlight.load(os.path.join(ROOT, "scenes", "cornell", "scene.json"), max_depth=4)
truth = scene.params["wall.albedo"].copy()
target = torch.from_numpy(backlight.render(scene, spp=256 if not args.quick else 16, seed=1000, resolution=res))
validation_spp, validation_seed = (64 if not args.quick else 4), 77
validation_target = torch.from_numpy(backlight.render(scene, spp=validation_spp, seed=validation_seed, resolution=res))
texture = torch.full(truth.shape, 0.5, requires_grad=True)
optimizer = torch.optim.Adam([texture], lr=args.lr)


def validation_loss():
    with torch.no_grad():
        image = backlight.torch.render(scene, {"wall.albedo": texture}, spp=validation_spp, seed=validation_seed,
                                       resolution=res)
        return float(((image - validation_target) ** 2).mean())


curve = [(0, validation_loss())]
start = time.perf_counter()
every = max(1, args.iterations // 8)
for it in range(1, args.iterations + 1):
    optimizer.zero_grad()
    image = backlight.torch.render(scene, {"wall.albedo": texture}, spp=args.spp, seed=it, resolution=res)
    loss = ((image - target) ** 2).mean()
    loss.backward()
    optimizer.step()
    with torch.no_grad():
        texture.clamp_(0.0, 1.0)
    elapsed = time.perf_counter() - start
    eta = elapsed / it * (args.iterations - it)
    print(f"\riteration {it}/{args.iterations}, loss {float(loss):.3e}, {it / elapsed:.1f} it/s, ETA {eta:.0f} s",
          end="", file=sys.stderr, flush=True)
    if it % every == 0 or it == args.iterations:
        curve.append((it, validation_loss()))
print(file=sys.stderr)
seconds = time.perf_counter() - start
first, last = curve[0][1], curve[-1][1]
for it, value in curve:
    print(f"iteration {it:4d}: validation loss {value:.4e}")
print(f"validation loss {first:.4e} -> {last:.4e} ({first / last:.1f}x lower) in {seconds:.1f} s")
np.save(os.path.join(args.out, "texture.npy"), texture.detach().numpy())
try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy([c[0] for c in curve], [c[1] for c in curve], "o-")
    ax.set_xlabel("iteration")
    ax.set_ylabel("validation loss (L2, same random numbers as the truth)")
    ax.set_title("Cornell wall texture through backlight.torch.render")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "loss.png"), dpi=100)
except ImportError:
    print("python3-matplotlib missing: no loss.png", file=sys.stderr)
