"""The Python module: parameter views, render and gradients against the CLI and against exact and
finite-difference derivatives, the GIL, and every kind of bad argument."""
import math
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import backlight

ROOT = os.environ.get("BACKLIGHT_ROOT", os.path.join(os.path.dirname(__file__), "..", ".."))
BIN = os.environ.get("BACKLIGHT_BIN", os.path.join(ROOT, "build", "bin"))
CORNELL = os.path.join(ROOT, "scenes", "cornell", "scene.json")
RES = (24, 20)  # (width, height): small and not square, so axis mix-ups show


def read_pfm(path):
    with open(path, "rb") as f:
        assert f.readline().strip() == b"PF"
        w, h = (int(v) for v in f.readline().split())
        assert float(f.readline()) < 0  # little endian
        data = np.frombuffer(f.read(), dtype="<f4").reshape(h, w, 3)
    return data[::-1]  # rows are stored bottom-up


def write_pfm(path, image):
    h, w, _ = image.shape
    with open(path, "wb") as f:
        f.write(b"PF\n%d %d\n-1\n" % (w, h))
        f.write(np.ascontiguousarray(image[::-1], dtype="<f4").tobytes())  # rows bottom-up
    return path


def weights(h, w, seed=3):
    return np.random.default_rng(seed).uniform(0.2, 1.0, size=(h, w, 3)).astype(np.float32)


@pytest.fixture
def scene():
    return backlight.load(CORNELL)


def test_params_are_writable_views_without_copies(scene):
    params = scene.params
    wall = params["wall.albedo"]
    assert wall.dtype == np.float32 and wall.ndim == 3 and wall.shape[2] == 3
    assert tuple(wall.shape) == tuple(scene.param_info["wall.albedo"]["shape"])
    assert params["light.radiance"].shape == (3,)
    # Two accesses see the same memory: a write through one shows in the other.
    again = scene.params["wall.albedo"]
    assert np.shares_memory(wall, again)
    wall[0, 0] = [0.25, 0.5, 0.75]
    np.testing.assert_array_equal(scene.params["wall.albedo"][0, 0], [0.25, 0.5, 0.75])


def test_render_matches_the_cli_bitwise(scene, tmp_path):
    image = backlight.render(scene, spp=4, seed=5, resolution=RES)
    assert image.shape == (RES[1], RES[0], 3) and image.dtype == np.float32
    out = tmp_path / "cli.pfm"
    subprocess.run([os.path.join(BIN, "backlight"), "render", CORNELL, "--spp", "4", "--seed", "5", "--resolution",
                    f"{RES[0]}x{RES[1]}", "-q", "-o", str(out)], check=True)
    np.testing.assert_array_equal(image, read_pfm(out))
    # The camera's own film is restored after a call with a resolution.
    assert scene.cameras[0] == (512, 512)


def test_writes_through_views_change_the_render(scene):
    before = backlight.render(scene, spp=2, seed=1, resolution=RES)
    scene.params["light.radiance"][:] *= 2
    after = backlight.render(scene, spp=2, seed=1, resolution=RES)
    # Every pixel's light comes from the one emitter: the image doubles exactly (a power of two).
    np.testing.assert_array_equal(after, 2 * before)


def test_emitter_gradient_is_exact(scene):
    # The image is linear in the only emitter's radiance: dF/dL_c = sum(a_c I_c) / L_c for F = sum(a I).
    a = weights(RES[1], RES[0])
    image = backlight.render(scene, spp=4, seed=7, resolution=RES)
    grads = backlight.backward(scene, a, spp=4, seed=7, resolution=RES, params=["light.radiance"])
    assert set(grads) == {"light.radiance"}
    radiance = scene.params["light.radiance"]
    exact = (a.astype(np.float64) * image).sum(axis=(0, 1)) / radiance
    np.testing.assert_allclose(grads["light.radiance"], exact, rtol=2e-6)


