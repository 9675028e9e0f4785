"""dm2 never writes through, deletes or overwrites what it did not create: a lock that is a link, a cache folder
that is not one, an output folder that holds or lies inside the run's own inputs. Each is one line, exit 2, and
every byte of the user's files unchanged."""

from __future__ import annotations

from pathlib import Path

import pytest
from shared_helpers import one_line_error, run

from dm2_backend.prepare.store import CACHE_MARKER


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("safety") / "seq"
    result = run("simulate", "--frames", "12", "--planar", "-o", str(out), "-q")
    assert result.exit_code == 0, result.output
    return out


def refine(seq: Path, *extra: str):
    return run("refine", "--scans", str(seq / "velodyne"), "--poses", str(seq / "warm_start.txt"), "--times",
               str(seq / "times.txt"), "-q", *extra)


@pytest.mark.parametrize("empty", [False, True])
def test_a_lock_that_is_a_link_is_refused_and_nothing_written_through_it(seq, tmp_path, empty):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    out = tmp_path / "R"
    out.mkdir()
    if not empty:
        (out / "x").write_text("mine")
    (out / ".dm2-lock").symlink_to(victim)
    one_line_error(refine(seq, "--out", str(out)), ".dm2-lock", "link")
    assert victim.read_text() == "keep" and (out / ".dm2-lock").is_symlink()


def test_cache_clear_refuses_a_folder_that_is_not_a_dm2_cache(tmp_path):
    home = tmp_path / "H"
    (home / "Documents").mkdir(parents=True)
    (home / "Documents" / "a.txt").write_text("mine")
    one_line_error(run("cache", "clear", "--cache-dir", str(home)), str(home), "not a dm2 cache")
    assert (home / "Documents" / "a.txt").read_text() == "mine"


def test_cache_clear_removes_only_the_entries_dm2_wrote(seq, tmp_path):
    cache = tmp_path / "C"
    assert refine(seq, "--out", str(tmp_path / "run"), "--cache-dir", str(cache)).exit_code == 0
    assert (cache / CACHE_MARKER).is_file()
    (cache / "photos").mkdir()
    (cache / "photos" / "p.jpg").write_bytes(b"\xff\xd8")
    result = run("cache", "clear", "--cache-dir", str(cache))
    assert result.exit_code == 0 and "removed 4 entries" in result.output, result.output
    assert sorted(p.name for p in cache.iterdir()) == [CACHE_MARKER, "photos"]
    assert (cache / "photos" / "p.jpg").read_bytes() == b"\xff\xd8"


@pytest.mark.parametrize("where", ["the sequence", "inside the scans", "the root"])
def test_the_output_never_holds_or_lies_inside_the_inputs(seq, where):
    before = {p: p.read_bytes() for p in seq.rglob("*") if p.is_file()}
    out = {"the sequence": seq, "inside the scans": seq / "velodyne" / "run", "the root": Path("/")}[where]
    result = refine(seq, "--out", str(out), "--force")
    one_line_error(result, str(out))
    assert {p: p.read_bytes() for p in seq.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize("kind", ["a file of the user's inside", "a file as the folder"])
def test_eval_profile_never_replaces_a_file(seq, tmp_path, kind):
    folder = tmp_path / "profile"
    if kind == "a file as the folder":
        folder.write_text("mine")
        victim = folder
    else:
        folder.mkdir()
        victim = folder / "consistency.json"
        victim.write_text("mine")
    result = run("eval", "--scans", seq / "velodyne", "--scans-times", seq / "times.txt", "--est",
                 seq / "warm_start.txt", "--est-times", seq / "times.txt", "--profile", folder)
    one_line_error(result, str(victim))
    assert victim.read_text() == "mine"


def _dense_checkpoint(path: Path, members: dict[str, bytes], compress: bool = True) -> None:
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)


def _npy(array) -> bytes:
    import io

    import numpy as np

    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


