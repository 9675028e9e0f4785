"""Whether a sequence's frames agree with a trajectory's relative poses: is a reference fit to judge refine by?

For frame pairs ``i, i + gap`` (every ``--every``-th ``i``, several gaps) the two frames are registered with open3d
point-to-plane ICP, started from each trajectory's relative pose in turn (the best fitness wins, so no trajectory's
start decides the answer). Each trajectory's relative pose is then compared with the registration's: translation
and rotation differences (median and rms over the pairs). A reference that the frames contradict (a jump the
frames do not show, relative poses the registrations put centimetres away while another trajectory agrees) is no
fixed point for a map optimiser, and an error measured against it says as much about the reference as about the
estimate.

Lengths come from the data (``dm2_backend.kernel.scan_scale``): the clouds are thinned to the larger of the raw point
spacing and the median range / 200; the correspondence distance is three times that.

    python benchmarks/reference_check.py --scans ../shared/data/depth3d/redkitchen_000-499 \\
        --trajectory reference=../shared/data/depth3d/redkitchen_000-499:depth --trajectory refine=RUN/poses_tum.txt

writes ``benchmarks/results/reference-check-<name>.json`` and ``.md``. ``--random-walk MM`` adds the first
trajectory with a random walk of MM millimetres (and MM / 40 degrees) a step, seeded: the check must tell it from the
first on frames whose truth is exact before its verdict on a real reference means anything.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dm2_backend.formats import ReadOptions, open_scans, read_trajectory  # noqa: E402
from dm2_backend.kernel.geometry import se3  # noqa: E402
from dm2_backend.kernel.scan_scale import derive_scale  # noqa: E402
from dm2_backend.kernel.scans import associate_scans  # noqa: E402

#: pairs whose best registration matches fewer than this fraction of the moving frame's points are not compared
MIN_FITNESS = 0.5
ICP = o3d.pipelines.registration


def registration_cloud(points: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    """``points`` voxel-down-sampled, with normals for point-to-plane ICP."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)[:, :3]))
    pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=30))
    return pcd


def _differences(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) between two relative poses."""
    d = se3.relative(a, b)
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(se3.rotation_angle(d[None, :3, :3])[0]))


def check(scans, trajectories: dict[str, np.ndarray], gaps: list[int], every: int) -> dict:
    """Per gap and trajectory: median and rms differences (translation m, rotation deg) of its relative poses from
    the frames' registrations, over the pairs the registration matched (:data:`MIN_FITNESS`)."""
    scale = derive_scale(scans)
    voxel = max(scale.spacing_raw, scale.range_median / 200.0)
    distance = 3.0 * voxel
    clouds: dict[int, o3d.geometry.PointCloud] = {}

    def cloud(i: int) -> o3d.geometry.PointCloud:
        if i not in clouds:
            clouds[i] = registration_cloud(scans[i].points, voxel)
        return clouds[i]

    result: dict = {"voxel_m": voxel, "distance_m": distance, "gaps": {}}
    for gap in gaps:
        rows = []
        for i in range(0, len(scans) - gap, every):
            j = i + gap
            starts = {name: se3.relative(p[i], p[j]) for name, p in trajectories.items()}
            best = None
            for start in starts.values():
                reg = ICP.registration_icp(cloud(j), cloud(i), distance, start,
                                           ICP.TransformationEstimationPointToPlane(),
                                           ICP.ICPConvergenceCriteria(max_iteration=60))
                if best is None or reg.fitness > best.fitness + 1e-3 or (
                        abs(reg.fitness - best.fitness) <= 1e-3 and reg.inlier_rmse < best.inlier_rmse):
                    best = reg
            if best.fitness < MIN_FITNESS:
                continue
            rows.append((i, {name: _differences(best.transformation, s) for name, s in starts.items()}))
            for k in [k for k in clouds if k < i - max(gaps)]:
                del clouds[k]
        summary = {"pairs": len(rows)}
        for name in trajectories:
            t = np.array([r[1][name][0] for r in rows])
            a = np.array([r[1][name][1] for r in rows])
            summary[name] = {"trans_median_m": float(np.median(t)), "trans_rms_m": float(np.sqrt(np.mean(t**2))),
                             "rot_median_deg": float(np.median(a)), "rot_rms_deg": float(np.sqrt(np.mean(a**2))),
                             "worst_pairs": [[int(r[0]), int(r[0]) + gap, round(r[1][name][0], 4)]
                                             for r in sorted(rows, key=lambda r: -r[1][name][0])[:5]]}
        result["gaps"][str(gap)] = summary
    return result