def test_texture_gradient_matches_same_seed_central_differences():
    # Russian roulette off: its continuation probability depends on the albedo, which same-seed
    # differences would see and the detached estimator (like Mitsuba's) leaves out.
    scene = backlight.load(CORNELL, max_depth=4, rr_depth=0)
    a = weights(RES[1], RES[0], seed=11)
    name = "plastic.albedo"
    grads = backlight.backward(scene, a, spp=4, seed=2, resolution=RES, params=[name])
    theta = scene.params[name].copy()
    v = np.random.default_rng(5).standard_normal(theta.shape).astype(np.float32)
    eps = 1e-2

    def functional(value):
        scene.params[name][...] = value
        return float((a.astype(np.float64) * backlight.render(scene, spp=4, seed=2, resolution=RES)).sum())

    step_plus, step_minus = (theta + eps * v).astype(np.float32), (theta - eps * v).astype(np.float32)
    fd = (functional(step_plus) - functional(step_minus)) / (2 * eps)
    predicted = float((grads[name].astype(np.float64) * (step_plus - step_minus)).sum()) / (2 * eps)
    scene.params[name][...] = theta
    assert fd != 0
    assert abs(predicted - fd) <= 1e-2 * abs(fd), (predicted, fd)


def test_grad_is_backward_of_the_loss_gradient(scene):
    target = weights(RES[1], RES[0], seed=4) * 0.3
    loss, grads, image = backlight.grad(scene, target, loss="l2", spp=4, seed=3, resolution=RES, params=["wall.albedo"])
    diff = image.astype(np.float64) - target
    assert loss == pytest.approx(np.mean(diff * diff), rel=1e-6)
    d_image = (2 * diff / diff.size).astype(np.float32)
    expected = backlight.backward(scene, d_image, spp=4, seed=3, resolution=RES, params=["wall.albedo"])
    g, e = grads["wall.albedo"], expected["wall.albedo"]
    assert np.linalg.norm(e) > 0
    assert np.linalg.norm(g - e) <= 1e-5 * np.linalg.norm(e)


def test_renders_release_the_gil(scene):
    ticks = []
    done = threading.Event()

    def render():
        backlight.render(scene, spp=64, seed=1, resolution=(96, 96))
        done.set()

    thread = threading.Thread(target=render)
    start = time.perf_counter()
    thread.start()
    while not done.is_set():
        ticks.append(time.perf_counter())
        time.sleep(0.005)
    thread.join()
    elapsed = time.perf_counter() - start
    # Holding the GIL for the whole render would leave the loop one tick at most.
    assert len(ticks) >= 5, (len(ticks), elapsed)


class FailingIndex:
    def __index__(self):
        raise TypeError("only integer tensors of a single element can be converted to an index")


