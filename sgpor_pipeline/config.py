"""Pipeline configuration: one parameter dataclass per stage, a TOML file, ``--set`` overrides.

The resolved configuration maps a stage name to an instance of that stage's ``Params``. TOML files
have one table per stage (``[fit]`` ``iterations = 3000``); overrides are ``stage.field=value`` with
the value parsed as a TOML literal (``3000``, ``0.5``, ``true``, ``"text"``, ``[1, 2]``; bare words
are strings). Unknown stages or fields are errors listing the valid names.
"""

from __future__ import annotations

import dataclasses
import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

import tomli_w

from .errors import PipelineError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclasses.dataclass
class NoParams:
    """Parameters of a stage that has none."""


# dataclass field metadata: the value at which a parameter reproduces the results from before it existed
KEY_NEUTRAL = "sgpor_key_neutral"


def added_param(default: Any) -> Any:
    """A dataclass field for a parameter added to a stage after results were cached, whose default
    reproduces them (typically an option that is off by default): while it has that value it is left
    out of the cache keys (:func:`params_key`), so upgrading does not recompute cached stages. Use as
    ``order: str = added_param("onion")``. A new parameter that changes results at its default must be
    a plain field (or bump the stage's VERSION)."""
    return dataclasses.field(default=default, metadata={KEY_NEUTRAL: default})


def params_key(params: Any) -> dict[str, Any]:
    """The parameters as they enter cache keys: :func:`params_to_dict` without the :func:`added_param`
    fields that are at their neutral value. (Stored and printed configurations keep every field.)"""
    out = params_to_dict(params)
    for f in dataclasses.fields(params):
        if KEY_NEUTRAL in f.metadata:
            neutral = f.metadata[KEY_NEUTRAL]
            if out[f.name] == (list(neutral) if isinstance(neutral, tuple) else neutral):
                del out[f.name]
    return out


def params_to_dict(params: Any) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, tuple):
            value = list(value)
        if isinstance(value, Path):
            value = str(value)
        out[f.name] = value
    return out


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert where lossless (int -> float, list -> tuple)."""
    origin = get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        if value is None and type(None) in get_args(tp):
            return None
        errors = []
        for arg in get_args(tp):
            if arg is type(None):
                continue
            try:
                return coerce(value, arg, where)
            except PipelineError as e:
                errors.append(e.message)
        raise PipelineError(f"{where}: {value!r} is not a {_type_name(tp)}")
    if origin is Literal:
        if value in get_args(tp):
            return value
        choices = ", ".join(repr(a) for a in get_args(tp))
        raise PipelineError(f"{where}: {value!r} is not one of {choices}")
    if origin in (list, tuple):
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise PipelineError(f"{where}: expected a list, got {value!r}")
        args = get_args(tp)
        item_tp = args[0] if args else Any
        items = [coerce(v, item_tp, where) for v in value] if item_tp is not Any else list(value)
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise PipelineError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise PipelineError(f"{where}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise PipelineError(f"{where}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise PipelineError(f"{where}: expected a string, got {value!r}")
    if tp is Path:
        if isinstance(value, (str, Path)):
            return Path(value)
        raise PipelineError(f"{where}: expected a path, got {value!r}")
    return value


def _is_text(tp: Any) -> bool:
    """A str or Path annotation, optional or not (``str | None``): a value typed as text."""
    if get_origin(tp) is typing.Union or get_origin(tp) is types.UnionType:
        args = [a for a in get_args(tp) if a is not type(None)]
        return bool(args) and all(a in (str, Path) for a in args)
    return tp in (str, Path)


def _is_text_list(tp: Any) -> bool:
    """A list or tuple of str or Path annotation: ``--set`` takes comma-separated names."""
    return get_origin(tp) in (list, tuple) and bool(get_args(tp)) and get_args(tp)[0] in (str, Path)


def parse_literal(text: str) -> Any:
    """A command-line value as a TOML literal; anything that is not one is a plain string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _apply(params: Any, stage: str, updates: dict[str, Any], source: str) -> Any:
    hints = get_type_hints(type(params))
    fields = {f.name for f in dataclasses.fields(params)}
    changes = {}
    for key, value in updates.items():
        if key not in fields:
            valid = ", ".join(sorted(fields)) or "(this stage has no parameters)"
            raise PipelineError(f"unknown parameter '{stage}.{key}'", path=source,
                                fix=f"valid parameters of '{stage}': {valid}")
        changes[key] = coerce(value, hints[key], f"{stage}.{key}")
    return dataclasses.replace(params, **changes)


