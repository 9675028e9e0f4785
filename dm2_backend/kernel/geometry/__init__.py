"""Geometry: the SE(3) toolkit (numpy) and its differentiable twin (torch)."""
