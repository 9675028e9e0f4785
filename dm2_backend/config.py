"""The YAML run configuration: defaults, loading, merging and dumping the effective config."""

from __future__ import annotations

import copy
from dataclasses import asdict
from pathlib import Path

import yaml

from dm2_backend import config_schema
from dm2_backend.atomic import atomic_write
from dm2_backend.errors import InputError, did_you_mean
from dm2_backend.optim.config import OptimConfig

DEFAULTS: dict = {
    "seed": 0,
    "device": "auto",
    #: processes optimising together (torch.distributed; ``dm2 refine --nproc``); torchrun sets its own
    "nproc": 1,
    "frames": {"max_points": 1024, "voxel": None},
    "warm_start": {"name": "poses", "options": {}},
    #: "auto": loops for laser scans moving like a ground vehicle, loops3d for depth cameras and for scanners
    #: that tilt or climb (prepare/steps.py resolve_auto)
    "place_recognition": {"name": "auto", "options": {}},
    "registration": {"name": "icp", "options": {}},
    "optimiser": asdict(OptimConfig()),
}


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


def load(path: str | Path | None, overrides: dict | None = None) -> dict:
    """Defaults, then the YAML file (if any), then command-line overrides."""
    cfg = copy.deepcopy(DEFAULTS)
    if path is not None:
        path = Path(path)
        try:
            user = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        except FileNotFoundError as exc:
            raise InputError(path, "no such file") from exc
        except IsADirectoryError as exc:
            raise InputError(path, "is a folder, expected a YAML file") from exc
        except UnicodeDecodeError as exc:
            raise InputError(path, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        except RecursionError:
            raise InputError(path, "invalid YAML: nested too deeply") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            raise InputError(path, f"invalid YAML: {getattr(exc, 'problem', exc)}",
                             line=None if mark is None else mark.line + 1) from exc
        if not isinstance(user, dict):
            raise InputError(path, "the config must be a mapping")
        unknown = set(user) - set(DEFAULTS)
        if unknown:
            first = sorted(map(str, unknown))[0]
            raise InputError(path, f"unknown config sections: {', '.join(sorted(map(str, unknown)))}"
                                   f"{did_you_mean(first, DEFAULTS)}")
        cfg = merge(cfg, user)
    cfg = merge(cfg, overrides or {})
    try:
        config_schema.validate(cfg)
    except config_schema.ConfigError as exc:
        raise InputError(path, str(exc)) from None
    except InputError as exc:  # e.g. an unknown plugin name: the error names the config it came from
        if exc.source is not None or path is None:
            raise
        raise InputError(path, exc.problem, line=exc.line) from None
    return cfg


def sets(path: str | Path | None, section: str) -> bool:
    """Whether the YAML config at ``path`` (already read by :func:`load`) sets ``section`` itself."""
    if path is None:
        return False
    user = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    return isinstance(user, dict) and section in user


def dump(cfg: dict, path: str | Path) -> None:
    with atomic_write(path) as fh:
        yaml.safe_dump(cfg, fh, sort_keys=False)
