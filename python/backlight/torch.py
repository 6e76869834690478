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
forward returned for emission, and for albedos and textures with Russian roulette off
(backlight.load(..., rr_depth=0): its continuation probability depends on them through the
throughput); for albedos while roulette is on and for roughness-like parameters it is exact in
expectation. Pass adjoint_seed to decorrelate the passes (unbiased for losses that are not linear
in the image, as Mitsuba 3 recommends for optimization). The scene's other parameters must keep
their values from forward to backward (backward checks their checksums and raises if one
changed). There are no second derivatives: a gradient taken with create_graph=True holds the
first derivatives, and differentiating it raises RuntimeError.
"""
import collections.abc
import numbers
import operator
import threading
import weakref
import zlib

import numpy as np
import torch

from . import _backlight

_METHODS = ("prb", "rb", "taped")

# One lock per scene, held from writing a call's tensors into the scene to the end of its pass:
# the module takes turns per pass, but two threads' writes could otherwise land between the other's
# write and render (an image rendered with the other thread's values).
_locks = weakref.WeakKeyDictionary()
_locks_guard = threading.Lock()


# scene.param_info per scene: shapes and valid ranges are fixed once a scene is loaded, and
# building the dict over every parameter cost 26 ms a call on a 12,000-parameter scene.
_infos = weakref.WeakKeyDictionary()


def _info(scene):
    with _locks_guard:
        info = _infos.get(scene)
        if info is None:
            info = _infos[scene] = scene.param_info
        return info


def _lock(scene):
    with _locks_guard:
        lock = _locks.get(scene)
        if lock is None:
            lock = _locks[scene] = threading.RLock()
        return lock


def _check(views, info, names, tensors):
    """Checks every tensor (a floating-point torch tensor of its parameter's shape, or 0-d for a
    one-element parameter, finite, in the parameter's valid range) before any is written: a failed
    call leaves the scene as it was. Returns the values as float32 arrays of the parameters'
    shapes. views is scene.params, fetched once per call (it builds a dict over every parameter of
    the scene: 12,000 of them cost ~6 ms a fetch), info the scene's param_info (_info)."""
    values = []
    for name, tensor in zip(names, tensors):
        if name not in views:
            raise _backlight.Error(f"unknown parameter '{name}' (see scene.params)")
        if not isinstance(tensor, torch.Tensor):
            raise _backlight.Error(f"{name}: expected a torch.Tensor, got {type(tensor).__name__}")
        if not tensor.is_floating_point():
            raise _backlight.Error(f"{name}: expected a floating-point tensor, got {tensor.dtype}")
        # A meta tensor has a shape and no values: copying it out raised NotImplementedError ("Cannot
        # copy out of meta tensor; no data!"), naming no parameter.
        if tensor.is_meta:
            raise _backlight.Error(f"{name}: a tensor on the 'meta' device has no values")
        detached = tensor.detach()
        try:
            value = detached.to("cpu", torch.float32).contiguous().numpy()
        except (RuntimeError, TypeError, NotImplementedError) as e:  # a sparse layout, a device torch cannot read
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise _backlight.Error(f"{name}: cannot read the tensor's values ({tensor.layout}, on {tensor.device}: "
                                   f"{reason})") from None
        if value.ndim == 0 and views[name].size == 1:  # a 0-d value for a one-element parameter
            value = value.reshape(views[name].shape)
        if value.shape != views[name].shape:
            raise _backlight.Error(f"{name}: expected shape {tuple(views[name].shape)}, got {tuple(value.shape)}")
        if not np.all(np.isfinite(value)):
            if bool(torch.isfinite(detached).all()):
                raise _backlight.Error(f"{name}: values beyond the float32 range (largest magnitude "
                                       f"{float(detached.abs().max()):g})")
            raise _backlight.Error(f"{name}: the tensor holds NaN or infinite values")
        lower, upper = info[name]["lower"], info[name]["upper"]
        if value.size and (value.min() < lower or value.max() > upper):
            raise _backlight.Error(f"{name}: values outside its valid range [{lower:g}, {upper:g}] "
                                   f"(min {value.min():g}, max {value.max():g})")
        values.append(value)
    return values


def _write(views, names, values):
    for name, value in zip(names, values):
        views[name][...] = value


def _run(views, names, values, run):
    """Writes values into the scene (through its views) and calls run(); if run raises, the written
    parameters get their old values back (a render refused for its camera left the scene changed,
    and a refused geometry broke every later render)."""
    old = [views[name].copy() for name in names]
    _write(views, names, values)
    try:
        return run()
    except BaseException:
        _write(views, names, old)
        raise


def _fingerprints(views, skip):
    """Checksums of every parameter not in `skip`: what backward compares with its forward's."""
    return {name: zlib.adler32(view) for name, view in views.items() if name not in skip}


_NO_SECOND = ("trying to differentiate twice: backlight.torch.render has no second derivatives (a gradient "
              "taken with create_graph=True holds first derivatives only)")


class _FirstOrderOnly(torch.autograd.Function):
    """The gradients of _Render.backward under create_graph=True, attached to the tensors they are
    the gradients of so that differentiating them raises. torch's once_differentiable attaches them
    to grad_output only: when that had no graph (a loss linear in the image), the gradient came back
    constant and a gradient penalty's second-order terms were dropped without a word."""

    @staticmethod
    def forward(ctx, count, *args):
        return tuple(a.clone() for a in args[:count])

    @staticmethod
    def backward(ctx, *grads):
        raise RuntimeError(_NO_SECOND)


class _Render(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scene, names, options, *tensors):
        views = scene.params
        values = _check(views, _info(scene), names, tensors)
        with _lock(scene):
            image = _run(views, names, values,
                         lambda: _backlight.render(scene, spp=options["spp"], seed=options["seed"],
                                                   camera=options["camera"], resolution=options["resolution"]))
            ctx.others = _fingerprints(views, set(names))
            # A tensor sharing memory with the scene's parameter (torch.from_numpy(scene.params[n]))
            # changes with every later write into the scene, which torch's in-place check does not
            # see: backward uses a copy of the values this render used.
            ctx.copies = {i: v.copy() for i, (n, v) in enumerate(zip(names, values))
                          if np.may_share_memory(v, views[n])}
        ctx.scene, ctx.names, ctx.options = scene, names, options
        ctx.save_for_backward(*tensors)
        reference = tensors[0] if tensors else None
        out = torch.from_numpy(image)
        return out.to(reference.device) if reference is not None else out

    @staticmethod
    def backward(ctx, grad_output):
        tensors = ctx.saved_tensors
        with torch.no_grad():
            grads = _Render._gradients(ctx, tensors, grad_output)
        if not torch.is_grad_enabled():  # no create_graph
            return grads
        # create_graph=True: the gradients are first derivatives; differentiating them raises.
        anchors = [t for i, t in enumerate(tensors) if ctx.needs_input_grad[3 + i]]
        anchors += [grad_output] if grad_output.requires_grad else []
        given = [i for i, g in enumerate(grads) if g is not None]
        if not given or not anchors:
            return grads
        attached = _FirstOrderOnly.apply(len(given), *[grads[i] for i in given], *anchors)
        out = list(grads)
        for i, g in zip(given, attached):
            out[i] = g
        return tuple(out)

    @staticmethod
    def _gradients(ctx, tensors, grad_output):
        views = ctx.scene.params
        values = _check(views, _info(ctx.scene), ctx.names, tensors)
        values = [ctx.copies.get(i, v) for i, v in enumerate(values)]
        wanted = [n for i, n in enumerate(ctx.names) if ctx.needs_input_grad[3 + i]]
        if not wanted:
            return (None, None, None, *[None] * len(tensors))
        d_image = grad_output.detach().to("cpu", torch.float32).contiguous().numpy()
        if not np.all(np.isfinite(d_image)):
            row, column, channel = np.argwhere(~np.isfinite(d_image))[0]
            raise _backlight.Error(
                f"the loss's gradient with respect to the image is NaN or infinite at pixel (row {row}, column "
                f"{column}, channel {channel}): check the loss there (e.g. sqrt or log of a black pixel)")
        o = ctx.options

        def backward_pass():
            # Parameters this render did not take as tensors are read from the scene as they are
            # now: if one changed since forward (another render's tensors, a write through a view),
            # the gradient would be taken at values the image was not rendered with.
            now = _fingerprints(views, set(ctx.names))
            changed = [name for name, value in ctx.others.items() if now.get(name) != value]
            if changed:
                raise _backlight.Error(
                    f"parameter '{changed[0]}' changed between this render's forward and backward (it is not one of "
                    f"its tensors {list(ctx.names)}): pass it as a tensor to every render, or render again after "
                    f"changing it")
            # Only the tensors that want a gradient are differentiated: a fixed camera pose passed
            # as a tensor would otherwise ask for geometry gradients.
            return _backlight.backward(ctx.scene, d_image, method=o["method"], spp=o["spp"], seed=o["seed"],
                                       adjoint_seed=o["adjoint_seed"], camera=o["camera"],
                                       resolution=o["resolution"], params=wanted)

        with _lock(ctx.scene):
            grads = _run(views, ctx.names, values, backward_pass)
        # In the shape given: a 0-d tensor for a one-element parameter gets a 0-d gradient.
        out = [torch.from_numpy(grads[n]).reshape(t.shape).to(t.device, t.dtype) if ctx.needs_input_grad[3 + i]
               else None for i, (n, t) in enumerate(zip(ctx.names, tensors))]
        return (None, None, None, *out)


def render(scene, params, *, spp=None, seed=None, camera=0, resolution=None, method="prb", adjoint_seed=None):
    """Renders scene with the given parameter tensors ({name: tensor shaped like scene.params[name]};
    for a one-element parameter also a 0-d tensor or a number) and returns a float32 tensor (height,
    width, 3) that gradients flow through back to those tensors, each gradient in its tensor's
    shape. With the same seed for both passes (adjoint_seed=None) the gradient is the exact
    derivative of this image for emission, and for albedos and textures with Russian roulette off
    (rr_depth=0); else exact in expectation. Parameters not given here must keep their values until
    backward (it raises otherwise). No second derivatives: differentiating a gradient taken with
    create_graph=True raises RuntimeError."""
    if not isinstance(scene, _backlight.Scene):
        raise _backlight.Error(f"scene: expected a backlight.Scene (backlight.load), got {type(scene).__name__}")
    if not isinstance(params, collections.abc.Mapping):
        raise _backlight.Error(f"params: expected a dict {{name: tensor}}, got {type(params).__name__}")
    if not params:
        raise _backlight.Error("params: give at least one {name: tensor} to differentiate")
    if not isinstance(method, str) or method not in _METHODS:
        raise _backlight.Error(f"unknown method {method!r} (prb, rb or taped)")
    names = list(params)
    tensors = [params[n] for n in names]
    # A number for a one-element parameter, as a 0-d tensor (it takes no gradient); bool is refused.
    tensors = [torch.tensor(float(t)) if isinstance(t, numbers.Real) and not isinstance(t, (bool, np.bool_)) else t
               for t in tensors]
    if adjoint_seed is not None:
        # NumPy and torch integers too, as the module's own seed arguments take them.
        try:
            index = None if isinstance(adjoint_seed, bool) else operator.index(adjoint_seed)
        except TypeError:
            index = None
        if index is None or not 0 <= index < 2**64:
            raise _backlight.Error(f"adjoint_seed: expected an integer in 0..2^64 - 1, got {adjoint_seed!r}")
        adjoint_seed = index
    options = {"spp": spp, "seed": seed, "camera": camera, "resolution": resolution, "method": method,
               "adjoint_seed": adjoint_seed}
    return _Render.apply(scene, names, options, *tensors)
