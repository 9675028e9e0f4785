"""The documentation site: the generated pages (scripts/gen_docs.py) cover the whole configuration and command line,
``mkdocs build --strict`` passes (no warning: every page in the nav, no broken link or anchor), every ``dm2``
command shown in a page names options that exist, and every relative link in README.md and docs/ points to a file
that exists."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote

import click
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _gen_docs():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "scripts" / "gen_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gen_docs = _gen_docs()


@pytest.fixture(scope="module")
def generated() -> dict[str, str]:
    """The generated pages, written into docs/ (ignored by git), by page."""
    gen_docs.generate(DOCS)
    return {rel: (DOCS / rel).read_text(encoding="utf-8") for rel in gen_docs.GENERATORS}


def test_mkdocs_build_strict(generated, tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is in the dev extra: bash scripts/setup.sh --dev")
    pytest.importorskip("material", reason="mkdocs-material is in the dev extra: bash scripts/setup.sh --dev")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    assert "WARNING" not in output, output
    for page in ("index.html", "reference/config/index.html", "reference/cli/index.html", "results/index.html",
                 "decisions/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    for name, _ in gen_docs.decision_records():  # every record is a page of the site
        assert (tmp_path / "site" / "decisions" / Path(name).stem / "index.html").is_file(), name


def test_config_page_lists_every_field(generated):
    from dm2_backend.config.schema import PLUGIN_GROUPS, RunConfig
    from dm2_backend.plugins.registry import discover

    page = generated["reference/config.md"]
    fields = gen_docs.config_fields()
    assert "optimiser.dense_voxel" in fields and "frames.max_points" in fields
    assert len(fields) > len(RunConfig.model_fields)
    missing = [f for f in fields if f"| `{f}` |" not in page]
    assert not missing, f"config fields missing from reference/config.md: {missing}"
    # every field and plugin option has a description (a pydantic description, or a `#:` comment above it)
    undocumented = [line for line in page.splitlines() if "| – |" in line]
    assert not undocumented, "undocumented rows in reference/config.md:\n" + "\n".join(undocumented)
    for section, group in PLUGIN_GROUPS.items():
        for name in discover(group):
            assert f"#### {section}: {name}\n" in page, f"plugin {section}: {name} missing"


def _sections(page: str) -> dict[str, str]:
    """``## heading`` -> its text, for a generated page."""
    parts = re.split(r"^## (.+)$", page, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))


def test_cli_page_lists_every_command_and_option(generated):
    sections = _sections(generated["reference/cli.md"])
    commands = gen_docs.commands()
    assert {"dm2", "dm2 refine", "dm2 eval", "dm2 cache", "dm2 cache info"} <= {path for path, _ in commands}
    for path, cmd in commands:
        assert path in sections, f"{path} missing from reference/cli.md"
        ctx = click.Context(cmd, info_name=path)
        help_option = cmd.get_help_option(ctx)
        for param in cmd.get_params(ctx):
            if param is help_option or getattr(param, "hidden", False):
                continue
            names = param.opts if isinstance(param, click.Option) else [param.human_readable_name]
            for name in names:
                assert f"`{name}`" in sections[path], f"{path}: {name} missing from reference/cli.md"


# ------------------------------------------------------------------------------------------ links


CODE_BLOCK = re.compile(r"^( {0,3}|\t*)(```|~~~).*?^\1\2[^\n]*$", re.M | re.S)
CODE_SPAN = re.compile(r"(`+)(?!`).*?(?<!`)\1(?!`)", re.S)
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*(?:<([^>\n]*)>|([^)\s]*))(?:\s+[\"'(][^)]*)?\)")
REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)
HTML_LINK = re.compile(r"<(?:a|img)\b[^>]*?\b(?:href|src)\s*=\s*[\"']([^\"']+)[\"']", re.I)


def link_targets(text: str) -> list[str]:
    """The link and image targets of a Markdown text, outside code blocks and code spans."""
    text = CODE_SPAN.sub("", CODE_BLOCK.sub("", text))
    inline = [angled or plain for angled, plain in INLINE_LINK.findall(text)]
    return [*inline, *REFERENCE.findall(text), *HTML_LINK.findall(text)]


