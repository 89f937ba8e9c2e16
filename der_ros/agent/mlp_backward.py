"""Forward and backward pass of the MLP Q-network written out, without autograd.

Why: a DQN gradient step on the 23-256-3 ring network (batch 128) does a few tens of
microseconds of arithmetic, but through autograd it also records a graph of ~20 nodes in the
forward pass and walks it in the backward pass (node objects, hooks, four gradient
accumulations into ``.grad``). With this module, clipping and Adam without temporaries
(``DQNAgent._gradient_step``, ``FlatAdam``), a whole update (sample, step, priorities) of the ring
learner went from 1,019 to 713 us of CPU (DER lambda 0.9; uniform 891 -> 569, PER 879 -> 591),
both measured in one process on the shared 2-core machine under load (bench/README.md).

How it stays exact: every gradient is computed with the kernel autograd itself calls, on
operands of the same memory layout, in the same order, so the results are bit-identical (checked
against a plain autograd step by ``test/agent/test_agent.py``). The parameters are used as detached
views, so none of this records an autograd graph and no ``no_grad`` context is needed. For
``out = F.linear(x, W, b)``, which is ``addmm(b, x, W.t())`` for 2-D inputs, autograd's addmm
backward computes

* ``dW = dout.t().mm(x)`` (``W.t()`` is column-major, so the weight gradient comes out as
  ``W``'s own layout),
* ``db = dout.sum(0)`` (the broadcast bias reduced back),
* ``dx = dout.mm(W)``,

and ReLU's backward is ``threshold_backward(dy, y, 0)`` on the ReLU output ``y``. The gradients
are written straight into the flat gradient buffer (the ``.grad`` views made by
:func:`~der_ros.agent.networks.flatten_parameters`) with ``out=``, where autograd would add them
to the zeroed buffer: the values are the same, only a ``-0.0`` may stay ``-0.0`` where ``0 + (-0)``
gives ``+0.0``; no later operation (norm, clipping, Adam) tells the two zeros apart.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from der_ros.agent.networks import MLPQNetwork

__all__ = ["MLPBackward", "detached_layers", "mlp_forward"]

_threshold_backward = torch.ops.aten.threshold_backward


def detached_layers(net: MLPQNetwork) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(weight, bias) of each layer as detached views: the same memory as the parameters (so they
    follow every in-place update of the flat buffer), but no autograd recording when used, which
    spares the ``no_grad`` context on every call of the hot path."""
    return [(layer.weight.detach(), layer.bias.detach()) for layer in net._linears]


def mlp_forward(x: torch.Tensor, layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """``MLPQNetwork.forward`` on :func:`detached_layers` (same kernels, same results), for float32
    inputs of shape (B, obs_dim)."""
    last = len(layers) - 1
    for i, (weight, bias) in enumerate(layers):
        x = F.linear(x, weight, bias)
        if i < last:
            x = torch.relu(x)
    return x


class MLPBackward:
    """Forward pass of an :class:`MLPQNetwork` that keeps the activations, and its backward pass.

    The network's parameters must be views of one flat buffer whose gradient views are set
    (:func:`~der_ros.agent.networks.flatten_parameters`); :meth:`backward` overwrites them.
    """

    def __init__(self, net: MLPQNetwork) -> None:
        self.layers = detached_layers(net)
        self.grads: list[tuple[torch.Tensor, torch.Tensor]] = []
        for layer in net._linears:
            if layer.weight.grad is None or layer.bias.grad is None:
                raise ValueError("MLPBackward needs gradient views on every parameter (flatten_parameters)")
            self.grads.append((layer.weight.grad, layer.bias.grad))
        self._inputs: list[torch.Tensor] = []

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Q-values of a batch (the same operations as ``MLPQNetwork.forward``), keeping each
        layer's input for :meth:`backward`."""
        x = obs if obs.dtype == torch.float32 else obs.float()
        x = x.flatten(1)
        inputs = []
        last = len(self.layers) - 1
        for i, (weight, bias) in enumerate(self.layers):
            inputs.append(x)
            x = F.linear(x, weight, bias)
            if i < last:
                x = torch.relu(x)
        self._inputs = inputs
        return x

    def backward(self, grad_out: torch.Tensor) -> None:
        """Write d(loss)/d(parameters) into the gradient views, given d(loss)/d(output of :meth:`forward`)."""
        g = grad_out
        for i in range(len(self.layers) - 1, -1, -1):
            x = self._inputs[i]
            g_weight, g_bias = self.grads[i]
            torch.mm(g.t(), x, out=g_weight)
            torch.sum(g, 0, out=g_bias)
            if i > 0:
                g = _threshold_backward(g.mm(self.layers[i][0]), x, 0)  # x = relu output of layer i - 1
        self._inputs = []
