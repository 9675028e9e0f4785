"""The pose-graph solvers' options and result (no heavy imports: the CLI reads these at start-up)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2_backend.runtime.errors import InputError

#: robust kernel -> default threshold on the whitened residual (95 % asymptotic efficiency where defined)
KERNELS = {"huber": 1.345, "cauchy": 2.3849, "tukey": 4.6851, "welsch": 2.9846, "geman-mcclure": 1.0,
           "fair": 1.3998, "dcs": 1.0}


@dataclass
class SolverOptions:
    max_iterations: int = 100
    relative_error_tol: float = 1e-5
    robust: str | None = None  # a key of KERNELS
    robust_k: float | None = None  # kernel threshold (whitened residual); default per kernel
    prior_sigma: float = 1e-3  # sigma (m and rad) of the prior on the anchored node(s)

    def kernel_k(self) -> float:
        return self.robust_k if self.robust_k is not None else KERNELS[self.robust]

    def check(self) -> None:
        if self.robust is not None and self.robust not in KERNELS:
            raise InputError(None, f"unknown robust kernel {self.robust!r}; choices: {', '.join(KERNELS)}")
        if self.robust_k is not None and not self.robust_k > 0:
            raise InputError(None, f"robust kernel threshold must be positive, got {self.robust_k}")
        if self.max_iterations < 1:
            raise InputError(None, f"max iterations must be at least 1, got {self.max_iterations}")
        if not self.relative_error_tol >= 0:
            raise InputError(None, f"relative tolerance must be >= 0, got {self.relative_error_tol}")


@dataclass(frozen=True)
class GraphResult:
    """Optimised poses (N,4,4) in the graph's node order; errors in GTSAM's convention (0.5 * chi2); the robust
    kernel and its threshold, the nodes held at their initial pose and, for g2o, whether the information was
    taken in the tangent space."""

    poses: np.ndarray
    initial_error: float | None
    final_error: float | None
    iterations: int | None
    seconds: float
    solver: str
    robust: str | None = None
    robust_k: float | None = None
    anchored: tuple[int, ...] = ()
    tangent_information: bool | None = None

    def summary(self) -> dict:
        """The result as ``report.json`` keeps it."""
        return {"solver": self.solver, "initial_error": self.initial_error, "final_error": self.final_error,
                "iterations": self.iterations, "seconds": self.seconds, **self.settings()}

    def settings(self) -> dict:
        """How the solver was set: the robust kernel, the held nodes (and g2o's tangent information)."""
        out = {"robust": self.robust, "robust_k": self.robust_k}
        if self.tangent_information is not None:
            out["tangent_information"] = self.tangent_information
        return {**out, "anchored": list(self.anchored)}
