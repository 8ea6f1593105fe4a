"""An optional CPU speed path: oneDNN matmuls with the activation fused in, where that is faster.

    --kernels auto     time both on the run's own networks and batch size at start-up (default)
    --kernels torch    plain PyTorch (F.linear: MKL's sgemm on x86 wheels)
    --kernels onednn   oneDNN for every nn.Linear, fused with the ReLU or Tanh after it

Why it exists: the same wheel of torch runs at very different speeds on the CPUs this project
meets. On some AMD EPYC CPUs MKL's sgemm reaches half of oneDNN's rate; on Intel Xeons it is
the other way round; and on some CPUs torch.tanh of a 256x256 batch costs half a matmul while
oneDNN applies it inside the matmul for free. No choice is right everywhere, so `auto` measures.

`use_onednn(net)` changes the class of every nn.Linear in `net` to OneDNNLinear (same
parameters, same state_dict keys) and, where an nn.ReLU or nn.Tanh follows it in an
nn.Sequential, fuses it into the layer and puts nn.Identity in its place. Networks stay
nn.Modules that are called normally; a layer a user inserts between a Linear and its
activation (LayerNorm, dropout) simply leaves that pair unfused.
"""

import copy
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

from plumbing import ConfigError

AVAILABLE = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")
ACTIVATIONS = {"relu": F.relu, "tanh": torch.tanh}
FUSABLE = {nn.ReLU: "relu", nn.Tanh: "tanh"}


def linear(x, weight, bias=None, activation=None):
    """activation(x weight^T + bias), activation "relu", "tanh" or None, through oneDNN.

    For matmuls with fewer than 16 rows, inputs or outputs (acting on one observation, a
    critic's last layer) oneDNN's fixed cost of about 15 us is more than F.linear takes.
    """
    if (AVAILABLE and x.dim() == 2 and x.dtype == torch.float32 and x.device.type == "cpu"
            and min(x.shape[0], *weight.shape) >= 16):
        if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, bias)):
            return OneDNNLinearFunction.apply(x, weight, bias, activation)
        # oneDNN's linear op: input, weight, bias, fused activation, its scalar arguments, algorithm
        return torch.ops.mkldnn._linear_pointwise(x, weight, bias, activation or "none", [], "")
    y = F.linear(x, weight, bias)
    return ACTIVATIONS[activation](y) if activation else y


class OneDNNLinearFunction(torch.autograd.Function):
    """activation(x weight^T + bias) with oneDNN's matmuls in the forward and backward pass.

    The activation's derivative is taken from the output y: relu' = (y > 0), tanh' = 1 - y^2.
    The backward is written with differentiable ops and `linear` itself, so it can be
    differentiated again (the discriminator's gradient penalty needs that).
    """

    @staticmethod
    def forward(ctx, x, weight, bias, activation):
        y = torch.ops.mkldnn._linear_pointwise(x, weight, bias, activation or "none", [], "")
        ctx.save_for_backward(x, weight, y)
        ctx.has_bias, ctx.activation = bias is not None, activation
        return y

    @staticmethod
    def backward(ctx, grad):
        x, weight, y = ctx.saved_tensors
        if ctx.activation == "relu":
            grad = torch.where(y > 0, grad, 0.0)
        elif ctx.activation == "tanh":
            grad = grad * (1 - y * y)
        grad_x = linear(grad, weight.t()) if ctx.needs_input_grad[0] else None  # grad W
        grad_weight = linear(grad.t(), x.t()) if ctx.needs_input_grad[1] else None  # grad^T x
        grad_bias = grad.sum(0) if ctx.has_bias and ctx.needs_input_grad[2] else None
        return grad_x, grad_weight, grad_bias, None


class OneDNNLinear(nn.Linear):
    """nn.Linear computed by `linear`, with an optional fused activation."""

    activation = None

    def forward(self, x):
        return linear(x, self.weight, self.bias, self.activation)

    def extra_repr(self):
        return super().extra_repr() + (f", fused {self.activation}" if self.activation else "")


def use_onednn(net):
    """Switches every nn.Linear of `net` to oneDNN, fusing the activation that follows it."""
    for module in list(net.modules()):
        if isinstance(module, nn.Sequential):
            layers = list(module)
            for i, layer in enumerate(layers[:-1]):
                if type(layer) is nn.Linear and type(layers[i + 1]) in FUSABLE:
                    layer.__class__, layer.activation = OneDNNLinear, FUSABLE[type(layers[i + 1])]
                    module[i + 1] = nn.Identity()
    for module in net.modules():
        if type(module) is nn.Linear:
            module.__class__ = OneDNNLinear
    return net


def _first_linear(net):
    return next(m for m in net.modules() if isinstance(m, nn.Linear))


def _seconds_per_pass(nets, batch_size, repeats=3, passes=10):
    """Best time of a forward and backward pass through each of `nets` on random inputs."""
    generator = torch.Generator().manual_seed(0)  # the run's own RNG stream stays untouched
    inputs = [torch.randn(batch_size, _first_linear(net).in_features, generator=generator) for net in nets]
    best = float("inf")
    for _ in range(repeats + 1):  # the first round warms up (allocations, oneDNN's primitives)
        start = time.perf_counter()
        for _ in range(passes):
            for net, x in zip(nets, inputs):
                net(x).sum().backward()
        best = min(best, (time.perf_counter() - start) / passes)
    return best


def choose(kernels, nets, batch_size, device):
    """The kernels to use, "torch" or "onednn": `kernels` itself unless it is "auto", which times
    both on copies of `nets` (nn.Sequential networks) with the run's batch size."""
    if kernels == "onednn" and not AVAILABLE:
        raise ConfigError("--kernels onednn: this build of torch has no oneDNN linear op; use --kernels torch")
    if kernels != "auto":
        return kernels
    if not AVAILABLE or torch.device(device).type != "cpu":
        return "torch"
    plain = [copy.deepcopy(net).requires_grad_(True) for net in nets]
    fused = [use_onednn(copy.deepcopy(net)) for net in plain]
    times = {"torch": _seconds_per_pass(plain, batch_size), "onednn": _seconds_per_pass(fused, batch_size)}
    return min(times, key=times.get)


def apply(kernels, modules):
    """Switches `modules` to oneDNN if kernels == "onednn" (else leaves them as they are)."""
    if kernels == "onednn":
        for module in modules:
            use_onednn(module)
