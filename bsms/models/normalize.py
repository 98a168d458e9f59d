"""Online feature normaliser whose statistics live in module buffers (saved with the weights)."""

from __future__ import annotations

import torch
import torch.distributed
from torch import Tensor, nn


def distributed() -> bool:
    """Whether this process is one of several in an initialised process group."""
    return torch.distributed.is_available() and torch.distributed.is_initialized() \
        and torch.distributed.get_world_size() > 1


class Normalizer(nn.Module):
    """Zero-mean, unit-variance scaling per feature, from running sums over what it has seen.

    Statistics accumulate in float64 while ``accumulate`` is called during training, for at
    most ``max_accumulations`` batches; after that they are frozen. They are buffers, so they
    go into every ``state_dict`` and follow ``.to(device)``.

    Args:
        size: number of features (the last dimension of the inputs).
        max_accumulations: batches after which the statistics freeze.
        std_epsilon: floor on the standard deviation (constant features are not blown up).
    """

    def __init__(self, size: int, max_accumulations: int = 1_000_000, std_epsilon: float = 1e-8):
        super().__init__()
        self.max_accumulations = max_accumulations
        self.std_epsilon = std_epsilon
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("accumulations", torch.zeros((), dtype=torch.int64))
        self.register_buffer("total", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("total_squares", torch.zeros(size, dtype=torch.float64))

    @property
    def frozen(self) -> bool:
        return int(self.accumulations) >= self.max_accumulations

    @torch.no_grad()
    def accumulate(self, x: Tensor) -> None:
        """Add the rows of ``x (..., size)`` to the statistics, unless frozen."""
        if self.frozen:
            return
        flat = x.detach().reshape(-1, x.shape[-1]).to(torch.float64)
        increments = torch.cat([flat.new_tensor([flat.shape[0]]), flat.sum(dim=0), (flat * flat).sum(dim=0)])
        if distributed():
            # every process adds what all processes saw, so the statistics stay identical
            torch.distributed.all_reduce(increments)
        if increments[0] == 0:
            return
        size = self.total.shape[0]
        self.count += increments[0]
        self.total += increments[1 : 1 + size]
        self.total_squares += increments[1 + size :]
        self.accumulations += 1

    @property
    def mean(self) -> Tensor:
        return self.total / self.count.clamp(min=1.0)

    @property
    def std(self) -> Tensor:
        variance = self.total_squares / self.count.clamp(min=1.0) - self.mean**2
        return variance.clamp(min=0.0).sqrt().clamp(min=self.std_epsilon)

    def forward(self, x: Tensor) -> Tensor:
        """(..., size) -> normalised, in the dtype of ``x``."""
        return ((x - self.mean.to(x.dtype)) / self.std.to(x.dtype))

    def inverse(self, x: Tensor) -> Tensor:
        """Undo :meth:`forward`."""
        return x * self.std.to(x.dtype) + self.mean.to(x.dtype)
