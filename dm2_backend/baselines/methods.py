"""The baselines by name (no heavy imports: the CLI reads these at start-up)."""

#: method -> description (``dm2 baseline --help``)
METHODS = {
    "gtsam": "pose graph (odometry + loop registrations) solved by GTSAM Levenberg-Marquardt",
    "g2o": "the same pose graph solved by g2o (needs dm2[g2o])",
    "multiway": "Open3D multiway registration (global_optimization with line-process loop pruning)",
    "icp": "the incremental ICP warm start itself",
}
#: methods that solve a g2o pose graph (``--graph``)
GRAPH_METHODS = ("gtsam", "g2o")
