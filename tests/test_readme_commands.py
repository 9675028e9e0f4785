"""Every shell command of README.md and docs/getting-started.md, as written: a renamed flag or a moved file fails
here. Commands on the built-in sample or on ``../shared/data`` run (exit 0); those on data that takes minutes
(real depth sequences, a whole Freiburg log) and those on the reader's own files (``lego_loam.txt``, ``my_*``) are
parsed by dm2's own command line (every option and value checked, nothing run); the set-up commands are what
``.ci/run`` itself runs."""

from __future__ import annotations

import os
import re
import shlex
import shutil
from pathlib import Path

import click
import pytest
from click.testing import CliRunner
from optim_cases import one_thread

from dm2_backend.cli.main import cli

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", REPO / "docs" / "getting-started.md"]
#: inputs that take minutes: parsed here, run by ``benchmarks/run.py`` (the depth and freiburg sets)
HEAVY = ("depth3d/redkitchen", "carmen/aces.clf")
#: options whose value is written, not read
OUTPUTS = {"--out", "-o", "--plot", "--profile", "--json", "--csv", "--markdown", "--save-evo"}
#: what .ci/run and the first README lines do themselves
SETUP = ("bash", "source", "python", "mkdocs")


def shell_lines(doc: Path) -> list[str]:
    """The commands of a document's ```bash blocks, continuation lines joined, in order."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", doc.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip() and not line.strip().startswith("#"):
                out.append(line.strip())
    return out


def steps(doc: Path) -> list[tuple[str, list[str]]]:
    """Each command as (its text, its words with the document's shell variables expanded); ``&&`` splits."""
    variables: dict[str, str] = {}
    out = []
    for line in shell_lines(doc):
        words = shlex.split(line, comments=True)
        if len(words) == 1 and re.fullmatch(r"[A-Z_]+=\S+", words[0]):
            name, value = words[0].split("=", 1)
            variables[name] = value
            continue
        command: list[str] = []
        for word in words + ["&&"]:
            if word == "&&":
                out.append((line, command))
                command = []
            elif not command and re.fullmatch(r"[A-Z_]+=\S*", word):
                continue  # the environment of this one command (``NAME=value program ...``)
            else:
                command.append(re.sub(r"\$([A-Z_]+)", lambda m: variables[m.group(1)], word))
    return out


CASES = [(doc, text, words) for doc in DOCS if doc.is_file() for text, words in steps(doc)]


def _inputs(words: list[str]) -> list[str]:
    """The words that name a file or folder to read."""
    out = []
    for before, word in zip([""] + words[:-1], words, strict=True):
        if before in OUTPUTS or word.startswith("-") or before in ("--topic", "--gt-topic", "--est-topic"):
            continue
        if "/" in word or re.search(r"\.(txt|bag|g2o|csv|json|bz2|gz|tum)$", word):
            out.append(word)
    return out


def _parse(words: list[str]) -> None:
    """dm2's command line takes ``words`` (every option and value converted), nothing run."""
    command = cli.get_command(click.Context(cli), words[1])
    assert command is not None, f"no command {words[1]}"
    with command.make_context(words[1], list(words[2:]), obj={}):
        pass


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """A folder beside a link to ``../shared``, as the repository root is: the README's paths resolve."""
    root = tmp_path_factory.mktemp("readme")
    (root / "repo").mkdir()
    shared = REPO.parent / "shared"
    if shared.exists():
        (root / "shared").symlink_to(shared)
    return root / "repo"


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    yield from one_thread()


def test_the_documents_have_commands():
    assert len(CASES) >= 10 and any(w[:2] == ["dm2", "refine"] for _, _, w in CASES)


@pytest.mark.parametrize(("doc", "text", "words"), CASES, ids=[f"{d.name}:{t[:60]}" for d, t, _ in CASES])
def test_command(doc, text, words, workdir, monkeypatch):
    monkeypatch.chdir(workdir)
    if words[0] in SETUP:
        target = next((w for w in words[1:] if "/" in w or w.endswith(".py")), None)
        if target and not words[1].startswith("-"):
            assert (REPO / target).exists() or shutil.which(target), f"{doc.name}: {target} not found"
        pytest.skip("set-up and test commands: .ci/run runs them")
    if words[0] != "dm2":
        assert (Path(os.sys.executable).parent / words[0]).exists(), f"{doc.name}: {words[0]} is not installed"
        pytest.skip(f"{words[0]}: installed; run on the reader's files")
    inputs = _inputs(words)
    shared = [w for w in inputs if w.startswith("../shared/")]
    if any(not Path(w).exists() for w in shared):
        pytest.skip(f"{next(w for w in shared if not Path(w).exists())} absent")
    own_data = any(not Path(w).exists() for w in inputs)
    if own_data or any(h in " ".join(words) for h in HEAVY):
        try:
            _parse(words)
        except click.ClickException as exc:
            pytest.fail(f"{doc.name}: {text}: {exc.format_message()}")
        return
    result = CliRunner().invoke(cli, words[1:], obj={})
    assert result.exit_code == 0, f"{doc.name}: {text}\n{result.output}"
    if words[1] in ("refine", "baseline"):
        out = words[words.index("--out") + 1]
        assert (Path(out) / "report.json").is_file()
