"""A seedable LiDAR simulator: procedural scenes, ray casting with open3d, loop trajectories with drift."""
