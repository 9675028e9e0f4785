"""Pose models: global poses as corrections on the warm start, starting at the identity.

``T_i = A(xi_i) @ T0_i`` where ``T0_i`` is the warm start and ``A(xi)`` a correction (rotation about the frame's
warm-start position, then a translation). ``xi_i`` is the sum of a per-frame term, produced either directly from
per-frame parameters (``direct``) or by L-Net, a PointNet on the frame's points (``lnet``, the paper's design), and
an optional *drift* term: the accumulated corrections of all frames up to i, so one parameter can bend the rest of
the trajectory the way odometry drift does, which lets loop closures propagate in a few steps instead of
diffusing frame by frame.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from dm2_backend.kernel.geometry import se3_torch

PLANAR_MASK = (1.0, 1.0, 0.0, 0.0, 0.0, 1.0)


class LNet(nn.Module):
    """PointNet over a frame's points (normalised) plus its warm-start position -> 6-vector (zero at start)."""

    def __init__(self, points: torch.Tensor, centres: torch.Tensor, width: int = 64) -> None:
        super().__init__()
        self.register_buffer("points", points)  # (N, M, 3) normalised
        self.register_buffer("centres", centres)  # (N, 3) normalised
        self.point_mlp = nn.Sequential(
            nn.Linear(3, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 2 * width)
        )
        self.head = nn.Sequential(nn.Linear(2 * width + 3, width), nn.ReLU(), nn.Linear(width, 6))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        feat = self.point_mlp(self.points[idx]).max(dim=1).values
        return self.head(torch.cat([feat, self.centres[idx]], -1))


class PoseModel(nn.Module):
    """Global poses of all frames as differentiable functions of the parameters."""

    def __init__(
        self,
        warm_start: np.ndarray,
        planar: bool,
        step_translation: float,
        step_rotation: float,
        kind: str = "direct",
        drift: bool = True,
        points: torch.Tensor | None = None,
        length_scale: float = 1.0,
        drift_factor: float | None = None,
    ) -> None:
        super().__init__()
        T0 = torch.tensor(warm_start, dtype=torch.float64)
        self.register_buffer("T0", T0)
        self.register_buffer("centres", T0[:, :3, 3].clone())
        scale = torch.tensor([step_translation] * 3 + [step_rotation] * 3, dtype=torch.float64)
        if planar:
            scale = scale * torch.tensor(PLANAR_MASK, dtype=torch.float64)
        self.register_buffer("scale", scale)
        n = len(warm_start)
        self.kind = kind
        if kind == "direct":
            self.local = nn.Parameter(torch.zeros(n, 6, dtype=torch.float64))
        elif kind == "lnet":
            if points is None:
                raise ValueError("L-Net needs the frames' points")
            lo = self.centres.min(0).values
            span = (self.centres.max(0).values - lo).max().clamp_min(1e-6)
            centres = ((self.centres - lo) / span * 2 - 1).float()
            self.lnet = LNet(points / float(length_scale), centres)
        else:
            raise ValueError(f"unknown pose model {kind!r} (direct or lnet)")
        self.drift = nn.Parameter(torch.zeros(n, 6, dtype=torch.float64)) if drift else None
        # Adam moves every drift parameter by about one step; N of them add up along the trajectory, so
        # each gets 1/sqrt(N) of the step to keep the accumulated noise at about one step.
        self.drift_factor = drift_factor if drift_factor is not None else 1.0 / np.sqrt(max(n, 1))

    def network_parameters(self) -> list[nn.Parameter]:
        return list(self.lnet.parameters()) if self.kind == "lnet" else []

    def pose_parameters(self) -> list[nn.Parameter]:
        params = [self.local] if self.kind == "direct" else []
        return params + ([self.drift] if self.drift is not None else [])

    def _local(self, idx: torch.Tensor) -> torch.Tensor:
        if self.kind == "direct":
            return self.local[idx]
        return self.lnet(idx).double()

    def drift_xi(self) -> torch.Tensor:
        """Accumulated drift corrections (N,6) as (v, w) about each frame's warm-start position.

        Frame m's drift parameter rotates every later frame i about c_m and shifts it; to first order in the
        rotation that is a rotation by ``W_i = sum_{m<=i} w_m`` about c_i plus the translation
        ``sum_{m<=i} v_m + w_m x (c_i - c_m)``: cumulative sums, O(N), instead of a chain of N products.
        """
        d = self.drift * (self.scale * self.drift_factor)
        v, w = d[:, :3], d[:, 3:]
        W = torch.cumsum(w, 0)
        swept = W.cross(self.centres, dim=-1) - torch.cumsum(w.cross(self.centres, dim=-1), 0)
        return torch.cat([torch.cumsum(v, 0) + swept, W], -1)

    def forward(self, idx: torch.Tensor | None = None) -> torch.Tensor:
        """Poses (len(idx),4,4) float64 of the frames ``idx`` (all frames when None)."""
        if idx is None:
            idx = torch.arange(len(self.T0), device=self.T0.device)
        xi = self._local(idx) * self.scale
        if self.drift is not None:
            xi = xi + self.drift_xi()[idx]
        return se3_torch.correction(xi, self.centres[idx]) @ self.T0[idx]
