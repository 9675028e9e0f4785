"""The YAML run configuration: defaults (``RunConfig()``), loading into one frozen :class:`RunConfig`, merging
and dumping the effective config."""

from __future__ import annotations

import copy
from pathlib import Path

import yaml

from dm2_backend.config import schema as config_schema
from dm2_backend.config.schema import RunConfig
from dm2_backend.runtime.atomic import atomic_write
from dm2_backend.runtime.errors import InputError, did_you_mean
from dm2_backend.runtime.input_files import CONFIG_MAX_BYTES, read_text_bounded


def merge(base: dict, override: dict) -> dict:
    """Recursive dict merge; ``override`` wins. Plugin ``options`` are replaced when the name changes."""
    out = copy.deepcopy(base)
    for key, value in (override or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            if "name" in value and value["name"] != out[key].get("name"):
                out[key] = {"name": value["name"], "options": {}}
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


class _NoAliasLoader(yaml.SafeLoader):
    """Safe YAML without aliases (a few nested ``*anchor`` references expand to billions of values, a "YAML
    bomb", that validation would walk and its error message print; a config has no need of them) and without a
    key given twice in one mapping (plain YAML keeps the last one silently)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "aliases (*name) are not accepted in a dm2 config: "
                                                          "write the values out", self.peek_event().start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, str | int | float | bool) and key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"the key {key!r} is given twice (YAML would keep "
                                                        "the last one silently)", key_node.start_mark)
            if isinstance(key, str | int | float | bool):
                seen.add(key)
        return super().construct_mapping(node, deep)


def read_yaml(path: Path) -> object:
    """The YAML document of a config file: a regular file of bounded size, safe-loaded without aliases."""
    if Path(path).is_dir():
        raise InputError(path, "is a folder, expected a YAML file")
    text = read_text_bounded(path, CONFIG_MAX_BYTES, "config")
    try:
        return yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506 (a SafeLoader)
    except RecursionError:
        raise InputError(path, "invalid YAML: nested too deeply") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise InputError(path, f"invalid YAML: {getattr(exc, 'problem', exc)}",
                         line=None if mark is None else mark.line + 1) from exc


def load(path: str | Path | None, overrides: dict | None = None) -> RunConfig:
    """Defaults, then the YAML file (if any), then command-line overrides, merged, then validated once."""
    cfg = RunConfig().model_dump()
    if path is not None:
        path = Path(path)
        user = read_yaml(path) or {}
        if not isinstance(user, dict):
            raise InputError(path, "the config must be a mapping")
        unknown = set(user) - set(RunConfig.model_fields)
        if unknown:
            first = sorted(map(str, unknown))[0]
            raise InputError(path, f"unknown config sections: {', '.join(sorted(map(str, unknown)))}"
                                   f"{did_you_mean(first, RunConfig.model_fields)}")
        cfg = merge(cfg, user)
    cfg = merge(cfg, overrides or {})
    try:
        return config_schema.validate(cfg)
    except config_schema.ConfigError as exc:
        raise InputError(path, str(exc)) from None
    except InputError as exc:  # e.g. an unknown plugin name: the error names the config it came from
        if exc.source is not None or path is None:
            raise
        raise InputError(path, exc.problem, line=exc.line) from None


def sets(path: str | Path | None, section: str) -> bool:
    """Whether the YAML config at ``path`` (already read by :func:`load`) sets ``section`` itself."""
    if path is None:
        return False
    user = read_yaml(Path(path)) or {}
    return isinstance(user, dict) and section in user


def dump(cfg: RunConfig | dict, path: str | Path, footer: str = "") -> None:
    """The effective config (or a part of it, as plain values) as YAML (what ``dm2 refine -c`` reads back);
    ``footer``: YAML comment lines written after it."""
    with atomic_write(path) as fh:
        yaml.safe_dump(cfg.model_dump() if isinstance(cfg, RunConfig) else cfg, fh, sort_keys=False)
        fh.write(footer)
