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
    r = torch.tensor(scene.params["light.radiance"])
    with pytest.raises(backlight.Error, match="expected a torch.Tensor"):
        backlight.torch.render(scene, {"light.radiance": np.ones(3, np.float32)}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="floating-point"):
        backlight.torch.render(scene, {"light.radiance": torch.ones(3, dtype=torch.bool)}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="unknown method 'magic'"):  # at forward, not in backward
        backlight.torch.render(scene, {"light.radiance": r}, spp=1, resolution=RES, method="magic")
    # Not a scene, params not a dict: AttributeError and TypeError from inside the wrapper.
    with pytest.raises(backlight.Error, match="scene: expected a backlight.Scene"):
        backlight.torch.render(None, {"light.radiance": r}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="params: expected a dict"):
        backlight.torch.render(scene, [("light.radiance", r)], spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="adjoint_seed: expected an integer"):
        backlight.torch.render(scene, {"light.radiance": r}, spp=1, resolution=RES, adjoint_seed=2.0)


def test_numpy_integers_are_seeds():
    # adjoint_seed=np.uint64(2) was refused ("expected an integer ..., got 2") while the module's
    # own seeds took it.
    scene = backlight.load(CORNELL)
    r = torch.tensor(scene.params["light.radiance"], requires_grad=True)
    image = backlight.torch.render(scene, {"light.radiance": r}, spp=1, seed=np.int64(2), resolution=RES,
                                   adjoint_seed=np.uint64(5))
    image.sum().backward()
    r2 = torch.tensor(scene.params["light.radiance"], requires_grad=True)
    backlight.torch.render(scene, {"light.radiance": r2}, spp=1, seed=2, resolution=RES,
                           adjoint_seed=5).sum().backward()
    assert torch.equal(r.grad, r2.grad)


def test_a_failed_forward_leaves_the_scene_unchanged():
    # An invalid tensor used to be written before the error (every later render then failed), and
    # tensors before an unknown name were written.
    scene = backlight.load(CORNELL)
    radiance = scene.params["light.radiance"].copy()
    with pytest.raises(backlight.Error, match="valid range"):
        backlight.torch.render(scene, {"light.radiance": torch.tensor([-1.0, 1.0, 1.0])}, spp=1, resolution=RES)
    with pytest.raises(backlight.Error, match="unknown parameter 'nope'"):
        backlight.torch.render(scene, {"light.radiance": torch.tensor(radiance * 2), "nope": torch.ones(3)}, spp=1,
                               resolution=RES)
    np.testing.assert_array_equal(scene.params["light.radiance"], radiance)
    backlight.render(scene, spp=1, resolution=RES)


def test_other_parameters_changed_before_backward_raise():
    # The gradient used to be taken at the changed value of a parameter the render did not take as a
    # tensor (another render's tensors, or a write through a view).
    scene = backlight.load(CORNELL)
    t = torch.tensor(scene.params["light.radiance"], requires_grad=True)
    image = backlight.torch.render(scene, {"light.radiance": t}, spp=2, seed=5, resolution=RES)
    backlight.torch.render(scene, {"plastic.albedo": torch.tensor([0.9, 0.1, 0.1])}, spp=2, seed=5, resolution=RES)
    with pytest.raises(backlight.Error, match="'plastic.albedo' changed between this render's forward and backward"):
        image.sum().backward()
    # Put back, the same graph's backward gives the module's gradient.
    scene.params["plastic.albedo"][...] = backlight.load(CORNELL).params["plastic.albedo"]
    image = backlight.torch.render(scene, {"light.radiance": t}, spp=2, seed=5, resolution=RES)
    image.sum().backward()
    expected = backlight.backward(scene, np.ones((RES[1], RES[0], 3), np.float32), spp=2, seed=5, resolution=RES,
                                  params=["light.radiance"])["light.radiance"]
    np.testing.assert_allclose(t.grad.numpy(), expected, rtol=1e-6)