@pytest.mark.parametrize("call, message", [
    (lambda s: backlight.load("/nonexistent/scene.json"), "/nonexistent/scene.json"),
    (lambda s: backlight.load(CORNELL, set={"nope.albedo": 1}), "unknown parameter 'nope.albedo'"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance": [1, 2]}), "light.radiance"),
    (lambda s: backlight.load(CORNELL, max_depth=0), "max_depth"),
    (lambda s: backlight.render(s, spp=0), "spp: 0 is out of range (1..1048576)"),
    # Wrong types and ranges of keyword arguments raised pybind11's TypeError ("incompatible
    # function arguments"), naming neither the argument nor the problem.
    (lambda s: backlight.render(s, spp=2.5), "spp: expected an integer, got float 2.5"),
    (lambda s: backlight.render(s, seed=-1), "seed: -1 is out of range"),
    (lambda s: backlight.render(s, resolution=(16, 16, 1)), "resolution: expected (width, height), got (16, 16, 1)"),
    (lambda s: backlight.render(s, resolution=(16, "a")), "resolution: height: expected an integer"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3), np.float32), resolution=RES, params="white.albedo"),
     "params: expected a list of parameter names, got the str 'white.albedo'"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3), np.float32), resolution=RES, adjoint_seed=-3),
     "adjoint_seed: -3 is out of range"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3), np.float32), resolution=RES, method=3),
     "method: expected a str, got int 3"),
    (lambda s: backlight.load(CORNELL, set=[1]), "set: expected a dict {name: value}, got list [1]"),
    (lambda s: backlight.load(CORNELL, max_depth="3"), "max_depth: expected an integer, got str '3'"),
    (lambda s: backlight.load(3), "path: expected a file name (str, bytes or os.PathLike), got int"),
    (lambda s: backlight.render(s, camera=99), "camera 99"),
    (lambda s: backlight.render(s, resolution=(0, 10)), "resolution"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3), np.float32), resolution=RES, method="magic"),
     "unknown method 'magic'"),
    (lambda s: backlight.backward(s, np.zeros((24, 20, 3), np.float32), resolution=RES), "expected shape (20, 24, 3)"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3)), resolution=RES), "expected dtype float32"),
    (lambda s: backlight.backward(s, np.zeros((20, 48, 3), np.float32)[:, ::2], resolution=RES), "C-contiguous"),
    (lambda s: backlight.backward(s, np.full((20, 24, 3), np.nan, np.float32), resolution=RES), "NaN"),
    (lambda s: backlight.backward(s, [[0.0]], resolution=RES), "expected a NumPy array"),
    (lambda s: backlight.backward(s, np.zeros((20, 24, 3), np.float32), resolution=RES, params=["nope"]),
     "params: unknown parameter 'nope' (see scene.params)"),
    (lambda s: backlight.grad(s, np.zeros((20, 24, 3), np.float32), resolution=RES, loss="l7"), "l7"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance": []}), "got 0 values"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance": ""}), "an empty file name"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance=1": 2}), "unknown parameter 'light.radiance=1'"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance": True}), "expected a number"),
    (lambda s: backlight.load(CORNELL, set={"light.radiance": ["a", "b", "c"]}), "expected a number"),
    # A string that is neither a file nor numbers: the message speaks of set=, not the CLI's --set.
    (lambda s: backlight.load(CORNELL, set={"white.albedo": "abc"}), "set: white.albedo: 'abc' is neither numbers"),
    # Messages quoting bytes that are not UTF-8 (a PNG read as JSON; a bytes path) came through empty.
    (lambda s: backlight.load(os.path.join(ROOT, "scenes", "cornell", "wall.png")), "malformed JSON"),
    (lambda s: backlight.load(b"/nonexistent/\xff.json"), "/nonexistent/\\xff.json: file not found"),
    (lambda s: backlight.check(s, "light.radiance", resolution=RES), "give exactly one of target and d_image"),
    (lambda s: backlight.check(s, "nope", d_image=np.ones((20, 24, 3), np.float32), resolution=RES),
     "param: unknown parameter 'nope'"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES, eps=0),
     "eps: expected a finite number > 0"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               eps="big"), "eps: expected a number, got str"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               directions=0), "directions: 0 is out of range"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               seeds=0), "seeds: 0 is out of range"),
    (lambda s: backlight.check(s, "light.radiance", target=np.ones((24, 20, 3), np.float32), resolution=RES),
     "target: expected shape (20, 24, 3)"),
    # None where an integer is required was read as an empty optional: resolution=(None, None)
    # rendered at a size from memory, check's direction_seed=None used an arbitrary seed and
    # seeds=None ran on (helper-33 audit).
    (lambda s: backlight.render(s, spp=1, resolution=(None, None)),
     "resolution: width: expected an integer, got NoneType None"),
    (lambda s: backlight.render(s, spp=1, resolution=(8, None)), "resolution: height: expected an integer"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               direction_seed=None), "direction_seed: expected an integer, got NoneType None"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               directions=None), "directions: expected an integer"),
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               seeds=None), "seeds: expected an integer"),
    # An object whose __index__ fails (torch.tensor(2.5)) gave its TypeError without the name.
    (lambda s: backlight.render(s, spp=FailingIndex()), "spp: expected an integer, got FailingIndex"),
    # None in set= became NaN ("element 0 is NaN or infinite").
    (lambda s: backlight.load(CORNELL, set={"light.radiance": None}), "'light.radiance': expected a number"),
    # An array of the wrong layout was taken in C order: a (3, H, W) texture scrambled its channels.
    (lambda s: backlight.load(CORNELL, set={"wall.albedo": np.zeros((3, 1024, 1024), np.float32)}),
     "'wall.albedo': expected shape (1024, 1024, 3) or a flat sequence, got (3, 1024, 1024)"),
    # A str path that is not UTF-8 (os.listdir's surrogate escapes) failed to cast (RuntimeError).
    (lambda s: backlight.load("/nonexistent/\udcff.json"), "/nonexistent/\\xff.json: file not found"),
    # Messages of the passes named the CLI's flags (--eps, --adjoint-seed) instead of the keywords.
    (lambda s: backlight.check(s, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), resolution=RES,
                               eps=1e-12),
     "eps 1e-12: θ ± eps·v of 'light.radiance' rounds to θ in float for every element (use a larger eps)"),
    (lambda s: backlight.check(s, "white.albedo", d_image=np.ones((20, 24, 3), np.float32), resolution=RES, eps=5),
     "eps 5 is not smaller than the width of the valid range [0, 1] of 'white.albedo'"),
    (lambda s: backlight.backward(s, np.ones((20, 24, 3), np.float32), resolution=RES, method="taped", seed=1,
                                  adjoint_seed=2),
     "method taped records one render and differentiates it: adjoint_seed must equal seed"),
    # Something else than a scene gave pybind11's TypeError of five lines ("incompatible function
    # arguments", the signature, the call).
    (lambda s: backlight.render(None, spp=1), "scene: expected a backlight.Scene (backlight.load), got NoneType"),
    (lambda s: backlight.backward("scene.json", np.ones((20, 24, 3), np.float32)),
     "scene: expected a backlight.Scene (backlight.load), got str"),
    (lambda s: backlight.grad(3, np.ones((20, 24, 3), np.float32)), "scene: expected a backlight.Scene"),
    (lambda s: backlight.check([s], "light.radiance", d_image=np.ones((20, 24, 3), np.float32)),
     "scene: expected a backlight.Scene"),
    # Worker threads: a positive integer (None: every core).
    (lambda s: backlight.set_threads(0), "threads: 0 is out of range (1..65536)"),
    (lambda s: backlight.set_threads(-1), "threads: -1 is out of range (1..65536)"),
    (lambda s: backlight.set_threads(10**9), "threads: 1000000000 is out of range (1..65536)"),
    (lambda s: backlight.set_threads(2.0), "threads: expected an integer, got float 2.0"),
    (lambda s: backlight.set_threads(True), "threads: expected an integer, got bool True"),
])
def test_bad_arguments_raise_one_line_errors(scene, call, message):
    with pytest.raises(backlight.Error) as info:
        call(scene)
    text = str(info.value)
    assert message in text and "\n" not in text
    assert "--" not in text  # Python's keyword names, not the CLI's flags
    assert isinstance(info.value, ValueError)


