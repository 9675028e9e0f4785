"""A run folder's entries are dm2's by content: what others write meanwhile, and what changed since, stay."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dm2_backend.pipeline.ownership import Written, identity, tree_identity
from dm2_backend.pipeline.run_folder import MARKER, adding_to, open_folder, run_folder
from dm2_backend.runtime.atomic import atomic_path, atomic_write
from dm2_backend.runtime.errors import InputError


def _write(path: Path, data: bytes = b"dm2") -> None:
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def _photos(out: Path) -> Path:
    """Another program's folder, created in ``out`` while a run writes there."""
    (out / "photos").mkdir()
    (out / "photos" / "a.jpg").write_bytes(b"jpeg")
    return out / "photos"


def test_identity_tells_content_links_and_trees(tmp_path):
    f = tmp_path / "f"
    f.write_bytes(b"abc")
    same = identity(f)
    f.write_bytes(b"abd")  # same size, other content
    assert identity(f) != same and identity(f).startswith("3:")
    link = tmp_path / "link"
    link.symlink_to(f)
    assert identity(link) is None
    tree = tmp_path / "tree"
    (tree / "sub").mkdir(parents=True)
    (tree / "sub" / "x").write_bytes(b"x")
    before = identity(tree)
    assert before.startswith("tree:1:")
    (tree / "y").write_bytes(b"")
    assert identity(tree) != before
    (tree / "y").unlink()
    assert identity(tree) == before
    (tree / "sub" / "l").symlink_to(f)
    assert identity(tree) is None


def test_a_folder_written_file_by_file_is_identified_as_a_walk_sees_it(tmp_path):
    written = Written(tmp_path)
    for k in range(3):
        _write(tmp_path / "velodyne" / f"{k:06d}.bin", bytes([k]) * 10)
        written.placed(tmp_path / "velodyne" / f"{k:06d}.bin")
    _write(tmp_path / "report.json", b"{}")
    written.placed(tmp_path / "report.json")
    ids = written.identities()
    assert ids["velodyne"] == identity(tmp_path / "velodyne") == tree_identity(written.parts_of("velodyne"))
    assert ids["report.json"] == identity(tmp_path / "report.json")


def test_what_another_program_writes_during_a_run_is_never_the_runs(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "report.json")
        photos = _photos(out)
    marker = json.loads((out / MARKER).read_text())
    assert marker["files"] == ["report.json"] and set(marker["identity"]) == {"report.json"}
    open_folder(out, "refine", force=True).release()
    assert not (out / "report.json").exists()
    assert (photos / "a.jpg").read_bytes() == b"jpeg"


@pytest.mark.parametrize("ending", [RuntimeError, KeyboardInterrupt])
def test_a_failed_or_interrupted_run_removes_only_what_it_wrote(tmp_path, ending):
    out = tmp_path / "new"
    with pytest.raises(ending), run_folder(out, "baseline"):
        _write(out / "poses_tum.txt")
        _write(out / "velodyne" / "000000.bin")
        (out / "velodyne" / "yours.txt").write_text("kept")
        _photos(out)
        raise ending
    assert sorted(p.name for p in out.iterdir()) == ["photos", "velodyne"]
    assert [p.name for p in (out / "velodyne").iterdir()] == ["yours.txt"]
    assert (out / "photos" / "a.jpg").read_bytes() == b"jpeg"


def test_a_folder_the_run_made_is_removed_only_when_empty(tmp_path):
    out = tmp_path / "new"
    with pytest.raises(RuntimeError), run_folder(out, "baseline"):
        with atomic_path(out / "prior", folder=True) as tmp:
            tmp.mkdir()
            (tmp / "init_pose.npy").write_bytes(b"npy")
        raise RuntimeError
    assert not out.exists()


def test_an_output_changed_since_the_run_is_left_and_named(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "poses_tum.txt", b"0 0 0 0 0 0 0 1\n")
        _write(out / "report.json")
    (out / "poses_tum.txt").write_bytes(b"0 0 0 0 0 0 0 1\n# my notes\n")
    marker = (out / MARKER).read_bytes()
    with pytest.raises(InputError, match="no longer holds what it wrote") as err:
        open_folder(out, "refine", force=True)
    assert "poses_tum.txt" in str(err.value)
    # refused before anything was removed
    assert (out / "report.json").exists() and (out / MARKER).read_bytes() == marker
    assert (out / "poses_tum.txt").read_bytes().endswith(b"# my notes\n")
    with pytest.raises(InputError), adding_to(out):  # dm2 map would replace it: refused as well
        _write(out / "poses_tum.txt")
    assert (out / "poses_tum.txt").read_bytes().endswith(b"# my notes\n")