def resolve_config(
    param_types: dict[str, type],
    config_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    preset: str | None = None,
) -> dict[str, Any]:
    """Defaults, then the named preset (:mod:`sgpor_pipeline.presets`), then the TOML file, then
    ``stage.field=value`` overrides. A file value that an override replaces is never read, so ``--set``
    can repair a bad value in a saved config."""
    config = {name: tp() for name, tp in param_types.items()}
    valid_stages = ", ".join(sorted(param_types))

    def check_stage(stage: str, source: str) -> None:
        if stage not in config:
            raise PipelineError(f"unknown stage '{stage}'", path=source, fix=f"valid stages: {valid_stages}")

    # each override split once: (item, well formed, stage, field as written, value text)
    split = []
    for item in overrides:
        key, sep, text = item.partition("=")
        stage, dot, field = key.strip().partition(".")
        split.append((item, bool(sep and dot), stage.strip(), field, text.strip()))
    overridden = {(stage, field.strip()) for _, ok, stage, field, _ in split if ok}

    if preset is not None:
        from .presets import preset_tables

        for stage, table in preset_tables(preset).items():
            check_stage(stage, f"preset '{preset}'")
            config[stage] = _apply(config[stage], stage, table, f"preset '{preset}'")
    if config_file is not None:
        config_file = Path(config_file)
        try:
            data = tomllib.loads(config_file.read_text())
        except FileNotFoundError:
            raise PipelineError("configuration file not found", path=config_file,
                                fix="check the --config path") from None
        except tomllib.TOMLDecodeError as e:
            raise PipelineError(f"not valid TOML ({e})", path=config_file,
                                fix="fix the syntax; see the saved config.toml of a run") from None
        for stage, table in data.items():
            check_stage(stage, str(config_file))
            if not isinstance(table, dict):
                raise PipelineError(f"'{stage}' must be a table ([{stage}])", path=config_file,
                                    fix=f"write the parameters under a [{stage}] header")
            table = {k: v for k, v in table.items() if (stage, k) not in overridden}
            config[stage] = _apply(config[stage], stage, table, str(config_file))
    for item, ok, stage, field, text in split:
        if not ok:
            raise PipelineError(f"--set expects STAGE.PARAM=VALUE, got '{item}'",
                                fix="for example --set fit.iterations=3000")
        check_stage(stage, "--set")
        value = parse_literal(text)
        tp = get_type_hints(type(config[stage])).get(field.strip())
        if (_is_text(tp) and not isinstance(value, str)) or (_is_text_list(tp) and not isinstance(value, (str, list))):
            value = text  # a name that reads as a number (a view "24") is still a name
        config[stage] = _apply(config[stage], stage, {field: value}, "--set")
    return config


def config_to_toml(config: dict[str, Any]) -> str:
    tables = {}
    for stage, params in config.items():
        values = {k: v for k, v in params_to_dict(params).items() if v is not None}
        tables[stage] = values
    return tomli_w.dumps(tables)


def save_config(path: Path, config: dict[str, Any]) -> None:
    Path(path).write_text(
        "# Fully resolved configuration of this run (defaults + --config + --set).\n"
        "# Pass it back with --config to repeat the run.\n" + config_to_toml(config)
    )