def test_check_compares_the_adjoint_with_finite_differences(scene, tmp_path):
    # backlight.check is the CLI's `check`: same rows, values restored afterwards.
    target = backlight.render(backlight.load(CORNELL, set={"light.radiance": [10, 10, 10]}), spp=4, seed=3,
                              resolution=RES)
    before = scene.params["light.radiance"].copy()
    rows = backlight.check(scene, "light.radiance", target=target, spp=2, seed=1, resolution=RES, directions=3)
    assert len(rows) == 3
    for r in rows:
        assert r["ok"] and r["relative_error"] < 1e-2, r
        assert abs(r["adjoint"]) > 0 and math.isnan(r["z"])
    np.testing.assert_array_equal(scene.params["light.radiance"], before)
    # The same numbers as the CLI prints for the same request.
    ones = write_pfm(str(tmp_path / "ones.pfm"), np.ones((20, 24, 3), np.float32))
    cli = subprocess.run([os.path.join(BIN, "backlight"), "check", CORNELL, "--param", "light.radiance",
                          "--adjoint-image", ones, "--spp", "2", "--seed", "1", "--resolution", "24x20",
                          "--directions", "2", "-q"], capture_output=True, text=True)
    assert cli.returncode == 0, cli.stderr
    printed = [line.split() for line in cli.stdout.splitlines() if line[:1].isdigit()]
    assert len(printed) == 2, cli.stdout
    rows = backlight.check(scene, "light.radiance", d_image=np.ones((20, 24, 3), np.float32), spp=2, seed=1,
                           resolution=RES, directions=2)
    for r, p in zip(rows, printed):
        assert float(p[1]) == pytest.approx(r["adjoint"], rel=1e-7)
        assert float(p[2]) == pytest.approx(r["finite_difference"], rel=1e-7)
    # Over several seeds (a plastic roughness, which sampling depends on): z scores and standard
    # errors.
    rows = backlight.check(scene, "plastic.roughness", target=target, spp=2, seed=1, resolution=RES, directions=1,
                           seeds=4, eps=0.02)
    assert not math.isnan(rows[0]["z"]) and rows[0]["fd_stderr"] > 0


