"""Classical back-ends to compare DeepMapping2 with: pose-graph optimisation (GTSAM, g2o), Open3D multiway
registration, and the ICP warm start itself."""
