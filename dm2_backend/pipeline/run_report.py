"""``report.json`` of a run folder as a typed record with one writer (refine and baseline alike)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from dm2_backend import __version__
from dm2_backend.pipeline.outputs import write_report
from dm2_backend.prepare.steps import Prepared


@dataclass
class PrepareSummary:
    """What the preparation did: which steps came from the cache, the data's scale, the topology's size."""

    cached: dict[str, bool]
    scale: dict[str, float]
    topology_edges: int
    pairs: int
    pairs_valid: int

    @classmethod
    def of(cls, prep: Prepared) -> PrepareSummary:
        return cls(cached=dict(prep.cached), scale=prep.frames.scale.to_dict(),
                   topology_edges=int(len(prep.topology.edges)), pairs=int((prep.topology.groups >= 0).sum()),
                   pairs_valid=int(prep.pairwise.valid.sum()))


@dataclass
class RunReport:
    """A run's results. Metrics are keyed as ``dm2 eval`` names them (``ape_trans_rmse_m``, ``map_entropy``,
    ...) for each stage: the warm start, the loop-closed poses (when the place recognition made them), the
    optimiser's start (refine) and the result. ``details`` holds the method's own entries (refine: best epoch,
    selection, derived settings, device; baseline: the solver's summary), written at the top level."""

    method: str
    frames: int
    planar: bool
    metrics: dict[str, float]
    warm_start_metrics: dict[str, float]
    map_quality: dict
    timings: dict[str, float]
    peak_rss_mb: float
    prepare: PrepareSummary
    files: list[str]
    ground_truth_scans: int | None = None
    loop_closed_metrics: dict[str, float] | None = None
    start_metrics: dict[str, float] | None = None
    epochs: list[dict] | None = None
    #: where the result's metrics are ill-posed or within reach of standing still (``evaluation/cautions.py``)
    cautions: list[str] | None = None
    #: the process's peak memory when each stage ended (MiB; it only grows: the first stage at ``peak_rss_mb``
    #: set it)
    peak_rss_mb_by_stage: dict[str, float] | None = None
    details: dict = field(default_factory=dict)
    dm2_version: str = __version__

    def to_dict(self) -> dict:
        """The ``report.json`` document: the fields (unset optional ones left out) and ``details`` flattened."""
        doc = {k: v for k, v in asdict(self).items() if k != "details" and v is not None}
        clash = set(doc) & set(self.details)
        if clash:
            raise ValueError(f"report details shadow report fields: {', '.join(sorted(clash))}")
        return {**doc, **self.details}

    def write(self, path: Path) -> None:
        write_report(path, self.to_dict())
