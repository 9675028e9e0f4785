"""A stateful test that tries to make dm2 lose a user's bytes (shared by the suite and ``benchmarks/fuzz_files.py``).

A folder fills with the user's things (files, folders, links to a file outside, FIFOs, stale temporary names,
crafted markers and locks, some named like dm2's outputs and checkpoints); real dm2 commands (``simulate``,
``baseline gtsam --graph``) run into it, with and without ``--force``, some failing, interrupted or intruded on
at a random write (another program writing into the folder meanwhile); the user edits what dm2 wrote. After every
step, every entry the user made or touched, and the file outside, hold exactly what they held.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from click.testing import CliRunner
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from dm2_backend.cli.main import cli
from dm2_backend.runtime import atomic

#: names the user's things take: plain, dm2's outputs and checkpoints, temporaries of dead processes
NAMES = ("notes.txt", "photos", "report.json", "poses.txt", "velodyne", "checkpoint-dense.npz", "checkpoint.pt",
         "info.json", ".tmp-999999-photos", "config.yaml")
KINDS = ("file", "folder", "link", "fifo")
GRAPH = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nEDGE_SE2 0 1 1 0 0.1 1 0 0 1 0 1\n"


class Stop(Exception):
    """A failure injected at a write."""


def _state(path: Path) -> tuple | None:
    """What an entry holds, links not followed: kind and content (a folder: its entries' states)."""
    try:
        st_ = path.lstat()
    except FileNotFoundError:
        return None
    if path.is_symlink():
        return ("link", os.readlink(path))
    if path.is_dir():
        return ("folder", tuple(sorted((p.name, _state(p)) for p in path.iterdir())))
    if path.is_file():
        return ("file", path.read_bytes())
    return ("other", st_.st_mode)


class FileSafety(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.tmp = Path(tempfile.mkdtemp(prefix="dm2-files-"))
        self.out = self.tmp / "out"
        self.outside = self.tmp / "victim.txt"
        self.outside.write_text("keep me")
        self.graph = self.tmp / "graph.g2o"
        self.graph.write_text(GRAPH)
        self.users: dict[str, tuple | None] = {}
        self.runs = 0
        self.crafted = False  # a crafted marker or lock: dm2 may refuse the folder from then on

    def teardown(self) -> None:
        import shutil

        shutil.rmtree(self.tmp, ignore_errors=True)

    @rule(name=st.sampled_from(NAMES), kind=st.sampled_from(KINDS))
    def user_makes(self, name: str, kind: str) -> None:
        path = self.out / name
        self.out.mkdir(exist_ok=True)
        if path.exists() or path.is_symlink():
            return
        if kind == "file":
            path.write_bytes(os.urandom(16))
        elif kind == "folder":
            path.mkdir()
            (path / "mine.bin").write_bytes(os.urandom(8))
        elif kind == "link":
            path.symlink_to(self.outside)
        else:
            os.mkfifo(path)
        self.users[name] = _state(path)

    @rule(data=st.data())
    def user_edits_what_dm2_wrote(self, data) -> None:
        if not self.out.is_dir():
            return
        theirs = sorted(p.name for p in self.out.iterdir() if p.is_file() and not p.is_symlink()
                        and p.name not in self.users and not p.name.startswith("."))
        if not theirs:
            return
        name = data.draw(st.sampled_from(theirs))
        with open(self.out / name, "ab") as fh:
            fh.write(b"\n# edited by the user\n")
        self.users[name] = _state(self.out / name)

    @rule(kind=st.sampled_from(("marker listing a user's thing", "marker with identities", "lock link")))
    def user_crafts(self, kind: str) -> None:
        self.out.mkdir(exist_ok=True)
        self.crafted = True
        if kind == "lock link":
            if not (self.out / ".dm2-lock").exists() and not (self.out / ".dm2-lock").is_symlink():
                (self.out / ".dm2-lock").symlink_to(self.outside)
            return
        listed = sorted(self.users) or ["notes.txt"]
        doc = {"command": "simulate", "files": listed}
        if kind == "marker with identities":
            doc["identity"] = {name: "tree:1:0123456789abcdef0123" for name in listed}
        marker = self.out / ".dm2-run.json"
        if ".dm2-run.json" not in self.users and not marker.is_symlink():
            marker.write_text(json.dumps(doc))

    @rule(command=st.sampled_from(("simulate", "baseline")), force=st.booleans(),
          event=st.sampled_from((None, "fail", "interrupt", "intruder")), at=st.integers(1, 6), late=st.booleans(),
          intruder=st.sampled_from(("intruder.txt", "report.json", "info.json", "poses.txt", "velodyne")))
    def dm2_runs(self, command: str, force: bool, event: str | None, at: int, late: bool, intruder: str) -> None:
        """``at``: the write (counted as each is about to be renamed into place) at which ``event`` happens;
        ``late``: after the run folder has recorded that write (else before); ``intruder``: the name another
        program writes."""
        self.runs += 1
        clean = force and event is None and not self.users and not self.crafted
        args = (["simulate", "-n", "3"] if command == "simulate" else ["baseline", "gtsam", "--graph", str(self.graph)])
        args += ["--out", str(self.out), "-q"] + (["--force"] if force else [])
        count = [0]

        def hook(path: Path, temporary: Path) -> None:
            if late and atomic._finished[-1] is not hook:  # behind the run folder's own record of the write
                atomic._finished.remove(hook)
                atomic._finished.append(hook)
            count[0] += 1
            if count[0] != at:
                return
            if event == "fail":
                raise Stop
            if event == "interrupt":
                raise KeyboardInterrupt
            if event == "intruder" and not (self.out / intruder).exists():
                (self.out / intruder).write_text("another program")
                self.users[intruder] = _state(self.out / intruder)

        atomic._finished.append(hook)
        try:
            result = CliRunner().invoke(cli, args, obj={})
        except KeyboardInterrupt:
            result = None
        finally:
            atomic._finished.remove(hook)
        if result is not None and result.exception is not None and not isinstance(
                result.exception, (SystemExit, Stop, KeyboardInterrupt)):
            raise result.exception
        if clean:  # only dm2's own, unchanged outputs in the folder: --force replaces them
            assert result is not None and result.exit_code == 0, result.output

    @invariant()
    def nothing_of_the_users_changed(self) -> None:
        assert self.outside.read_text() == "keep me"
        for name, state in self.users.items():
            assert _state(self.out / name) == state, name
