"""The DeepMapping2 losses: occupancy BCE (M-Net), Chamfer, and local-to-global consistency."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from dm2_backend.kernel.geometry import se3_torch


def free_space_samples(
    points: torch.Tensor, origins: torch.Tensor, per_ray: int, margin: float, generator: torch.Generator
) -> torch.Tensor:
    """Points sampled on each ray between the sensor origin and the hit, at random fractions per ray,
    stopping ``margin`` metres short of the hit. ``points`` (G, M, 3), ``origins`` (G, 3) -> (G, M*per_ray, 3)."""
    ray = points - origins[:, None, :]
    length = ray.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    top = (1 - margin / length).clamp_min(0)  # (G, M, 1)
    u = torch.rand(*points.shape[:2], per_ray, generator=generator, dtype=points.dtype) * top
    samples = origins[:, None, None, :] + u.unsqueeze(-1) * ray.unsqueeze(2)
    return samples.reshape(points.shape[0], -1, 3)


def clear_of(samples: torch.Tensor, surface: torch.Tensor, margin: float) -> torch.Tensor:
    """The free-space ``samples`` (..., D) farther than ``margin`` from every ``surface`` point (..., D), as (S, D).

    A ray that grazes a surface (the ground seen by a LiDAR far ahead, a wall along a corridor) runs within a
    cell of it long before its hit, so samples taken only along the ray would be labelled free where other rays
    observed the surface; dropping them keeps the two labels apart."""
    pts = samples.reshape(-1, samples.shape[-1])
    tree = cKDTree(surface.detach().reshape(-1, surface.shape[-1]).cpu().numpy())
    dist, _ = tree.query(pts.detach().cpu().numpy(), k=1, distance_upper_bound=margin)
    keep = torch.from_numpy(~np.isfinite(dist)).to(pts.device)
    return pts[keep]


def occupancy_bce(field, occupied: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """The paper's BCE: observed points labelled 1, free-space samples labelled 0 (each term averaged)."""
    dims = field.dim
    lo = field(occupied[..., :dims].float())
    loss = F.binary_cross_entropy_with_logits(lo, torch.ones_like(lo))
    if free.numel():  # every sample may have been dropped as too close to a surface (clear_of)
        lf = field(free[..., :dims].float())
        loss = loss + F.binary_cross_entropy_with_logits(lf, torch.zeros_like(lf))
    return loss


def consistency(
    T_anchor: torch.Tensor, T_neighbours: torch.Tensor, relative: torch.Tensor, anchor_points: torch.Tensor
) -> torch.Tensor:
    """The paper's L_C for one anchor: mean over neighbours j and points s of
    ``|| T_i s - T_j inv(T_j^i) s ||`` with ``relative`` (k,4,4) = T_j^i (neighbour j in anchor i's frame)."""
    via_neighbours = T_neighbours @ se3_torch.inverse(relative)  # (k,4,4): anchor pose implied by each j
    a1 = se3_torch.transform(T_anchor, anchor_points)  # (M,3)
    a2 = se3_torch.transform(via_neighbours, anchor_points.unsqueeze(0))  # (k,M,3)
    return (a2 - a1.unsqueeze(0)).norm(dim=-1).mean()
