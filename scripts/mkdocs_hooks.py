"""MkDocs hooks (``hooks:`` in mkdocs.yml): the generated pages are written before every build, and the nav's
``Decisions`` section lists every record in ``docs/decisions/``, so that ``mkdocs build --strict`` alone builds
the whole site from the sources."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gen_docs  # noqa: E402  (a sibling script, not a package)

DECISIONS = "Decisions"


def on_config(config, **kwargs):
    """Expand the nav entry ``Decisions: decisions/index.md`` into the index and every record, by number."""
    docs = Path(config["docs_dir"])
    for i, item in enumerate(config["nav"] or []):
        if isinstance(item, dict) and item.get(DECISIONS) == "decisions/index.md":
            records = [{title: f"decisions/{name}"} for name, title in gen_docs.decision_records(docs / "decisions")]
            config["nav"][i] = {DECISIONS: ["decisions/index.md", *records]}
    return config


def on_pre_build(config, **kwargs):
    gen_docs.generate(Path(config["docs_dir"]))