def _read(spec: str, scans) -> tuple[str, np.ndarray]:
    """``name=path[:format]`` -> the trajectory's pose at each scan."""
    name, _, rest = spec.partition("=")
    path, _, fmt = rest.rpartition(":") if ":" in rest and not Path(rest).exists() else (rest, "", "")
    traj = read_trajectory(Path(path), fmt or None, ReadOptions())
    if len(traj) == len(scans) and (traj.timestamps is None or scans.timestamps is None):
        return name, traj.poses
    _, matched = associate_scans(scans, traj, 0.01)
    if len(matched) != len(scans):
        raise SystemExit(f"{path}: {len(matched)} of {len(scans)} scans have a pose")
    return name, matched.poses


def with_random_walk(poses: np.ndarray, mm: float, seed: int = 0) -> np.ndarray:
    """``poses`` with every step perturbed in the moving frame by ``mm`` millimetres and ``mm / 40`` degrees
    (normal, per axis)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    steps = se3.relative(poses[:-1], poses[1:])
    noise = se3.make_poses(Rotation.from_rotvec(rng.normal(0.0, np.radians(mm / 40.0), (len(steps), 3))).as_matrix(),
                           rng.normal(0.0, mm / 1000.0, (len(steps), 3)))
    out = [poses[0]]
    for step, n in zip(steps, noise, strict=True):
        out.append(out[-1] @ step @ n)
    return np.stack(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", required=True, type=Path)
    ap.add_argument("--trajectory", action="append", required=True, help="name=path[:format], two or more")
    ap.add_argument("--gaps", type=int, nargs="+", default=[1, 10, 30])
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--name", default=None, help="results file name (default: the scans folder's)")
    ap.add_argument("--random-walk", type=float, default=None, metavar="MM")
    args = ap.parse_args()
    scans = open_scans(args.scans, None, ReadOptions())
    trajectories = dict(_read(s, scans) for s in args.trajectory)
    if args.random_walk:
        first = next(iter(trajectories))
        trajectories[f"{first}_with_random_walk"] = with_random_walk(trajectories[first], args.random_walk)
    t0 = time.perf_counter()
    result = check(scans, trajectories, args.gaps, args.every)
    result.update(scans=str(args.scans), trajectories=args.trajectory, every=args.every,
                  seconds=round(time.perf_counter() - t0, 1),
                  command="python benchmarks/reference_check.py " + " ".join(sys.argv[1:]))
    out = REPO / "benchmarks" / "results" / f"reference-check-{args.name or args.scans.name}"
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    lines = [f"# Reference check: {args.scans}", "", f"`{result['command']}`", "",
             f"ICP thinning {result['voxel_m']:.4f} m, correspondence distance {result['distance_m']:.4f} m; "
             f"pairs matched at fitness >= {MIN_FITNESS}.", "",
             "| gap | pairs | trajectory | trans median (mm) | trans rms (mm) | rot median (deg) | rot rms (deg) |",
             "|---:|---:|---|---:|---:|---:|---:|"]
    for gap, summary in result["gaps"].items():
        for name in trajectories:
            s = summary[name]
            lines.append(f"| {gap} | {summary['pairs']} | {name} | {1e3 * s['trans_median_m']:.1f} | "
                         f"{1e3 * s['trans_rms_m']:.1f} | {s['rot_median_deg']:.2f} | {s['rot_rms_deg']:.2f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
