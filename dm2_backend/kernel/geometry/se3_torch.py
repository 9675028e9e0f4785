"""Differentiable twin of :mod:`dm2_backend.kernel.geometry.se3` for the optimiser (torch)."""

from __future__ import annotations

import torch


def skew(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([z, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], z, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, smooth at zero (Taylor terms below 1e-4 rad)."""
    theta2 = (w * w).sum(-1, keepdim=True).unsqueeze(-1)
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def correction(xi: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """World-frame corrections (...,4,4) from ``xi = (v, w)`` (...,6): rotate by Exp(w) about ``centres``
    (...,3), then translate by v. Zero ``xi`` gives the identity."""
    R = exp_so3(xi[..., 3:])
    t = centres - (R @ centres.unsqueeze(-1)).squeeze(-1) + xi[..., :3]
    T = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def prefix_product(M: torch.Tensor) -> torch.Tensor:
    """Inclusive prefix products ``M_0 @ M_1 @ ... @ M_i`` of (N,4,4), in O(log N) batched steps."""
    out = M
    shift = 1
    n = M.shape[0]
    while shift < n:
        out = torch.cat([out[:shift], out[:-shift] @ out[shift:]], 0)
        shift *= 2
    return out


def transform(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply poses (...,4,4) to points (...,M,3)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def inverse(T: torch.Tensor) -> torch.Tensor:
    """Rigid inverse of poses (...,4,4)."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3].unsqueeze(-1)).squeeze(-1)
    out[..., 3, 3] = 1
    return out
