"""Training as optimisation: the DeepMapping2 loop over anchor groups, with checkpoints and resume (the
checkpoint file in :mod:`~dm2_backend.optim.checkpoint`, the choice of the returned poses in
:mod:`~dm2_backend.optim.selection`)."""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from dm2_backend.config.optimiser import OptimConfig, switch
from dm2_backend.kernel.geometry import se3_torch
from dm2_backend.kernel.prepared import Frames
from dm2_backend.optim import distributed, losses
from dm2_backend.optim.batching import make_groups
from dm2_backend.optim.checkpoint import CHECKPOINT, load_checkpoint, plain_state, save_checkpoint
from dm2_backend.optim.derived import Derived, derive, loss_regime, pose_regime, sampled_points
from dm2_backend.optim.epoch import TERMS, Epoch, TracePoint
from dm2_backend.optim.mnet_file import MNET, save_mnet
from dm2_backend.optim.occupancy import GridOccupancy
from dm2_backend.optim.pose_model import PoseModel
from dm2_backend.optim.problem import Execution, Problem, Watch
from dm2_backend.optim.regime import disagreement, locally_accurate
from dm2_backend.optim.selection import Best, first_candidate, offer, selection
from dm2_backend.optim.stop import Stop, StopReason
from dm2_backend.runtime.errors import InputError, one_line
from dm2_backend.runtime.progress import progress
from dm2_backend.runtime.threads import ordered_map


@dataclass(frozen=True)
class OptimResult:
    """The first-order stage's returned poses, its epochs and why they ended."""

    poses: np.ndarray
    best_epoch: int
    history: tuple[Epoch, ...] = ()
    derived: Derived | None = None
    stopped: Stop = Stop(StopReason.BUDGET, "")
    #: which poses were returned and why (``best_epoch`` -1: the start itself)
    selection: str = ""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def sample_points(frames: Frames, m: int, seed: int) -> np.ndarray:
    """Exactly ``m`` points per frame (random subset, or with repeats for small frames): (N, m, 3)."""
    rng = np.random.default_rng(seed)
    out = np.empty((len(frames), m, 3), dtype=np.float32)
    for i, p in enumerate(frames.points):
        out[i] = p[rng.choice(len(p), m, replace=len(p) < m)]
    return out