def test_double_backward_raises():
    # Second-order terms used to be dropped silently (the gradient had no graph).
    scene = backlight.load(CORNELL)
    t = torch.tensor(scene.params["light.radiance"], requires_grad=True)
    loss = (backlight.torch.render(scene, {"light.radiance": t}, spp=1, seed=0, resolution=(8, 8)) ** 2).sum()
    g, = torch.autograd.grad(loss, t, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiate twice"):
        (g.sum() + t.sum()).backward()


def test_a_gradient_taken_with_create_graph_is_not_silently_constant():
    # once_differentiable raises only when grad_output has a graph: for a loss linear in the image
    # (grad_output constant) the gradient came back without one, so a gradient penalty lost its
    # second-order terms silently and torch.autograd.grad(g.sum(), t) said "does not require grad".
    scene = backlight.load(CORNELL)
    t = torch.tensor(scene.params["white.albedo"], requires_grad=True)
    image = backlight.torch.render(scene, {"white.albedo": t}, spp=1, seed=0, resolution=(8, 8))
    g, = torch.autograd.grad(image.sum(), t, create_graph=True)
    expected = backlight.backward(scene, np.ones((8, 8, 3), np.float32), spp=1, seed=0, resolution=(8, 8),
                                  params=["white.albedo"])["white.albedo"]
    np.testing.assert_array_equal(g.detach().numpy(), expected)  # first derivatives as without create_graph
    with pytest.raises(RuntimeError, match="differentiate twice: backlight.torch.render has no second derivatives"):
        torch.autograd.grad(g.sum(), t)
    with pytest.raises(RuntimeError, match="no second derivatives"):
        ((g ** 2).sum() + image.sum()).backward()


def test_docstrings_say_albedo_gradients_are_exact_only_with_russian_roulette_off():
    # They called the same-seed gradient exact "for parameters sampling does not depend on", which
    # albedos and textures are not while Russian roulette is on (its probability uses the throughput).
    for doc in (backlight.torch.__doc__, backlight.torch.render.__doc__):
        assert "rr_depth=0" in " ".join(doc.split()), doc


def test_a_meta_tensor_is_refused_by_name():
    # torch.empty(..., device="meta") has a shape and no values: NotImplementedError "Cannot copy out
    # of meta tensor; no data!" came out of the conversion, naming no parameter.
    scene = backlight.load(CORNELL)
    with pytest.raises(backlight.Error) as info:
        backlight.torch.render(scene, {"light.radiance": torch.empty(3, device="meta")}, spp=1, resolution=(8, 8))
    assert str(info.value) == "light.radiance: a tensor on the 'meta' device has no values", str(info.value)
    # A layout NumPy cannot read (sparse): the same kind of one-line error.
    with pytest.raises(backlight.Error, match="^light.radiance: .*sparse"):
        backlight.torch.render(scene, {"light.radiance": torch.ones(3).to_sparse()}, spp=1, resolution=(8, 8))


def test_set_with_a_tensor_that_requires_grad_says_what_to_do():
    # The message was "expected a number, numbers (a list or an array) or an image file name, got
    # Tensor" (NumPy's conversion refuses a tensor that requires grad).
    with pytest.raises(backlight.Error) as info:
        backlight.load(CORNELL, set={"light.radiance": torch.ones(3, requires_grad=True)})
    text = str(info.value)
    assert text.startswith("set: 'light.radiance': a tensor that requires grad") and "\n" not in text, text
    assert ".detach()" in text and "backlight.torch.render" in text, text
    scene = backlight.load(CORNELL, set={"light.radiance": torch.full((3,), 2.0, requires_grad=True).detach()})
    np.testing.assert_array_equal(scene.params["light.radiance"], [2, 2, 2])


def test_a_0d_value_for_a_one_element_parameter():
    # plastic.roughness has shape (1,): torch.tensor(0.3) and 0.3 were refused ("expected shape (1,),
    # got ()"). The gradient comes back in the shape given.
    scene = backlight.load(CORNELL)
    assert tuple(scene.params["plastic.roughness"].shape) == (1,)
    one = torch.tensor([0.3], requires_grad=True)
    reference = backlight.torch.render(scene, {"plastic.roughness": one}, spp=2, seed=4, resolution=(8, 8))
    reference.sum().backward()
    zero_d = torch.tensor(0.3, requires_grad=True)
    image = backlight.torch.render(scene, {"plastic.roughness": zero_d}, spp=2, seed=4, resolution=(8, 8))
    image.sum().backward()
    assert torch.equal(image, reference)
    assert zero_d.grad.shape == () and float(zero_d.grad) == float(one.grad[0]) != 0
    number = backlight.torch.render(scene, {"plastic.roughness": 0.3, "light.radiance": torch.ones(3) * 17}, spp=2,
                                    seed=4, resolution=(8, 8))
    assert number.shape == (8, 8, 3)
    with pytest.raises(backlight.Error, match=r"light.radiance: expected shape \(3,\), got \(\)"):
        backlight.torch.render(scene, {"light.radiance": torch.tensor(1.0)}, spp=1, resolution=(8, 8))
    with pytest.raises(backlight.Error, match="light.radiance: expected a torch.Tensor"):
        backlight.torch.render(scene, {"light.radiance": True}, spp=1, resolution=(8, 8))


def test_a_failed_pass_restores_the_values_it_wrote():
    # The tensors were written before the pass, which can still refuse (a camera the scene lacks, a
    # degenerate pose): the scene kept them, and a degenerate pose broke every later render.
    scene = backlight.load(os.path.join(ROOT, "scenes", "pose", "scene.json"))
    radiance = scene.params["light.radiance"].copy()
    positions = scene.params["box.positions"].copy()
    with pytest.raises(backlight.Error, match="camera 7"):
        backlight.torch.render(scene, {"light.radiance": torch.tensor(radiance * 2)}, camera=7, resolution=(8, 8))
    np.testing.assert_array_equal(scene.params["light.radiance"], radiance)
    with pytest.raises(backlight.Error, match="degenerate"):
        backlight.torch.render(scene, {"box.positions": torch.zeros(positions.shape)}, spp=1, resolution=(8, 8))
    np.testing.assert_array_equal(scene.params["box.positions"], positions)
    backlight.render(scene, spp=1, resolution=(8, 8))


def test_tensors_without_grad_are_not_differentiated():
    # A fixed camera pose passed as a tensor asked for geometry gradients, which the Cornell box's
    # conductor cannot give: backward failed although only the albedo wanted a gradient.
    scene = backlight.load(CORNELL)
    origin = torch.tensor(scene.params["main.origin"])
    albedo = torch.tensor(scene.params["white.albedo"], requires_grad=True)
    image = backlight.torch.render(scene, {"main.origin": origin, "white.albedo": albedo}, spp=1, seed=2,
                                   resolution=(16, 16))
    image.sum().backward()
    expected = backlight.backward(scene, np.ones((16, 16, 3), np.float32), spp=1, seed=2, resolution=(16, 16),
                                  params=["white.albedo"])["white.albedo"]
    np.testing.assert_allclose(albedo.grad.numpy(), expected, rtol=1e-6)


def test_a_tensor_sharing_the_scenes_memory_keeps_its_forwards_values():
    # torch.from_numpy(scene.params[name]) is the scene's memory: a later render overwrote it, and
    # backward took the gradient at the later values.
    scene = backlight.load(CORNELL)
    theta = scene.params["white.albedo"].copy()
    shared = torch.from_numpy(scene.params["white.albedo"]).requires_grad_()
    a = weights(16, 16, seed=6)
    image = backlight.torch.render(scene, {"white.albedo": shared}, spp=2, seed=1, resolution=(16, 16))
    backlight.torch.render(scene, {"white.albedo": torch.tensor([0.1, 0.1, 0.1])}, spp=2, seed=1, resolution=(16, 16))
    (image * torch.from_numpy(a)).sum().backward()
    scene.params["white.albedo"][...] = theta
    expected = backlight.backward(scene, a, spp=2, seed=1, resolution=(16, 16), params=["white.albedo"])
    np.testing.assert_allclose(shared.grad.numpy(), expected["white.albedo"], rtol=1e-6)


def test_renders_from_two_threads_use_their_own_values():
    # Two threads' tensors were written between the other's write and render: most images were
    # rendered with the other thread's values.
    import threading
    scene = backlight.load(CORNELL)
    values = {0: np.array([4.0, 4.0, 4.0], np.float32), 1: np.array([30.0, 10.0, 2.0], np.float32)}
    reference = {}
    for k, v in values.items():
        scene.params["light.radiance"][...] = v
        reference[k] = backlight.render(scene, spp=1, seed=1, resolution=(16, 16))
    wrong = []

    def work(k):
        for _ in range(8):
            image = backlight.torch.render(scene, {"light.radiance": torch.tensor(values[k])}, spp=1, seed=1,
                                           resolution=(16, 16))
            if not np.array_equal(image.numpy(), reference[k]):
                wrong.append(k)

    threads = [threading.Thread(target=work, args=(k,)) for k in values]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not wrong


def test_clear_errors_for_the_loss_gradient_and_float32_range():
    scene = backlight.load(CORNELL)
    t = torch.tensor(scene.params["white.albedo"], requires_grad=True)
    image = backlight.torch.render(scene, {"white.albedo": t}, spp=1, resolution=(8, 8))
    bad = torch.ones_like(image)
    bad[2, 5, 1] = float("nan")
    with pytest.raises(backlight.Error, match=r"NaN or infinite at pixel \(row 2, column 5, channel 1\)"):
        (image * bad).sum().backward()
    with pytest.raises(backlight.Error, match="beyond the float32 range"):
        backlight.torch.render(scene, {"light.radiance": torch.tensor([1e39, 1.0, 1.0], dtype=torch.float64)})
    with pytest.raises(backlight.Error, match="adjoint_seed"):
        backlight.torch.render(scene, {"white.albedo": t}, adjoint_seed=-1)


def test_exit_while_a_daemon_thread_renders():
    # At interpreter exit a daemon thread taking the GIL back is ended by pthread_exit; inside
    # pybind11's GIL guard (a destructor) that unwinding aborted the process ("terminate called
    # without an active exception", exit 134; torch's slow shutdown made it nearly certain). The
    # pass is now stopped at exit and the thread ends with an error.
    script = ("import torch, backlight, threading, time, sys\n"
              f"s = backlight.load({CORNELL!r})\n"
              "threading.Thread(target=lambda: backlight.render(s, spp=64, resolution=(256, 256)), daemon=True).start()\n"
              "time.sleep(0.5)\n"
              "sys.exit(0)\n")
    # The thread's error then printed a traceback while the interpreter finalized, cut off mid-line
    # ("Exception in thread Thread-1 (<lambda>):\nTraceback ..."; 5 runs in 5 with torch imported):
    # it is now SystemExit, which ends a thread without a word. A loop of renders (the next pass
    # refused) ends the same way.
    loop = script.replace("lambda: backlight.render(s, spp=64, resolution=(256, 256))",
                          "lambda: [backlight.render(s, spp=4, resolution=(64, 64)) for _ in range(10**6)]")
    for code in (script, script, loop):
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        assert "terminate called" not in r.stderr
        assert r.stderr == "", r.stderr[-2000:]


@pytest.mark.parametrize("example", ["torch_texture.py", "torch_masked_loss.py"])
def test_examples_run(example, tmp_path):
    script = os.path.join(ROOT, "python", "examples", example)
    r = subprocess.run([sys.executable, script, "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "loss" in r.stdout
    # Results people look at are pictures (python3-matplotlib is a dependency, tools/deps).
    pictures = ["loss.png"] + (["compare.png"] if example == "torch_masked_loss.py" else [])
    for name in pictures:
        assert (tmp_path / name).stat().st_size > 0, name
