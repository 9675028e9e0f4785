"""The run configuration's schema: every section validated at load, plugin options against the plugin's own
dataclass fields, so that a wrong value is one line naming its field before any work starts.

pydantic checks the types (``frames.max_points: many`` -> "frames.max_points: Input should be a valid
integer"); the optimiser section keeps its own checks (:meth:`OptimConfig.from_dict`), and plugin options are
checked against the fields of the plugin class the section names (``auto`` is checked once resolved).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PositiveFloat,
    PositiveInt,
    PydanticSchemaGenerationError,
    PydanticUserError,
    TypeAdapter,
    ValidationError,
)

from dm2_backend.errors import did_you_mean
from dm2_backend.optim.config import OptimConfig

#: config section -> entry-point group of its plugins
PLUGIN_GROUPS = {"warm_start": "dm2.warm_start", "place_recognition": "dm2.place_recognition",
                 "registration": "dm2.registration"}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FramesSection(_Strict):
    """How each scan becomes a frame: at most ``max_points`` points, an optional voxel size (m)."""

    max_points: PositiveInt = 1024
    voxel: PositiveFloat | None = None


class PluginSection(_Strict):
    """A plugin by its registered name, with keyword options for its class."""

    name: str
    options: dict[str, Any] = Field(default_factory=dict)


class RunConfig(_Strict):
    """The whole run configuration (``dm2 refine -c``); see ``config.DEFAULTS`` for the defaults."""

    #: numpy and torch seeds are unsigned 32-bit (checked here, not after the preparation)
    seed: int = Field(default=0, ge=0, lt=2**32)
    device: Literal["auto", "cpu", "cuda"] | str = "auto"
    nproc: PositiveInt = 1
    frames: FramesSection
    warm_start: PluginSection
    place_recognition: PluginSection
    registration: PluginSection
    optimiser: dict[str, Any]


class ConfigError(ValueError):
    """One line: the field path and what is wrong with it."""


def validate(cfg: dict) -> None:
    """Raise :class:`ConfigError` for the first wrong value of ``cfg`` (a merged config dict)."""
    try:
        model = RunConfig.model_validate(cfg)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "config"
        raise ConfigError(f"{where}: {err['msg']} (got {err.get('input')!r})") from None
    if model.device not in ("auto", "cpu", "cuda") and not model.device.startswith("cuda:"):
        raise ConfigError(f"device: auto, cpu, cuda or cuda:N, not {model.device!r}")
    try:
        OptimConfig.from_dict(cfg["optimiser"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"optimiser: {exc}") from None
    for section, group in PLUGIN_GROUPS.items():
        plugin = getattr(model, section)
        if plugin.name != "auto":
            check_plugin_options(section, group, plugin.name, plugin.options)


def check_plugin_options(section: str, group: str, name: str, options: dict) -> None:
    """The options against the plugin class's dataclass fields: unknown names and wrong types."""
    from dm2_backend.plugins.registry import load

    cls = load(group, name)
    if not dataclasses.is_dataclass(cls):
        return
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise ConfigError(f"{section}.options: {name} has no option {unknown[0]!r}"
                          f"{did_you_mean(unknown[0], fields)}; its options: {', '.join(sorted(fields))}")
    hints = _hints(cls)
    for key, value in options.items():
        hint = hints.get(key)
        if hint is None:
            continue
        try:
            adapter = TypeAdapter(hint)
        except (PydanticSchemaGenerationError, PydanticUserError):  # a type pydantic cannot check: names only
            continue
        try:
            adapter.validate_python(value, strict=False)
        except ValidationError as exc:
            raise ConfigError(f"{section}.options.{key}: {exc.errors()[0]['msg']} (got {value!r})") from None


def _hints(cls) -> dict:
    import typing

    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # unresolvable annotations: the names check only
        return {}