@pytest.mark.parametrize("craft", ["a member that inflates", "a header claiming 10^11 frames", "another member"])
def test_a_crafted_dense_checkpoint_is_refused_before_it_is_decoded(tmp_path, craft):
    """A few kilobytes that would decompress to gigabytes, or an array header claiming any size: one line naming
    the file, memory untouched."""
    import numpy as np

    from dm2_backend.optim import dense_checkpoint
    from dm2_backend.runtime.errors import InputError

    start = np.tile(np.eye(4), (5, 1, 1))
    good = {"poses.npy": _npy(start), "start.npy": _npy(start), "meta.npy": _npy(np.array("{}"))}
    if craft == "a member that inflates":
        good["poses.npy"] = _npy(start)[:128] + b"\0" * (64 << 20)  # 64 MiB of zeros deflate to about 64 KiB
    elif craft == "a header claiming 10^11 frames":
        header = _npy(np.zeros((1, 4, 4)))
        good["poses.npy"] = header.replace(b"(1, 4, 4)", b"(100000000000, 4, 4)")
    else:
        good["extra.npy"] = _npy(start)
    path = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    _dense_checkpoint(path, good)
    assert path.stat().st_size < 1 << 20
    with pytest.raises(InputError) as info:
        dense_checkpoint.load(path, start, rounds=30)
    assert info.value.source == str(path) and "not a dm2 dense-stage checkpoint" in info.value.message


@pytest.mark.parametrize("craft", ["rotations scaled by 1000", "NaN poses", "a negative epoch", "other frames"])
def test_a_crafted_optimiser_checkpoint_is_refused(tmp_path, craft):
    import numpy as np
    import torch

    from dm2_backend.optim.checkpoint import load_checkpoint, plain_state
    from dm2_backend.runtime.errors import InputError

    poses = np.tile(np.eye(4), (6, 1, 1))
    epoch = 0
    if craft == "rotations scaled by 1000":
        poses[:, :3, :3] *= 1000
    elif craft == "NaN poses":
        poses[2, 0, 3] = np.nan
    elif craft == "a negative epoch":
        epoch = -1
    else:
        poses = poses[:4]
    path = tmp_path / "checkpoint.pt"
    torch.save(plain_state({"best": {"poses": poses}, "history": [], "epoch": epoch}), path)
    with pytest.raises(InputError, match="not a checkpoint of this run") as info:
        load_checkpoint(path, "cpu", frames=6)
    assert info.value.source == str(path)


def test_a_writer_cleans_its_own_leftovers_only(tmp_path):
    """The temporaries a killed writer of ``out`` left (its file, the old output it set aside, a work folder) go;
    ``.tmp-<pid>-outdoor/`` of the user's stays."""
    from dm2_backend.runtime.atomic import atomic_write

    dead = 2**22 + 4321
    for name in ("out", "old-out", "out-work-x1"):
        (tmp_path / f".tmp-{dead}-{name}").write_text("left")
    (tmp_path / f".tmp-{dead}-outdoor").mkdir()
    with atomic_write(tmp_path / "out") as fh:
        fh.write("ok")
    assert sorted(p.name for p in tmp_path.iterdir()) == [f".tmp-{dead}-outdoor", "out"]


def test_a_yaml_key_that_is_a_list_is_one_line(tmp_path):
    from dm2_backend import config
    from dm2_backend.runtime.errors import InputError

    path = tmp_path / "c.yaml"
    path.write_text("? [a, b]\n: 1\n")
    with pytest.raises(InputError) as info:
        config.read_yaml(path)
    assert info.value.source == str(path)


def test_a_dense_checkpoint_with_a_corrupt_member_or_a_reflection_is_one_line(tmp_path):
    import numpy as np

    from dm2_backend.optim import dense_checkpoint
    from dm2_backend.runtime.errors import InputError

    start = np.tile(np.eye(4), (5, 1, 1))
    mirrored = start.copy()
    mirrored[:, 0, 0] = -1.0  # orthonormal, determinant -1
    for members in ({"poses.npy": _npy(mirrored), "start.npy": _npy(start), "meta.npy": _npy(np.array("{}"))},):
        path = tmp_path / "mirror.npz"
        _dense_checkpoint(path, members)
        with pytest.raises(InputError):
            dense_checkpoint.load(path, start, rounds=30)
    good = tmp_path / "good.npz"
    _dense_checkpoint(good, {"poses.npy": _npy(start), "start.npy": _npy(start), "meta.npy": _npy(np.array("{}"))})
    data = bytearray(good.read_bytes())
    data[60:90] = b"\xff" * 30  # inside the first member's deflated bytes
    bad = tmp_path / dense_checkpoint.DENSE_CHECKPOINT
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError) as info:
        dense_checkpoint.load(bad, start, rounds=30)
    assert info.value.source == str(bad)


