"""Adam on one flat parameter buffer (the optimiser of paper sections 4.1 and 5).

Same update as ``torch.optim.Adam`` with default options (Kingma & Ba 2015, bias-corrected
moments, no weight decay, no AMSGrad)::

    m <- b1 m + (1 - b1) g          v <- b2 v + (1 - b2) g^2
    p <- p - lr * (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)

Why not ``torch.optim.Adam``: for CartPole's 4-256-2 network a gradient step takes a few hundred
microseconds, and the generic optimiser's per-call machinery (hooks, profiler records, per-group
bookkeeping) was a quarter of it. All parameters live in one tensor
(:func:`der_ros.agent.networks.flatten_parameters`), so the update is five tensor operations.
"""

from __future__ import annotations

import math
from typing import Any

import torch

__all__ = ["FlatAdam"]


class FlatAdam:
    """Adam over a single flat parameter tensor and its gradient buffer."""

    def __init__(
        self,
        params: torch.Tensor,
        grads: torch.Tensor,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        if params.shape != grads.shape:
            raise ValueError(f"params {tuple(params.shape)} and grads {tuple(grads.shape)} differ in shape")
        self.params = params
        self.grads = grads
        #: torch.optim-style groups, so callers can change the rate with ``group["lr"] = x``
        self.param_groups: list[dict[str, Any]] = [{"params": [params], "lr": float(lr)}]
        self.beta1, self.beta2 = float(betas[0]), float(betas[1])
        self.eps = float(eps)
        self.exp_avg = torch.zeros_like(params)
        self.exp_avg_sq = torch.zeros_like(params)
        self._denom = torch.empty_like(params)  # reused every step (same kernels as a fresh tensor)
        self.step_count = 0

    @property
    def lr(self) -> float:
        return float(self.param_groups[0]["lr"])

    @lr.setter
    def lr(self, value: float) -> None:
        self.param_groups[0]["lr"] = float(value)

    def step(self) -> None:
        # no no_grad context needed: the flat buffer is a plain tensor (the parameters are views of it)
        self.step_count += 1
        t = self.step_count
        g = self.grads
        self.exp_avg.lerp_(g, 1.0 - self.beta1)
        self.exp_avg_sq.mul_(self.beta2).addcmul_(g, g, value=1.0 - self.beta2)
        bias1 = 1.0 - self.beta1**t
        bias2_sqrt = math.sqrt(1.0 - self.beta2**t)
        denom = torch.sqrt(self.exp_avg_sq, out=self._denom).div_(bias2_sqrt).add_(self.eps)
        self.params.addcdiv_(self.exp_avg, denom, value=-self.lr / bias1)

    def state_dict(self) -> dict[str, Any]:
        return {
            "lr": self.lr,
            "betas": (self.beta1, self.beta2),
            "eps": self.eps,
            "step": self.step_count,
            "exp_avg": self.exp_avg,
            "exp_avg_sq": self.exp_avg_sq,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if tuple(state["exp_avg"].shape) != tuple(self.params.shape):
            raise ValueError(
                f"optimizer state has {tuple(state['exp_avg'].shape)} moments, expected {tuple(self.params.shape)}"
            )
        self.lr = float(state["lr"])
        self.beta1, self.beta2 = (float(b) for b in state["betas"])
        self.eps = float(state["eps"])
        self.step_count = int(state["step"])
        self.exp_avg.copy_(state["exp_avg"])
        self.exp_avg_sq.copy_(state["exp_avg_sq"])
