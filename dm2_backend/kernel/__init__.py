"""The kernel every stage stands on, importing none of them: the data model (trajectories, scans, the preparation's
typed outputs, the pose graph), SE(3), the planes and cells of the dense objective, the pose graph's edges and its
solvers (GTSAM, g2o)."""
