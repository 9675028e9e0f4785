"""The classical back-ends dm2 is compared with, as a table over the kernel's solvers: the pose graph solved by
GTSAM or g2o (``solvers``), Open3D multiway registration (``multiway``) and the ICP warm start itself; their names in
``methods``."""
