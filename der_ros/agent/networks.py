"""Q-networks of the paper: an MLP for vector observations and the Atari CNN.

* Section 4.1 (CartPole): "the multilinear perceptron model of 256 cells" -> :class:`MLPQNetwork`
  with one hidden layer of 256 ReLU units by default (``hidden_sizes``).
* Section 5 (Atari) and Fig. S1: input 84x84x4 stacked grey frames; conv 32 filters 8x8 stride 4,
  conv 64 4x4 stride 2, conv 64 3x3 stride 1 (ReLU after each), a 512-unit ReLU layer, then one
  output per action -> :class:`AtariCNN`. Frames are stored as uint8 (4x less memory in replay)
  and scaled by 1/255 inside the network ("normalize input data").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["MLPQNetwork", "AtariCNN", "make_q_network", "flatten_parameters"]


class MLPQNetwork(nn.Module):
    """Fully connected Q-network: obs (flattened) -> hidden ReLU layers -> one Q-value per action."""

    def __init__(self, obs_dim: int, n_actions: int, hidden_sizes: Sequence[int] = (256,)) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim
        for h in hidden_sizes:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        layers.append(nn.Linear(width, n_actions))
        self.net = nn.Sequential(*layers)
        self._linears = [m for m in layers if isinstance(m, nn.Linear)]

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        # Same maths as self.net(x), without nn.Module call overhead per layer: with a 4-256-2 net
        # on CPU the per-call Python overhead is a large share of a DQN gradient step.
        x = obs if obs.dtype == torch.float32 else obs.float()
        x = x.flatten(1)
        last = len(self._linears) - 1
        for i, layer in enumerate(self._linears):
            x = F.linear(x, layer.weight, layer.bias)
            if i < last:
                x = torch.relu(x)
        return x


class AtariCNN(nn.Module):
    """The paper's Atari Q-network (section 5, Fig. S1); input (B, 4, 84, 84), uint8 or float in [0, 255]."""

    def __init__(self, in_channels: int, n_actions: int, frame_size: int = 84) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(in_channels, 32, kernel_size=8, stride=4),
            nn.ReLU(),
            nn.Conv2d(32, 64, kernel_size=4, stride=2),
            nn.ReLU(),
            nn.Conv2d(64, 64, kernel_size=3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n_flat = self.features(torch.zeros(1, in_channels, frame_size, frame_size)).shape[1]
        self.head = nn.Sequential(nn.Linear(n_flat, 512), nn.ReLU(), nn.Linear(512, n_actions))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        # Scaling here (not in the replay) keeps stored frames uint8: 84*84*4 bytes per observation.
        x = obs.float() * (1.0 / 255.0)
        return self.head(self.features(x))


def make_q_network(
    obs_shape: tuple[int, ...], obs_dtype: np.dtype | type, n_actions: int, kind: str, hidden_sizes: Sequence[int]
) -> nn.Module:
    """Build the Q-network for ``kind`` ('mlp', 'cnn' or 'auto': cnn for 3-D uint8 observations)."""
    dtype = np.dtype(obs_dtype)
    if kind == "auto":
        kind = "cnn" if (len(obs_shape) == 3 and dtype == np.uint8) else "mlp"
    if kind == "cnn":
        if len(obs_shape) != 3 or obs_shape[1] != obs_shape[2]:
            raise ValueError(f"network = 'cnn' needs (C, H, H) observations, got obs_shape = {obs_shape}")
        return AtariCNN(obs_shape[0], n_actions, frame_size=obs_shape[1])
    if kind == "mlp":
        return MLPQNetwork(int(np.prod(obs_shape)), n_actions, hidden_sizes)
    raise ValueError(f"network = {kind!r}, expected 'auto', 'mlp' or 'cnn'")


def flatten_parameters(module: nn.Module, with_grad: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Move all parameters of ``module`` into one contiguous buffer (parameters become views of it).

    Returns ``(flat, flat_grad)``: ``flat`` is a plain leaf tensor that aliases every parameter, so
    Adam, gradient clipping, the hard target copy and Polyak averaging each become one operation on
    one tensor instead of one per layer. With ``with_grad``, every ``param.grad`` is set to a view of
    ``flat_grad`` and autograd accumulates into it in place; zero it with ``flat_grad.zero_()``
    (never ``zero_grad(set_to_none=True)``, which would detach the views), and set ``flat.grad =
    flat_grad`` for the optimizer. Call after moving the module to its device.
    """
    params = list(module.parameters())
    if not params:
        raise ValueError("module has no parameters")
    device, dtype = params[0].device, params[0].dtype
    total = sum(p.numel() for p in params)
    flat = torch.empty(total, device=device, dtype=dtype)
    flat_grad = torch.zeros(total, device=device, dtype=dtype) if with_grad else None
    offset = 0
    with torch.no_grad():
        for p in params:
            n = p.numel()
            flat[offset : offset + n].copy_(p.reshape(-1))
            p.data = flat[offset : offset + n].view_as(p)
            if flat_grad is not None:
                p.grad = flat_grad[offset : offset + n].view_as(p)
            offset += n
    if flat_grad is not None:
        flat.grad = flat_grad
    return flat, flat_grad