def sample_normals(frames: Frames, samples: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit surface normal at each sampled point (N, m, 3): the smallest principal axis of its ``k`` nearest
    points in its own frame (frames on threads)."""

    def normals(i: int) -> np.ndarray:
        pts, q = frames.points[i], samples[i]
        kk = min(k, len(pts))
        if kk < 3:
            return np.zeros(q.shape, dtype=np.float32)
        _, idx = cKDTree(pts).query(q, k=kk)
        nb = pts[idx].astype(np.float64)  # (m, k, 3)
        nb -= nb.mean(1, keepdims=True)
        _, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))
        return vecs[:, :, 0]

    out = np.zeros(samples.shape, dtype=np.float32)
    for i, n in enumerate(ordered_map(normals, range(len(samples)))):
        out[i] = n
    return out


class Optimiser:
    """Refines warm-start poses by minimising BCE + alpha Chamfer + beta consistency over anchor groups."""

    def __init__(self, problem: Problem, cfg: OptimConfig, execution: Execution | None = None,
                 watch: Watch | None = None) -> None:
        """``problem``: the frames, registrations and start (:class:`~dm2_backend.optim.problem.Problem`);
        ``watch``: what rank 0 evaluates per epoch (``map_metric``, with ``cfg.select == "map"``, chooses the
        returned poses among the start and the epochs; the others are recorded, never used to choose);
        ``execution``: seed, device, progress, points sampled ahead and this process's rank."""
        frames, topology, pairwise, warm_start = problem.frames, problem.topology, problem.pairwise, problem.start
        execution, watch = execution or Execution(), watch or Watch()
        seed, samples = execution.seed, execution.samples
        self.cfg = cfg
        self.dist = execution.dist or distributed.Dist()
        self.seed = seed
        self.metric, self.map_metric, self.trace_metric = watch.metric, watch.map_metric, watch.trace
        self.progress = execution.progress
        self.device = resolve_device(execution.device)
        if cfg.threads > 0 and self.device.type == "cpu":
            torch.set_num_threads(cfg.threads)
        lengths = derive(cfg, frames.scale, frames.planar)
        spread = disagreement(warm_start, topology.groups, pairwise.relative, pairwise.valid,
                              frames.scale.length)
        # loop-closed poses need no drift terms (they would undo the closures;
        # docs/decisions/0014-first-order-optimiser-defaults.md); the pose-graph solution agrees with the
        # registrations by construction; other starts are judged by the measured disagreement
        accurate = (problem.locally_accurate or topology.loop_closed
                    or locally_accurate(spread, lengths.unit, cfg.accurate_below))
        polish = accurate and not frames.planar
        pose, loss = pose_regime(cfg, accurate, polish), loss_regime(cfg, frames.planar, polish)
        self.planar = frames.planar
        self.n = len(frames)
        self.steps_per_epoch = math.ceil(self.n / cfg.batch_groups)
        epochs = cfg.epochs
        if cfg.max_steps > 0:  # long sequences: fewer passes, the same step budget, but at least min_epochs
            epochs = max(min(cfg.epochs, cfg.min_epochs), min(cfg.epochs, cfg.max_steps // self.steps_per_epoch))
        first_order = switch(cfg.first_order, not problem.after_dense)
        self.epochs = epochs if first_order else 0
        warmup = int(round(loss.pose_warmup * self.steps_per_epoch)) if pose.drift is False else 0
        torch.manual_seed(seed)
        if samples is None:
            samples = sample_points(frames, sampled_points(cfg, frames.max_points, frames.planar), seed)
        pts = samples
        if polish and cfg.chamfer_truncate is None:  # polishing: the Chamfer distance truncated at one unit
            lengths = replace(lengths, chamfer_truncate=lengths.unit)
        self.derived = Derived(
            **asdict(lengths),
            drift=pose.drift, lr_pose=pose.lr_pose, start_disagreement=spread, locally_accurate_start=accurate,
            use_bce=loss.use_bce, use_consistency=loss.use_consistency, chamfer_metric=loss.chamfer_metric,
            pose_warmup=loss.pose_warmup, polish=polish, points_per_frame=pts.shape[1],
            # an epoch whose poses disagree with the registrations far more than the start did has diverged (a
            # scattered map can look sharp to the map metric: no two frames overlap any more); never selected
            max_disagreement=None if spread is None else max(4.0 * spread, lengths.unit),
            epochs=self.epochs, first_order=first_order, pose_warmup_steps=warmup,
        )
        self.points = torch.from_numpy(pts).to(self.device)
        self.normals = None
        if self.derived.chamfer_metric == "plane":
            self.normals = torch.from_numpy(sample_normals(frames, pts)).to(self.device)
        self.topo_groups = topology.groups
        self._pairs = (topology.groups, pairwise.relative, pairwise.valid, frames.scale.length)
        self.groups = make_groups(cfg.batching, topology.groups, seed)
        self.relative = torch.from_numpy(pairwise.relative).to(self.device)
        self.valid = torch.from_numpy(pairwise.valid & (topology.groups >= 0)).to(self.device)
        self.model = PoseModel(
            warm_start, frames.planar, self.derived.step_translation, self.derived.step_rotation,
            kind=cfg.pose_model, drift=self.derived.drift, points=self.points,
            length_scale=frames.scale.length, drift_factor=cfg.drift_factor,
        ).to(self.device)
        lo, hi = self._map_box(warm_start, pts)
        self.field = GridOccupancy(
            lo, hi, self.derived.finest_cell, levels=cfg.grid_levels, features=cfg.grid_features,
            max_cells=cfg.grid_max_cells,
        ).to(self.device)
        groups = [
            {"params": self.field.parameters(), "lr": cfg.lr_field},
            {"params": self.model.pose_parameters(), "lr": self.derived.lr_pose},
        ]
        if self.model.network_parameters():
            groups.append({"params": self.model.network_parameters(), "lr": cfg.lr_network})
        self.optim = torch.optim.Adam(groups)
        total = max(1, self.epochs * self.steps_per_epoch)

        def cosine(s: int) -> float:
            return cfg.lr_final + (1 - cfg.lr_final) * 0.5 * (1 + math.cos(math.pi * min(s, total) / total))

        def poses_after_warmup(s: int) -> float:  # the poses hold still while the field learns the map
            return 0.0 if s < warmup else cosine(s)

        self.sched = torch.optim.lr_scheduler.LambdaLR(
            self.optim, [cosine, poses_after_warmup] + [cosine] * (len(groups) - 2))

    def _map_box(self, poses: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sub = pts[:, :: max(1, pts.shape[1] // 32)]
        world = np.einsum("nij,nmj->nmi", poses[:, :3, :3], sub) + poses[:, None, :3, 3]
        lo, hi = world.reshape(-1, 3).min(0), world.reshape(-1, 3).max(0)
        pad = 0.2 * (hi - lo).max() + 4 * self.derived.unit
        dims = 2 if self.planar else 3
        return lo[:dims] - pad, hi[:dims] + pad

    # ------------------------------------------------------------------ one step
    def _step_loss(self, anchors: np.ndarray, generator: torch.Generator) -> dict[str, torch.Tensor]:
        cfg, unit = self.cfg, self.derived.unit
        groups = self.groups[anchors]
        topo = self.topo_groups[anchors]
        frames = np.unique(np.concatenate([anchors, groups[groups >= 0], topo[topo >= 0]]))
        slot = np.full(self.n, -1)
        slot[frames] = np.arange(len(frames))
        fidx = torch.from_numpy(frames).to(self.device)
        T = self.model(fidx)  # (F,4,4) float64
        Tf = T.float()
        local = self.points[fidx]
        world = se3_torch.transform(Tf, local)  # (F,M,3)
        out: dict[str, torch.Tensor] = {}
        total = torch.zeros((), device=self.device)
        member = np.unique(np.concatenate([anchors, groups[groups >= 0]]))
        ms = torch.from_numpy(slot[member]).to(self.device)
        if self.derived.use_bce:
            hits = world[ms, : cfg.bce_points_per_frame]
            margin = self.derived.free_margin
            free = losses.free_space_samples(hits, Tf[ms, :3, 3], cfg.samples_per_ray, margin, generator)
            if cfg.free_clear:
                free = losses.clear_of(free, world, margin)
            out["bce"] = losses.occupancy_bce(self.field, hits, free)
            total = total + out["bce"]
        if cfg.use_chamfer:
            out["chamfer"] = self._chamfer(anchors, groups, slot, T, world, fidx) / unit
            total = total + cfg.alpha * out["chamfer"]
        if self.derived.use_consistency:
            a = torch.from_numpy(slot[anchors]).to(self.device)
            nb = torch.from_numpy(slot[np.where(topo >= 0, topo, anchors[:, None])]).to(self.device)
            rel = self.relative[torch.from_numpy(anchors).to(self.device)]
            via = T[nb] @ se3_torch.inverse(rel)  # (B,k,4,4)
            a1 = se3_torch.transform(Tf[a], local[a])  # (B,M,3)
            a2 = se3_torch.transform(via.float(), local[a].unsqueeze(1))  # (B,k,M,3)
            d = (a2 - a1.unsqueeze(1)).norm(dim=-1).mean(-1) / unit  # (B,k), in units
            if cfg.consistency_kernel == "cauchy":
                d = torch.log1p(d)
            valid = self.valid[torch.from_numpy(anchors).to(self.device)]
            out["consistency"] = (d * valid).sum() / valid.sum().clamp_min(1)
            total = total + cfg.beta * out["consistency"]
        out["loss"] = total
        return out

    def _chamfer(self, anchors, groups, slot, T, world, fidx) -> torch.Tensor:
        """Chamfer between each anchor and its group members. Nearest neighbours come from a KD-tree per frame
        over its current world points, each queried once with the points of every frame paired with it (one
        tree over the whole batch with the frame number as a far-apart 4th coordinate took 1.8x as long)."""
        pairs = np.array([(a, j) for a, row in zip(anchors, groups) for j in row if j >= 0 and j != a])
        if len(pairs) == 0:
            return torch.zeros((), device=self.device)
        pts = world.detach().cpu().numpy().astype(np.float64)  # (F, M, 3)
        m = pts.shape[1]
        sa, sj = slot[pairs[:, 0]], slot[pairs[:, 1]]
        trees = {int(f): cKDTree(pts[f]) for f in np.union1d(sa, sj)}

        def query(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
            """For each pair, the index in frame dst of the nearest point to each point of frame src."""
            out = np.empty((len(src), m), dtype=np.int64)
            for f in np.unique(dst):
                sel = np.nonzero(dst == f)[0]
                out[sel] = trees[int(f)].query(pts[src[sel]].reshape(-1, 3), k=1)[1].reshape(len(sel), m)
            return out

        ian = torch.from_numpy(query(sa, sj)).to(self.device)
        ina = torch.from_numpy(query(sj, sa)).to(self.device)
        sa_t, sj_t = torch.from_numpy(sa).to(self.device), torch.from_numpy(sj).to(self.device)
        A, N = world[sa_t], world[sj_t]  # (P,M,3)
        nA = torch.gather(N, 1, ian.unsqueeze(-1).expand(-1, -1, 3))
        nN = torch.gather(A, 1, ina.unsqueeze(-1).expand(-1, -1, 3))
        cut = self.derived.chamfer_truncate
        if self.normals is None:
            return (A - nA).norm(dim=-1).clamp(max=cut).mean() + (N - nN).norm(dim=-1).clamp(max=cut).mean()
        # point-to-plane: the residual along the neighbour's surface normal (rotated into the world)
        Rn = torch.einsum("fij,fmj->fmi", T[:, :3, :3].float(), self.normals[fidx])
        nrm_N = torch.gather(Rn[sj_t], 1, ian.unsqueeze(-1).expand(-1, -1, 3))
        nrm_A = torch.gather(Rn[sa_t], 1, ina.unsqueeze(-1).expand(-1, -1, 3))
        da = ((A - nA) * nrm_N).sum(-1).abs().clamp(max=cut)
        dn = ((N - nN) * nrm_A).sum(-1).abs().clamp(max=cut)
        return da.mean() + dn.mean()

    # ------------------------------------------------------------------ epochs
    def poses(self) -> np.ndarray:
        """Current poses, re-anchored so the first frame keeps its warm-start pose (fixes the gauge)."""
        with torch.no_grad():
            T = self.model().cpu().numpy()
        T0 = self.model.T0[0].cpu().numpy()
        return T0 @ np.linalg.inv(T[0]) @ T

    def _state(self, epoch: int, best: Best, history: list[Epoch]) -> dict:
        """The checkpoint: tensors and plain Python values only (arrays as tensors, numpy scalars as floats),
        so that it loads with ``torch.load(weights_only=True)``, which runs no code from the file."""
        return {
            "epoch": epoch, "model": self.model.state_dict(), "field": self.field.state_dict(),
            "optim": self.optim.state_dict(), "sched": self.sched.state_dict(), "best": plain_state(best.state()),
            "history": [e.row() for e in history], "config": plain_state(self.cfg.model_dump()), "seed": int(self.seed),
        }

    def _save_mnet(self, path: Path) -> None:
        """The occupancy field for the maps (``dm2_backend.maps``), with the transform from its frame to the
        world of :meth:`poses` (re-anchored on the first frame)."""
        with torch.no_grad():
            first = self.model()[0].cpu().numpy()
        gauge = self.model.T0[0].cpu().numpy() @ np.linalg.inv(first)
        save_mnet(path, self.field, gauge, trained=bool(self.derived.use_bce) and self.epochs > 0)

    def run(self, checkpoint_dir: Path | None = None, resume: bool = False) -> OptimResult:
        """Train; with several ranks only rank 0 reads and writes the checkpoint, shows progress and
        evaluates ``metric``, and every rank resumes from rank 0's checkpoint. Each epoch: :meth:`_epoch` (the
        steps), :meth:`_judge` (its row, and whether its poses are the best so far), :meth:`_converged` (the
        early stop)."""
        lead = self.dist.rank == 0
        by_map = self.cfg.select == "map" and self.map_metric is not None
        first = self.poses()  # the start is a candidate: refine never returns a blurrier map than it was given
        best = first_candidate(first, float(self.map_metric(first)) if by_map and lead else None)
        ckpt = checkpoint_dir / CHECKPOINT if checkpoint_dir else None
        best, history, start = self._resume(ckpt, resume, len(first), best)
        ddp = distributed.data_parallel(self) if self.dist.enabled else None
        stopped: Stop | None = None
        flat = 0
        bar = progress(range(start, self.epochs), "refine", unit="epoch",
                       enabled=self.progress and lead and self.epochs > start)
        for epoch in bar:
            t0 = time.perf_counter()
            sums, trace, stopped = self._epoch(epoch, ddp)
            if stopped is not None:
                break
            mean = {k: v / self.steps_per_epoch for k, v in sums.items()}
            record = Epoch(epoch, mean["loss"], time.perf_counter() - t0, (epoch + 1) * self.steps_per_epoch,
                           tuple(trace), **{t: mean[t] for t in TERMS if t in mean})
            best = self._judge(record, history, best, by_map)
            shown = {k: getattr(history[-1], k) for k in ("loss", "ate", "map_entropy")}
            bar.set_postfix(**{k: f"{v:.4g}" for k, v in shown.items() if v is not None})
            flat, stopped = self._converged(epoch, history, best, by_map, flat)
            if stopped is not None:
                history[-1] = replace(history[-1], converged=stopped.detail)
            if ckpt is not None and lead:
                save_checkpoint(ckpt, self._state(epoch, best, history))
            if stopped is not None:
                break
        rejected = sum(e.rejected is not None for e in history)
        if rejected and best.epoch < 0 and (stopped is None or not stopped.failed):
            stopped = Stop(StopReason.DIVERGED, f"diverged: all {rejected} epochs disagreed with the registrations "
                                                f"(limit {self.derived.max_disagreement:.3g} m); returned the start")
        if ckpt is not None and lead:
            self._save_mnet(checkpoint_dir / MNET)
        if stopped is None:
            stopped = (Stop(StopReason.BUDGET, f"{len(history)} epochs") if self.epochs > 0
                       else Stop(StopReason.NOT_RUN, "no first-order epoch (optimiser.first_order)"))
        return OptimResult(best.poses, best.epoch, tuple(history), self.derived, stopped,
                           selection(best, by_map, rejected, self.epochs))

    def _resume(self, ckpt: Path | None, resume: bool, frames: int, best: Best) -> tuple[Best, list[Epoch], int]:
        """With ``resume``, the model, optimiser and schedule of rank 0's checkpoint (on every rank), and the best
        poses, the epoch rows and the next epoch it records; else ``best``, no rows and epoch 0."""
        dist = self.dist
        state = None
        if resume and dist.rank == 0 and ckpt is not None and ckpt.exists():
            state = load_checkpoint(ckpt, "cpu" if dist.enabled else self.device, frames)
        if resume and dist.enabled:
            state = distributed.broadcast(state)
        if state is None:
            return best, [], 0
        try:
            self.model.load_state_dict(state["model"])
            self.field.load_state_dict(state["field"])
            self.optim.load_state_dict(state["optim"])
            self.sched.load_state_dict(state["sched"])
            return state["best"], state["history"], state["epoch"] + 1
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:  # e.g. a 3D run's state into a 2D one
            raise InputError(ckpt, "--resume: this checkpoint is of another kind of run and does not fit this "
                                   f"one ({one_line(str(exc))[:160]}); run without --resume") from None

    def _epoch(self, epoch: int, ddp) -> tuple[dict[str, float], list[TracePoint], Stop | None]:
        """One pass over the anchor groups in this epoch's seeded order: the summed loss terms, the convergence
        trace (a few points: the loss and, with a metric, accuracy) and a :class:`Stop` on a non-finite loss."""
        dist, lead = self.dist, self.dist.rank == 0
        rng = np.random.default_rng([self.seed, epoch])
        gen = torch.Generator(device="cpu").manual_seed(distributed.generator_seed(int(rng.integers(2**31)), dist))
        order = rng.permutation(self.n)  # the same on every rank
        trace_every = max(1, self.steps_per_epoch // 8)
        sums: dict[str, float] = {}
        trace, window = [], []
        for s in range(self.steps_per_epoch):
            anchors = order[s * self.cfg.batch_groups : (s + 1) * self.cfg.batch_groups]
            if len(anchors) == 0:
                continue
            if ddp is None:
                parts = values = self._step_loss(anchors, gen)
                loss = parts["loss"]
            else:  # this rank's share; DDP averages the gradients, so weight by the share times the ranks
                mine, weight = distributed.shard(anchors, dist)
                parts = ddp(mine, gen)
                values = distributed.reduce_parts(parts, weight)
                loss = parts["loss"] * (weight * dist.world)
            if not torch.isfinite(values["loss"]):  # the reduced loss: every rank stops together
                return sums, trace, Stop(StopReason.NON_FINITE, f"non-finite loss at epoch {epoch} step {s}; kept "
                                                                "the best epoch")
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self.optim.step()
            self.sched.step()
            for key, val in values.items():
                sums[key] = sums.get(key, 0.0) + float(val.detach())
            window.append(float(values["loss"].detach()))
            if (s + 1) % trace_every == 0 or s + 1 == self.steps_per_epoch:
                ate = float(self.trace_metric(self.poses())) if self.trace_metric is not None and lead else None
                trace.append(TracePoint(epoch * self.steps_per_epoch + s + 1, float(np.mean(window)), ate))
                window = []
        return sums, trace, None

    def _judge(self, record: Epoch, history: list[Epoch], best: Best, by_map: bool) -> Best:
        """Add what the epoch's poses measure to its ``record`` (accuracy, disagreement with the registrations,
        map entropy), append it to ``history`` and return the best candidate so far: an epoch that disagrees
        far more than the start did has diverged and is never one."""
        lead = self.dist.rank == 0
        poses = self.poses()
        if self.metric is not None and lead:
            name = getattr(self.metric, "name", None) or None  # which metric "ate" is (pipeline.live.LiveMetric)
            record = replace(record, ate=float(self.metric(poses)), ate_metric=name)
        spread, limit = disagreement(poses, *self._pairs), self.derived.max_disagreement
        diverged = spread is not None and limit is not None and spread > limit
        record = replace(record, disagreement=spread)
        if diverged:
            record = replace(record, rejected=f"disagrees with the registrations ({spread:.3g} m > {limit:.3g} m)")
        elif self.map_metric is not None and lead:
            record = replace(record, map_entropy=float(self.map_metric(poses)))
        history.append(record)
        return best if diverged else offer(best, record, poses, by_map and lead)

    def _converged(self, epoch: int, history: list[Epoch], best: Best, by_map: bool, flat: int
                   ) -> tuple[int, Stop | None]:
        """The early stop: after two epochs in a row whose loss changed by less than ``converge_tol`` of itself
        and whose map did not improve (past the pose warm-up; only under the step budget, explicit epochs run
        them all, and with the map selection, judged on rank 0: every rank takes its decision). Returns the
        count of such epochs and the :class:`Stop`, if it is time."""
        lead = self.dist.rank == 0
        early = self.cfg.converge_tol > 0 and self.cfg.max_steps > 0 and self.cfg.select == "map"
        warmup_epochs = math.ceil(self.derived.pose_warmup_steps / self.steps_per_epoch)
        if early and by_map and lead and epoch >= warmup_epochs + 1:
            previous, loss = history[-2].loss, history[-1].loss
            better_map = best.epoch == epoch
            small = abs(previous - loss) <= self.cfg.converge_tol * max(abs(previous), 1e-12)
            flat = flat + 1 if small and not better_map else 0
        if self.dist.enabled and early:
            flat = distributed.broadcast(flat)
        if flat >= 2 and epoch + 1 < self.epochs:
            return flat, Stop(StopReason.CONVERGED, f"stopped after epoch {epoch} of {self.epochs}: the loss changed "
                              f"by less than {self.cfg.converge_tol:g} of itself and the map did not improve, twice")
        return flat, None
