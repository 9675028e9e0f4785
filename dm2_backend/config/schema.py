"""The run configuration's schema: one frozen :class:`RunConfig`, every section validated once at load, plugin
options against the plugin's own dataclass fields, so that a wrong value is one line naming its field before any
work starts.

pydantic checks the types and choices (``frames.max_points: many`` -> "frames.max_points: Input should be a
valid integer", ``optimiser.start: gtsam`` -> "optimiser.start: Input should be 'auto', 'graph' or 'prepared'");
plugin options are checked against the fields of the plugin class the section names (``auto`` is checked once
resolved).
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

from dm2_backend.config.optimiser import OptimConfig
from dm2_backend.runtime.errors import did_you_mean

#: config section -> entry-point group of its plugins
PLUGIN_GROUPS = {"warm_start": "dm2.warm_start", "place_recognition": "dm2.place_recognition",
                 "registration": "dm2.registration"}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FramesSection(_Strict):
    """How each scan becomes a frame: at most ``max_points`` points, an optional voxel size (m)."""

    max_points: PositiveInt = 1024
    voxel: PositiveFloat | None = None


class PluginSection(_Strict):
    """A plugin by its registered name, with keyword options for its class."""

    name: str
    options: dict[str, Any] = Field(default_factory=dict)


class RunConfig(_Strict):
    """The whole run configuration (``dm2 refine -c``); ``RunConfig()`` is the default one."""

    #: numpy and torch seeds are unsigned 32-bit (checked here, not after the preparation)
    seed: int = Field(default=0, ge=0, lt=2**32)
    #: torch device: auto, cpu, cuda or cuda:N
    device: Literal["auto", "cpu", "cuda"] | str = "auto"
    #: processes optimising together (torch.distributed; ``dm2 refine --nproc``); torchrun sets its own
    nproc: PositiveInt = 1
    frames: FramesSection = FramesSection()
    warm_start: PluginSection = PluginSection(name="poses")
    #: "auto": loops for laser scans moving like a ground vehicle, loops3d for depth cameras and for scanners
    #: that tilt or climb (prepare/steps.py resolve_auto)
    place_recognition: PluginSection = PluginSection(name="auto")
    registration: PluginSection = PluginSection(name="icp")
    optimiser: OptimConfig = OptimConfig()


class ConfigError(ValueError):
    """One line: the field path and what is wrong with it."""


def validate(cfg: dict) -> RunConfig:
    """The :class:`RunConfig` of ``cfg`` (a merged config dict); :class:`ConfigError` for its first wrong value."""
    try:
        model = RunConfig.model_validate(cfg)
    except ValidationError as exc:
        raise ConfigError(one_line(exc)) from None
    if model.device not in ("auto", "cpu", "cuda") and not model.device.startswith("cuda:"):
        raise ConfigError(f"device: auto, cpu, cuda or cuda:N, not {model.device!r}")
    for section, group in PLUGIN_GROUPS.items():
        plugin = getattr(model, section)
        if plugin.name != "auto":
            check_plugin_options(section, group, plugin.name, plugin.options)
    return model


def one_line(exc: ValidationError) -> str:
    """The first error: its field path, pydantic's message and the value; an unknown field with the nearest
    known name."""
    err = exc.errors()[0]
    loc = [str(p) for p in err["loc"]]
    where = ".".join(loc) or "config"
    hint = ""
    if err["type"] == "extra_forbidden":
        model: type[BaseModel] = RunConfig
        for part in loc[:-1]:
            annotation = model.model_fields[part].annotation if part in model.model_fields else None
            if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
                break
            model = annotation
        else:
            hint = did_you_mean(loc[-1], model.model_fields)
    return f"{where}: {err['msg']} (got {err.get('input')!r}){hint}"


def check_plugin_options(section: str, group: str, name: str, options: dict) -> None:
    """The options against the plugin class's dataclass fields: unknown names and wrong types. A value pydantic
    converts (YAML's ``1.0e9`` is a string, ``"3"`` for a float) is replaced in ``options`` by its conversion, so the
    plugin receives the type it declares."""
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
            options[key] = adapter.validate_python(value, strict=False)
        except ValidationError as exc:
            raise ConfigError(f"{section}.options.{key}: {exc.errors()[0]['msg']} (got {value!r})") from None


def _hints(cls) -> dict:
    import typing

    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # unresolvable annotations: the names check only
        return {}
