"""backlight.torch: the autograd Function against backlight.render/backward, a same-seed
finite-difference check through torch, its errors, and the examples in a short run."""
import os
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import backlight  # noqa: E402
import backlight.torch  # noqa: E402

ROOT = os.environ.get("BACKLIGHT_ROOT", os.path.join(os.path.dirname(__file__), "..", ".."))
CORNELL = os.path.join(ROOT, "scenes", "cornell", "scene.json")
RES = (24, 20)


def weights(h, w, seed=3):
    return np.random.default_rng(seed).uniform(0.2, 1.0, size=(h, w, 3)).astype(np.float32)


def test_forward_and_backward_agree_with_the_module():
    scene = backlight.load(CORNELL)
    texture = torch.tensor(scene.params["plastic.albedo"], requires_grad=True)
    radiance = torch.tensor(scene.params["light.radiance"], requires_grad=True)
    image = backlight.torch.render(scene, {"plastic.albedo": texture, "light.radiance": radiance}, spp=4, seed=9,
                                   resolution=RES)
    assert image.shape == (RES[1], RES[0], 3) and image.dtype == torch.float32
    np.testing.assert_array_equal(image.detach().numpy(), backlight.render(scene, spp=4, seed=9, resolution=RES))
    a = weights(RES[1], RES[0])
    (image * torch.from_numpy(a)).sum().backward()
    expected = backlight.backward(scene, a, spp=4, seed=9, resolution=RES, params=["plastic.albedo", "light.radiance"])
    for name, tensor in (("plastic.albedo", texture), ("light.radiance", radiance)):
        e = expected[name]
        assert np.linalg.norm(e) > 0
        assert np.linalg.norm(tensor.grad.numpy() - e) <= 1e-5 * np.linalg.norm(e), name


def test_backward_uses_the_values_of_its_forward():
    # Another render with other values between forward and backward must not change the gradient.
    scene = backlight.load(CORNELL)
    theta = scene.params["plastic.albedo"].copy()
    a = weights(RES[1], RES[0], seed=8)
    t1 = torch.tensor(theta, requires_grad=True)
    image = backlight.torch.render(scene, {"plastic.albedo": t1}, spp=4, seed=4, resolution=RES)
    backlight.torch.render(scene, {"plastic.albedo": torch.tensor(theta * 0.5)}, spp=4, seed=4, resolution=RES)
    (image * torch.from_numpy(a)).sum().backward()
    scene.params["plastic.albedo"][...] = theta
    expected = backlight.backward(scene, a, spp=4, seed=4, resolution=RES, params=["plastic.albedo"])["plastic.albedo"]
    assert np.linalg.norm(t1.grad.numpy() - expected) <= 1e-5 * np.linalg.norm(expected)


def test_same_seed_central_differences_through_torch():
    scene = backlight.load(CORNELL, max_depth=4, rr_depth=0)
    a = torch.from_numpy(weights(RES[1], RES[0], seed=12))
    theta = torch.tensor(scene.params["wall.albedo"])
    v = torch.randn(theta.shape, generator=torch.Generator().manual_seed(3))
    eps = 1e-2

    def loss(value):
        image = backlight.torch.render(scene, {"wall.albedo": value}, spp=4, seed=6, resolution=RES)
        return (torch.log1p(image) * a).sum()  # a loss backlight does not know

    t = theta.clone().requires_grad_(True)
    loss(t).backward()
    with torch.no_grad():
        plus, minus = theta + eps * v, theta - eps * v
        fd = (loss(plus).double() - loss(minus).double()) / (2 * eps)
    predicted = (t.grad.double() * (plus - minus).double()).sum() / (2 * eps)
    assert fd != 0
    assert abs(predicted - fd) <= 1e-2 * abs(fd), (float(predicted), float(fd))


def test_bad_tensors_raise():
    scene = backlight.load(CORNELL)
    with pytest.raises(backlight.Error, match="expected shape"):
        backlight.torch.render(scene, {"light.radiance": torch.ones(4)}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="NaN"):
        backlight.torch.render(scene, {"light.radiance": torch.full((3,), float("nan"))}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="unknown parameter 'nope'"):
        backlight.torch.render(scene, {"nope": torch.ones(3)}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="at least one"):
        backlight.torch.render(scene, {}, spp=1, resolution=RES)


@pytest.mark.parametrize("example", ["torch_texture.py", "torch_masked_loss.py"])
def test_examples_run(example, tmp_path):
    script = os.path.join(ROOT, "python", "examples", example)
    r = subprocess.run([sys.executable, script, "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "loss" in r.stdout
