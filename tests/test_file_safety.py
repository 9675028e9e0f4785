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
