"""PyTorch bridge: backlight's render as a differentiable torch operation.

    import torch, backlight, backlight.torch
    scene = backlight.load("scenes/cornell/scene.json")
    texture = torch.tensor(scene.params["wall.albedo"], requires_grad=True)
    image = backlight.torch.render(scene, {"wall.albedo": texture}, spp=8)
    loss = my_torch_loss(image)
    loss.backward()                     # texture.grad: backlight's adjoint pass (prb)

forward writes the tensors into the scene's parameters and renders; backward writes the same
values again (the scene may have been rendered with others in between), transports grad_output
back through the scene (path replay by default) and returns one gradient per tensor. By default
the adjoint pass uses the forward's seed, so the gradient is the exact derivative of the image
forward returned; pass adjoint_seed to decorrelate them (unbiased for losses that are not linear
in the image, as Mitsuba 3 recommends for optimization).
"""
import numpy as np
import torch

from . import _backlight


def _write(scene, names, tensors):
    views = scene.params
    for name, tensor in zip(names, tensors):
        if name not in views:
            raise _backlight.Error(f"unknown parameter '{name}' (see scene.params)")
        value = tensor.detach().to("cpu", torch.float32).contiguous().numpy()
        view = views[name]
        if value.shape != view.shape:
            raise _backlight.Error(f"{name}: expected shape {tuple(view.shape)}, got {tuple(value.shape)}")
        if not np.all(np.isfinite(value)):
            raise _backlight.Error(f"{name}: the tensor holds NaN or infinite values")
        view[...] = value


class _Render(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scene, names, options, *tensors):
        _write(scene, names, tensors)
        image = _backlight.render(scene, spp=options["spp"], seed=options["seed"], camera=options["camera"],
                                  resolution=options["resolution"])
        ctx.scene, ctx.names, ctx.options = scene, names, options
        ctx.save_for_backward(*tensors)
        reference = tensors[0] if tensors else None
        out = torch.from_numpy(image)
        return out.to(reference.device) if reference is not None else out

    @staticmethod
    def backward(ctx, grad_output):
        tensors = ctx.saved_tensors
        _write(ctx.scene, ctx.names, tensors)
        o = ctx.options
        d_image = grad_output.detach().to("cpu", torch.float32).contiguous().numpy()
        grads = _backlight.backward(ctx.scene, d_image, method=o["method"], spp=o["spp"], seed=o["seed"],
                                    adjoint_seed=o["adjoint_seed"], camera=o["camera"],
                                    resolution=o["resolution"], params=list(ctx.names))
        out = [torch.from_numpy(grads[n]).to(t.device, t.dtype) if ctx.needs_input_grad[3 + i] else None
               for i, (n, t) in enumerate(zip(ctx.names, tensors))]
        return (None, None, None, *out)


def render(scene, params, *, spp=None, seed=None, camera=0, resolution=None, method="prb", adjoint_seed=None):
    """Renders scene with the given parameter tensors ({name: tensor shaped like scene.params[name]}) and
    returns a float32 tensor (height, width, 3) that gradients flow through back to those tensors."""
    if not params:
        raise _backlight.Error("params: give at least one {name: tensor} to differentiate")
    names = list(params)
    options = {"spp": spp, "seed": seed, "camera": camera, "resolution": resolution, "method": method,
               "adjoint_seed": adjoint_seed}
    return _Render.apply(scene, names, options, *[params[n] for n in names])