def test_paths_may_be_path_objects():
    import pathlib
    scene = backlight.load(pathlib.Path(CORNELL))
    assert scene.path == CORNELL
    assert backlight.render(scene, spp=1, resolution=(4, 4), seed=2**64 - 1).shape == (4, 4, 3)


def test_bad_values_written_through_views_are_refused_by_name(scene):
    scene.params["wall.albedo"][3, 4, 1] = np.nan
    with pytest.raises(backlight.Error, match="wall.albedo"):
        backlight.render(scene, spp=1, resolution=RES)
    scene.params["wall.albedo"][3, 4, 1] = -1.0
    with pytest.raises(backlight.Error, match="outside its valid range"):
        backlight.render(scene, spp=1, resolution=RES)
    scene.params["wall.albedo"][3, 4, 1] = 0.5
    backlight.render(scene, spp=1, resolution=RES)


def test_passes_on_one_scene_from_two_threads_take_turns(scene):
    # A pass resizes the camera's film and rebuilds sampling data: two threads passing one scene
    # used to crash or return images of the other's size. They now wait for each other.
    expected = {res: backlight.render(scene, spp=1, seed=3, resolution=res) for res in [(8, 6), (12, 4)]}
    d_image = np.ones((6, 8, 3), np.float32)
    gradient = backlight.backward(scene, d_image, spp=1, seed=3, resolution=(8, 6), params=["light.radiance"])
    errors = []

    def work(res, rounds):
        try:
            for _ in range(rounds):
                image = backlight.render(scene, spp=1, seed=3, resolution=res)
                if not np.array_equal(image, expected[res]):
                    errors.append(f"render at {res} differs")
                if res == (8, 6):
                    g = backlight.backward(scene, d_image, spp=1, seed=3, resolution=res, params=["light.radiance"])
                    if not np.array_equal(g["light.radiance"], gradient["light.radiance"]):
                        errors.append("backward differs")
        except Exception as e:  # noqa: BLE001 (reported below)
            errors.append(repr(e))

    threads = [threading.Thread(target=work, args=(res, 60)) for res in [(8, 6), (12, 4)]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert scene.cameras[0] == tuple(int(v) for v in backlight.load(CORNELL).cameras[0])


def test_values_put_back_after_a_failed_geometry_step_render_as_before(scene):
    # The failed step left the light's vertices where it put them; the restored values matched the
    # recorded pose, so nothing re-posed and light samples came from the collapsed triangles.
    before = backlight.render(scene, spp=4, seed=1, resolution=RES)
    positions = scene.params["light.positions"]
    loaded = positions.copy()
    positions[:] = 0
    with pytest.raises(backlight.Error, match="degenerate"):
        backlight.render(scene, spp=4, seed=1, resolution=RES)
    positions[:] = loaded
    assert np.array_equal(backlight.render(scene, spp=4, seed=1, resolution=RES), before)


def test_set_takes_numbers_of_any_shape():
    # Lists longer than ~60 numbers were joined into one string and refused as a file name;
    # nested lists and 2-D arrays were refused.
    positions = backlight.load(CORNELL).params["plastic_box.positions"] * np.float32(1.01)
    s = backlight.load(CORNELL, set={"plastic_box.positions": positions.ravel().tolist(),
                                     "light.radiance": [[5.0, 6.0, 7.0]],
                                     "wall.albedo": np.full((1024, 1024, 3), 0.25),
                                     "plastic.albedo": np.float64(0.5)})
    np.testing.assert_array_equal(s.params["plastic_box.positions"], positions)
    np.testing.assert_array_equal(s.params["light.radiance"], [5, 6, 7])
    assert np.all(s.params["wall.albedo"] == 0.25)
    np.testing.assert_array_equal(s.params["plastic.albedo"], [0.5, 0.5, 0.5])


def test_assigning_to_params_raises_instead_of_doing_nothing(scene):
    # scene.params was a fresh dict each time: assigning to it changed nothing, silently.
    with pytest.raises(TypeError):
        scene.params["light.radiance"] = np.ones(3, np.float32)
    scene.params["light.radiance"][...] = 2.0  # the way: write into the view
    np.testing.assert_array_equal(scene.params["light.radiance"], [2, 2, 2])


@pytest.mark.parametrize("which", ["render", "backward"])
def test_ctrl_c_interrupts_a_pass(scene, which):
    # Python handles signals between bytecodes of its main thread: a pass used to keep Ctrl-C
    # waiting until it finished. It now stops after its current tiles with KeyboardInterrupt.
    # The pass asked for (2^20 spp at 256²) would take hours: without the interruption this test
    # does not finish within ctest's timeout (no wall-clock assertion of its own).
    import _thread
    res = (256, 256)
    spp = 1 << 20  # the limit of one pass
    d_image = np.ones((res[1], res[0], 3), np.float32)
    call = {
        "render": lambda: backlight.render(scene, spp=spp, seed=1, resolution=res),
        "backward": lambda: backlight.backward(scene, d_image, spp=spp, seed=1, resolution=res,
                                               params=["wall.albedo"]),
    }[which]
    timer = threading.Timer(0.3, _thread.interrupt_main)
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        call()
    timer.join()
    # The scene is usable and unchanged: the lock released, the film size restored.
    assert scene.cameras[0] == tuple(int(v) for v in backlight.load(CORNELL).cameras[0])
    image = backlight.render(scene, spp=1, seed=1, resolution=RES)
    np.testing.assert_array_equal(image, backlight.render(backlight.load(CORNELL), spp=1, seed=1, resolution=RES))


def test_check_over_seeds_uses_students_t_and_reports_resolution(scene):
    # Two seeds accept |z| up to Student's t quantile of the 4-sigma tail for one degree of freedom
    # (10050, a Cauchy quantile): each row says so and how coarse it is; one seed has neither.
    d_image = np.ones((RES[1], RES[0], 3), np.float32)
    rows = backlight.check(scene, "light.radiance", d_image=d_image, seeds=2, directions=1, spp=1, resolution=RES)
    expected = 1 / math.tan(math.pi * math.erfc(4 / math.sqrt(2)) / 2)
    assert abs(rows[0]["z_threshold"] - expected) < 1e-6 * expected, rows
    assert rows[0]["resolution"] >= 0
    single = backlight.check(scene, "light.radiance", d_image=d_image, directions=1, spp=1, resolution=RES)
    assert math.isnan(single[0]["z_threshold"]) and math.isnan(single[0]["resolution"])
    # Errors against the RMS of the finite differences over the directions: with one direction,
    # the relative error itself; with three, the rows' errors over that RMS.
    assert single[0]["rms_relative_error"] == single[0]["relative_error"], single
    three = backlight.check(scene, "light.radiance", d_image=d_image, directions=3, spp=1, resolution=RES)
    rms = math.sqrt(sum(r["finite_difference"] ** 2 for r in three) / 3)
    for r in three:
        assert math.isclose(r["rms_relative_error"], abs(r["adjoint"] - r["finite_difference"]) / rms), three


def test_check_that_compares_nothing_passes_nothing():
    # A parameter that does not reach the image (a camera that is not rendered): both sides are
    # exactly 0 in every direction. Rows said ok = True (0 against 0); the CLI says "nothing
    # compared" and exits 1.
    pose = backlight.load(os.path.join(ROOT, "scenes", "pose", "scene.json"))
    rows = backlight.check(pose, "left.origin", d_image=np.ones((16, 16, 3), np.float32), spp=1, resolution=(16, 16),
                           directions=2)
    assert all(r["nothing_compared"] and not r["ok"] for r in rows), rows
    assert all(r["adjoint"] == 0 and r["finite_difference"] == 0 for r in rows), rows
    rows = backlight.check(pose, "box.albedo", d_image=np.ones((16, 16, 3), np.float32), spp=1, resolution=(16, 16),
                           directions=2)
    assert all(not r["nothing_compared"] and r["ok"] for r in rows), rows


def test_a_scene_whose_path_is_not_utf8_has_a_repr_and_a_path(tmp_path):
    # A file name with the byte 0xff: repr(scene) and scene.path raised UnicodeDecodeError.
    folder = os.path.join(os.fsencode(tmp_path), b"\xff")
    os.symlink(os.path.dirname(os.path.abspath(CORNELL)), folder)
    scene = backlight.load(os.path.join(folder, b"scene.json"))
    text = repr(scene)
    assert text.startswith("<backlight.Scene '") and "/\\xff/scene.json'" in text, text
    # The path as os.fsdecode gives it: os.fsencode turns it back into the file system's bytes.
    assert os.fsencode(scene.path) == os.path.join(folder, b"scene.json")
    assert backlight.load(scene.path).path == scene.path


def test_set_threads_limits_the_worker_threads(scene):
    # Images are the same on any number of threads (tiles own their pixels and random numbers).
    default = backlight.render(scene, spp=4, seed=3, resolution=RES)
    d_image = weights(RES[1], RES[0])
    gradient = backlight.backward(scene, d_image, spp=4, seed=3, resolution=RES, params=["light.radiance"])
    every_core = backlight.get_threads()
    assert every_core >= 1
    backlight.set_threads(1)
    try:
        assert backlight.get_threads() == 1
        one = backlight.render(scene, spp=4, seed=3, resolution=RES)
        one_gradient = backlight.backward(scene, d_image, spp=4, seed=3, resolution=RES, params=["light.radiance"])
    finally:
        backlight.set_threads(None)
    assert backlight.get_threads() == every_core
    np.testing.assert_array_equal(one, default)
    np.testing.assert_allclose(one_gradient["light.radiance"], gradient["light.radiance"], rtol=1e-6)
    # The limit is the pool's: a process that set one thread starts no TBB worker.
    script = ("import os, sys, backlight\n"
              "if sys.argv[1] != '0': backlight.set_threads(int(sys.argv[1]))\n"
              f"s = backlight.load({CORNELL!r})\n"
              "backlight.render(s, spp=16, seed=1, resolution=(64, 64))\n"
              "print(len(os.listdir('/proc/self/task')))\n")
    counts = {n: int(subprocess.run([sys.executable, "-c", script, str(n)], capture_output=True, text=True,
                                    check=True).stdout) for n in (0, 1)}
    assert counts[1] == 1, counts
    if (os.cpu_count() or 1) > 1:
        assert counts[0] > 1, counts


def test_backward_docstring_says_exact_only_with_russian_roulette_off():
    # It called the same-seed gradient of albedos and textures exact; with Russian roulette on (rr_depth
    # 5 by default) the continuation probability depends on them (README, "Same seed, exact derivative").
    doc = " ".join(backlight.backward.__doc__.split())
    assert "rr_depth=0" in doc and "albedos and textures" in doc, doc