def test_baseline_graph_never_writes_over_its_graph_or_the_root(tmp_path):
    from shared_helpers import DATA, need

    graph = need(DATA / "posegraphs" / "intel.g2o")
    copy = tmp_path / "g" / "intel.g2o"
    copy.parent.mkdir()
    copy.write_bytes(graph.read_bytes())
    one_line_error(run("baseline", "gtsam", "--graph", copy, "--out", copy.parent, "--force"), str(copy.parent))
    one_line_error(run("baseline", "gtsam", "--graph", copy, "--out", "/"), "root or home")
    assert copy.read_bytes() == graph.read_bytes()


@pytest.mark.parametrize("craft", ["a pickle", "rotations scaled by 1000", "NaN poses", "a header claiming 10^11 poses",
                                   "one pose as 3x3"])
def test_dm2_map_refuses_a_crafted_poses_file_in_one_line(seq, tmp_path, craft):
    """A run folder someone sent: its ``poses.npy`` is read like any input (bounded, numeric, finite, rigid)."""
    import numpy as np

    out = tmp_path / "R"
    assert refine(seq, "--out", str(out), "--no-cache").exit_code == 0
    poses = np.load(out / "poses.npy")
    target = out / "poses.npy"
    if craft == "a pickle":
        np.save(target, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    elif craft == "rotations scaled by 1000":
        poses[:, :3, :3] *= 1000.0
        np.save(target, poses)
    elif craft == "NaN poses":
        poses[3] = np.nan
        np.save(target, poses)
    elif craft == "a header claiming 10^11 poses":
        data = _npy(poses)
        target.write_bytes(data.replace(f"({len(poses)}, 4, 4)".encode(), b"(100000000000, 4, 4)", 1))
    else:
        np.save(target, poses[:, :3, :3])
    before = {p: p.read_bytes() for p in out.iterdir() if p.is_file()}
    why = {"a pickle": "numeric", "rotations scaled by 1000": "rotation", "NaN poses": "NaN",
           "a header claiming 10^11 poses": "declares", "one pose as 3x3": "shape"}[craft]
    one_line_error(run("map", str(out), "--scans", str(seq / "velodyne"), "--times", str(seq / "times.txt")),
                   "poses.npy", why)
    assert {p: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


@pytest.mark.parametrize("which", ["checkpoint.pt", "checkpoint-dense.npz"])
def test_a_crafted_checkpoint_is_refused_before_the_preparation(seq, tmp_path, monkeypatch, which):
    """``--resume`` reads the run folder's checkpoints before the long work: a damaged one is one line and the
    preparation never starts."""
    import numpy as np
    import torch

    from dm2_backend.optim.checkpoint import plain_state
    from dm2_backend.pipeline import parallel

    out = tmp_path / "R"
    assert refine(seq, "--out", str(out), "--no-cache").exit_code == 0
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, :3, :3] *= 1000  # not rigid motions
    if which == "checkpoint.pt":
        torch.save(plain_state({"best": {"poses": poses}, "history": [], "epoch": 0}), out / which)
    else:
        _dense_checkpoint(out / which, {"poses.npy": _npy(poses), "start.npy": _npy(np.tile(np.eye(4), (12, 1, 1))),
                                        "meta.npy": _npy(np.array('{"rounds_done": 1, "damping": 1e-4, '
                                                                  '"history": [], "stopped": null}'))})

    def never(*args, **kwargs):
        raise AssertionError("the preparation started")

    monkeypatch.setattr(parallel, "prepare_once", never)
    one_line_error(refine(seq, "--out", str(out), "--no-cache", "--resume"), which, "rigid")
