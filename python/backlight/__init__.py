"""backlight: a differentiable renderer with path replay backpropagation, from Python.

    import backlight
    scene = backlight.load("scenes/cornell/scene.json", set={"light.radiance": [17, 12, 4]})
    wall = scene.params["wall.albedo"]          # writable float32 view, no copy
    image = backlight.render(scene, spp=16)      # float32 (height, width, 3)
    grads = backlight.backward(scene, d_image)   # {name: gradient shaped like the parameter}
    loss, grads, image = backlight.grad(scene, target, loss="l2")
    rows = backlight.check(scene, "light.radiance", target=target)  # adjoint vs finite differences

backlight.torch wraps render and backward as a torch.autograd.Function. Errors a caller can
cause raise backlight.Error (a ValueError) with the one-line message the CLI prints. One pass
runs on a scene at a time; passes release the GIL and use every core (TBB), or as many as
backlight.set_threads(n) allows (the CLI's --threads).
"""
from ._backlight import Error, Scene, backward, check, get_threads, grad, load, render, set_threads

__all__ = ["Error", "Scene", "backward", "check", "get_threads", "grad", "load", "render", "set_threads"]