def test_a_users_folder_named_like_a_checkpoint_is_never_removed(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "report.json")
    (out / "checkpoint-dense.npz").mkdir()
    (out / "checkpoint-dense.npz" / "mine.txt").write_text("mine")
    with pytest.raises(InputError, match="not listed"):
        open_folder(out, "refine", force=True)
    assert (out / "checkpoint-dense.npz" / "mine.txt").read_text() == "mine"


def test_files_added_by_dm2_map_are_identified_and_replaceable(tmp_path):
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "map.ply", b"old")
    with adding_to(out):
        _write(out / "map.ply", b"new map")  # dm2's own, unchanged since: replaced
        _write(out / "map.pgm", b"P5")
    marker = json.loads((out / MARKER).read_text())
    assert marker["identity"]["map.ply"] == identity(out / "map.ply")
    assert marker["identity"]["map.pgm"] == identity(out / "map.pgm")
    open_folder(out, "refine", force=True).release()
    assert not (out / "map.ply").exists() and not (out / "map.pgm").exists()


@pytest.mark.parametrize("ids", [["report.json"], {"report.json": 3}, {"../x": "1:ab"}, {"report.json": "x" * 65}])
def test_a_marker_with_crafted_identities_is_refused_whole(tmp_path, ids):
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "report.json")
    marker = json.loads((out / MARKER).read_text())
    (out / MARKER).write_text(json.dumps({**marker, "identity": ids}))
    with pytest.raises(InputError, match="not a dm2 run marker"):
        open_folder(out, "refine", force=True)
    assert (out / "report.json").exists()


def test_a_crafted_marker_cannot_name_a_users_file_into_removal(tmp_path):
    out = tmp_path / "home"
    out.mkdir()
    (out / "Documents").mkdir()
    (out / "Documents" / "cv.txt").write_text("mine")
    (out / MARKER).write_text(json.dumps({"command": "refine", "files": ["Documents"],
                                          "identity": {"Documents": "tree:1:0123456789abcdef0123"}}))
    open_folder(out, "refine", force=True).release()
    assert (out / "Documents" / "cv.txt").read_text() == "mine"


def test_a_marker_without_identities_owns_nothing(tmp_path):
    """A name alone (a crafted marker, or one of a dm2 that recorded no identities) never gets a file removed."""
    out = tmp_path / "run"
    with run_folder(out, "refine"):
        _write(out / "report.json")
    marker = json.loads((out / MARKER).read_text())
    del marker["identity"]
    (out / MARKER).write_text(json.dumps(marker))
    with pytest.raises(InputError, match="no longer holds what it wrote"):
        open_folder(out, "refine", force=True)
    with pytest.raises(InputError), adding_to(out):
        _write(out / "report.json")
    assert (out / "report.json").read_text() == "dm2"


def test_resume_never_replaces_an_output_edited_since(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt), run_folder(out, "refine", fp={"inputs": {"scans": "s"}}):
        _write(out / "report.json", b"{}")
        _write(out / "checkpoint.pt", b"state")
        raise KeyboardInterrupt
    folder = open_folder(out, "refine", resume=True, fp={"inputs": {"scans": "s"}})
    assert {"report.json", "checkpoint.pt"} <= set(folder.inherited)
    folder.release()
    (out / "report.json").write_bytes(b'{"mine": 1}')
    with pytest.raises(InputError, match="no longer holds what it wrote"):
        open_folder(out, "refine", resume=True, fp={"inputs": {"scans": "s"}})
    assert (out / "report.json").read_bytes() == b'{"mine": 1}'


def test_an_output_another_program_writes_during_the_run_is_not_replaced(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(InputError, match="appeared while this run wrote"), run_folder(out, "baseline"):
        _write(out / "poses_tum.txt")
        (out / "report.json").write_text("another program's")
        _write(out / "report.json")
    assert (out / "report.json").read_text() == "another program's"
    assert not (out / "poses_tum.txt").exists()  # the failed run removed its own
    with run_folder(tmp_path / "again", "baseline"):  # a file the run itself wrote is replaced as before
        _write(tmp_path / "again" / "checkpoint.pt", b"1")
        _write(tmp_path / "again" / "checkpoint.pt", b"2")
    assert (tmp_path / "again" / "checkpoint.pt").read_bytes() == b"2"


def test_a_name_that_appears_while_dm2_writes_it_is_never_replaced(tmp_path):
    target = tmp_path / "report.json"
    with pytest.raises(InputError, match="appeared while it was written"), atomic_write(target) as fh:
        fh.write("dm2's")
        target.write_text("another program's")  # created after the write began, before the rename
    assert target.read_text() == "another program's" and not list(tmp_path.glob(".tmp-*"))
    with atomic_write(target) as fh:  # a name that is there when the write begins is replaced, as before
        fh.write("dm2's")
    assert target.read_text() == "dm2's"