def broken_links(path: Path) -> list[str]:
    """Relative links of ``path`` whose file does not exist (anchors, URLs and absolute paths are not checked)."""
    out = []
    for target in link_targets(path.read_text(encoding="utf-8")):
        target = unquote(target.split("#", 1)[0].split("?", 1)[0])
        if not target or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith(("/", "//")):
            continue
        if not (path.parent / target).exists():
            out.append(f"{path.relative_to(ROOT)}: {target}")
    return out


def test_link_targets_parser():
    text = ("[a](x.md) ![i](img/p.png \"t\") [b](<y z.md>) [c](https://e.org/x) [d](#anchor) `[e](no.md)`\n"
            "```bash\n[f](no2.md)\n```\n[g]: ref.md\n<img src=\"h.png\"> [k](dir/k.md#part) [l `m`](l.md)\n")
    assert link_targets(text) == ["x.md", "img/p.png", "y z.md", "https://e.org/x", "#anchor", "dir/k.md#part",
                                  "l.md", "ref.md", "h.png"]


def test_relative_links_point_to_files(generated):
    pages = [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]
    broken = [b for page in pages if page.is_file() for b in broken_links(page)]
    assert not broken, "broken relative links:\n" + "\n".join(broken)


# ---------------------------------------------------------------------------- commands in the pages


def shell_commands(text: str) -> list[list[str]]:
    """The ``dm2`` command lines in the ``bash`` blocks of a page, split as the shell splits them."""
    out = []
    for block in re.findall(r"^```(?:bash|sh|shell)\n(.*?)^```", text, re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            for part in re.split(r"&&|\|\||;|\|", line):
                words = shlex.split(part, comments=True)
                while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):  # VAR=value prefixes
                    words.pop(0)
                if words and words[0] == "dm2":
                    out.append(words)
    return out


def unknown_options(words: list[str]) -> list[str]:
    """The options of a ``dm2 ...`` command line that its command does not have (and an unknown command)."""
    from dm2_backend.cli.main import cli

    cmd: click.Command = cli
    ctx = click.Context(cli, info_name="dm2")
    rest = words[1:]
    bad = []
    while isinstance(cmd, click.Group):
        while rest and rest[0].startswith("-"):  # the group's own options (dm2 --debug ...)
            bad += [w for w in [rest.pop(0)] if not _known(cmd, ctx, w)]
        if not rest:
            return bad
        name = rest.pop(0)
        sub = cmd.get_command(ctx, name)
        if sub is None:
            return [*bad, f"no command {name!r}"]
        cmd, ctx = sub, click.Context(sub, info_name=name, parent=ctx)
    for word in rest:
        if word == "--":
            break
        if word.startswith("-") and not re.match(r"^-\d", word) and not _known(cmd, ctx, word):
            bad.append(word)
    return bad


def _known(cmd: click.Command, ctx: click.Context, word: str) -> bool:
    names = {n for p in cmd.get_params(ctx) for n in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]}
    word = word.split("=", 1)[0]
    if word in names:
        return True
    # combined short flags (-as = -a -s)
    return bool(re.match(r"^-[A-Za-z]{2,}$", word)) and all(f"-{c}" in names for c in word[1:])


def test_commands_in_pages_use_existing_options():
    handwritten = [p for p in sorted(DOCS.rglob("*.md"))
                   if p.relative_to(DOCS).as_posix() not in gen_docs.GENERATORS and p.parent.name != "decisions"]
    problems, seen = [], 0
    for page in handwritten:
        for words in shell_commands(page.read_text(encoding="utf-8")):
            seen += 1
            bad = unknown_options(words)
            if bad:
                problems.append(f"{page.relative_to(ROOT)}: {shlex.join(words)}: {', '.join(bad)}")
    assert seen > 10
    assert not problems, "\n".join(problems)


def test_unknown_options_check():
    assert unknown_options(["dm2", "refine", "--scans", "s", "--out", "o", "--gt=g"]) == []
    assert unknown_options(["dm2", "eval", "gt.txt", "est.txt", "-as"]) == []
    assert unknown_options(["dm2", "--debug", "cache", "clear", "--older-than", "7d"]) == []
    assert unknown_options(["dm2", "refine", "--scan", "s"]) == ["--scan"]
    assert unknown_options(["dm2", "refien"]) == ["no command 'refien'"]
