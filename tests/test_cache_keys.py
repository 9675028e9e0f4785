"""The preparation cache never serves results computed from other inputs, options or code: every read option
and every input file is in the key, a changed plugin option re-runs that step and those after it only, a
damaged entry is rebuilt, and the caller's config is not changed."""

from __future__ import annotations

import copy
import logging
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from optim_cases import one_thread, planar_case

from dm2_backend import config
from dm2_backend.cli.main import cli
from dm2_backend.config.schema import RunConfig
from dm2_backend.formats import ReadOptions, open_scans, read_trajectory
from dm2_backend.prepare import store
from dm2_backend.prepare.cache_keys import code_fingerprint, file_fingerprint, module_closure, source_key, step_key
from dm2_backend.prepare.steps import prepare
from dm2_backend.simulate.sequence import write_sequence

STEPS = ("frames", "warm_start", "place_recognition", "registration")


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    case = planar_case(frames=40)
    root = tmp_path_factory.mktemp("seq")
    write_sequence(root, case.scans, case.gt, case.warm, 10.0)
    return root


def frames_key(path: Path, options: ReadOptions) -> str:
    return step_key(source_key(open_scans(path, None, options)))


@pytest.mark.parametrize("option", [
    {"times": "times.txt"}, {"calib": "calib.txt"}, {"topic": "/scan"}, {"depth_scale": 500.0},
    {"intrinsics": (525.0, 525.0, 319.5, 239.5)}, {"pose_source": "odometry"}, {"duplicate_times": "error"},
    {"stride": 2}, {"laser_offset": (0.1, 0.0, 0.0)}, {"max_range": 30.0}, {"min_range": 0.5},
    {"extra": {"third_party": 1}},
])
def test_every_read_option_is_in_the_key(seq, option):
    """Each declared read option (and a third party's ``extra``) changes the frames' key."""
    if "times" in option:
        option = {"times": seq / "times.txt"}
    if "calib" in option:
        (seq / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
        option = {"calib": seq / "calib.txt"}
    assert frames_key(seq / "velodyne", ReadOptions(**option)) != frames_key(seq / "velodyne", ReadOptions())


def test_the_same_inputs_give_the_same_key(seq):
    assert frames_key(seq / "velodyne", ReadOptions(depth_scale=5.0)) == frames_key(seq / "velodyne",
                                                                                    ReadOptions(depth_scale=5.0))


def test_a_scan_overwritten_in_place_changes_the_key(seq, tmp_path):
    folder = tmp_path / "velodyne"
    folder.mkdir()
    for f in sorted((seq / "velodyne").iterdir()):
        (folder / f.name).write_bytes(f.read_bytes())
    before = frames_key(folder, ReadOptions())
    st = folder.stat()
    victim = sorted(folder.iterdir())[5]
    victim.write_bytes(victim.read_bytes()[:-16])  # one scan rewritten; the folder's own mtime put back
    os.utime(folder, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert folder.stat().st_mtime_ns == st.st_mtime_ns
    assert frames_key(folder, ReadOptions()) != before
    # a times file rewritten in place changes the key too
    times = tmp_path / "times.txt"
    times.write_text((seq / "times.txt").read_text())
    with_times = frames_key(folder, ReadOptions(times=times))
    stamps = np.loadtxt(times)
    np.savetxt(times, stamps * 1.5)  # the same length, other stamps
    assert frames_key(folder, ReadOptions(times=times)) != with_times
    assert file_fingerprint(tmp_path / "nothing") == []


def test_the_code_of_a_plugin_and_of_what_it_uses_is_in_the_key():
    from dm2_backend.plugins.topology_loops import LoopsTopology
    from dm2_backend.plugins.topology_radius import RadiusTopology

    closure = module_closure(LoopsTopology.__module__)
    # the shared algorithms the plugin calls are part of its fingerprint, not just its own file
    shared = {"dm2_backend.algorithms.common", "dm2_backend.algorithms.gates", "dm2_backend.kernel.geometry.se3"}
    assert shared <= closure
    assert code_fingerprint(LoopsTopology) != code_fingerprint(RadiusTopology)


def run(seq: Path, cache: Path, cfg: RunConfig):
    scans = open_scans(seq / "velodyne", None, ReadOptions(times=seq / "times.txt"))
    given = read_trajectory(seq / "warm_start.txt", "kitti")
    return prepare(scans, given, cfg, cache, progress=False)


def test_a_changed_option_reruns_that_step_and_those_after_only(seq, tmp_path):
    cache = tmp_path / "cache"
    base = {"frames": {"max_points": 128}, "place_recognition": {"name": "radius"}}
    cfg = config.load(None, base)
    first = run(seq, cache, cfg)
    assert first.cached == dict.fromkeys(STEPS, False)
    assert run(seq, cache, cfg).cached == dict.fromkeys(STEPS, True)
    reg = config.load(None, config.merge(base, {"registration": {"options": {"max_distance": 0.7}}}))
    assert run(seq, cache, reg).cached == {"frames": True, "warm_start": True, "place_recognition": True,
                                           "registration": False}
    pr = config.load(None, config.merge(base, {"place_recognition": {"options": {"radius": 3.0}}}))
    assert run(seq, cache, pr).cached == {"frames": True, "warm_start": True, "place_recognition": False,
                                          "registration": False}


def test_prepare_leaves_the_callers_config_as_given(seq, tmp_path):
    cfg = config.load(None, {"frames": {"max_points": 128}})
    given = copy.deepcopy(cfg)
    prep = run(seq, tmp_path / "cache", cfg)
    assert cfg == given and cfg.place_recognition.name == "auto"
    assert prep.resolved["place_recognition"].name == "loops"


def test_a_damaged_entry_is_reported_and_rebuilt(seq, tmp_path, caplog):
    cache = tmp_path / "cache"
    cfg = config.load(None, {"frames": {"max_points": 128}, "place_recognition": {"name": "radius"}})
    expected = [np.array(p) for p in run(seq, cache, cfg).frames.points]  # copies: the entry is memory-mapped
    points = next(cache.glob("frames-*")) / "points.npy"
    points.write_bytes(points.read_bytes()[: points.stat().st_size // 2])
    with caplog.at_level(logging.WARNING):
        again = run(seq, cache, cfg)
    assert again.cached["frames"] is False and again.cached["registration"] is True
    assert any("is damaged" in r.getMessage() and "computing it again" in r.getMessage() for r in caplog.records)
    for a, b in zip(expected, again.frames.points, strict=True):
        np.testing.assert_array_equal(a, b)
    assert run(seq, cache, cfg).cached["frames"] is True  # the rebuilt entry serves the next run


def test_cache_info_and_clear(seq, tmp_path):
    cache = tmp_path / "cache"
    run(seq, cache, config.load(None, {"frames": {"max_points": 128}, "place_recognition": {"name": "radius"}}))
    info = CliRunner().invoke(cli, ["cache", "info", "--cache-dir", str(cache)])
    assert info.exit_code == 0 and "entries    4," in info.output and "frames" in info.output
    kept = CliRunner().invoke(cli, ["cache", "clear", "--cache-dir", str(cache), "--older-than", "1d"])
    entries = [p for p in cache.iterdir() if p.name != store.CACHE_MARKER]
    assert kept.exit_code == 0 and "removed 0 entries" in kept.output and len(entries) == 4
    bad = CliRunner().invoke(cli, ["cache", "clear", "--cache-dir", str(cache), "--older-than", "soon"])
    assert bad.exit_code == 2 and "--older-than" in bad.output
    gone = CliRunner().invoke(cli, ["cache", "clear", "--cache-dir", str(cache)])
    assert gone.exit_code == 0 and "removed 4 entries" in gone.output
    assert [p.name for p in cache.iterdir()] == [store.CACHE_MARKER]  # the folder stays a dm2 cache


def test_loop_closed_is_a_field_that_survives_the_cache(seq, tmp_path):
    cache = tmp_path / "cache"
    cfg = config.load(None, {"frames": {"max_points": 128}, "place_recognition": {"name": "loops"}})
    fresh = run(seq, cache, cfg).topology
    cached = run(seq, cache, cfg).topology
    assert fresh.closures == fresh.log[0]["closures"]
    assert fresh.loop_closed == (fresh.poses is not None and fresh.closures > 0)
    assert (cached.loop_closed, cached.closures) == (fresh.loop_closed, fresh.closures)


def test_repaired_steps_survive_the_cache_and_default_to_none_when_missing(tmp_path):
    groups, edges = np.array([[1], [0]]), np.array([[0, 1]])
    store.put(tmp_path, "topology-x", {"groups": groups, "edges": edges},
              {"edge_kind": ["temporal"], "log": [{}], "repaired_steps": [3, 7]})
    assert store.topology_from(store.get(tmp_path, "topology-x")).repaired_steps == (3, 7)
    store.put(tmp_path, "topology-old", {"groups": groups, "edges": edges}, {"edge_kind": ["temporal"], "log": [{}]})
    assert store.topology_from(store.get(tmp_path, "topology-old")).repaired_steps == ()
