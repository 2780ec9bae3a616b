"""Load and validate a setup TOML file; every problem becomes one ``key.path: reason`` line.

Validation is two-staged: each device section (``[camera]``, ``[robot]``, ``[tracker]``) is
validated against the model registered for its ``driver``; the rest against
:class:`SetupConfig`. All problems of both stages are collected and raised together as one
:class:`hil.errors.ConfigError` (its lines read ``file: key.path: reason``).
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from hil.config.faults import FaultSpec
from hil.config.setup import SetupConfig
from hil.config.types import STRICT
from hil.errors import ConfigError
from plugins.registry import DRIVER_KINDS, DriverRegistry, RegistryError

DEFAULT_SETUP_NAME = "sim.toml"
ENV_DEFAULT_SETUP = "HIL_SETUP"


def _loc(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _problems(exc: ValidationError, prefix: str = "") -> list[str]:
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        path = _loc(loc)
        if prefix:
            path = prefix if path == "(top level)" else f"{prefix}.{path}"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "missing" and loc and isinstance(loc[-1], int):
            path = path[: path.rindex("[")]
            msg = f"too few values (item {loc[-1]} missing)"
        elif err["type"] == "missing":
            msg = "required key missing"
        lines.append(f"{path}: {msg}")
    return lines


def _validate_device(
    role: str, raw: Any, registry: DriverRegistry, context: dict[str, Any],
) -> tuple[BaseModel | None, list[str]]:
    if not isinstance(raw, Mapping):
        return None, [f"{role}: must be a table with driver = \"<name>\""]
    name = raw.get("driver")
    if name is None:
        return None, [f"{role}.driver: required key missing (one of {registry.names(role)})"]
    if not isinstance(name, str):
        return None, [f"{role}.driver: must be a string"]
    try:
        info = registry.get(role, name)
    except RegistryError as exc:
        return None, [f"{role}.driver: {exc}"]
    try:
        return info.config_model.model_validate(dict(raw), context=context), []
    except ValidationError as exc:
        return None, _problems(exc, role)


def parse_setup(
    data: Mapping[str, Any], *, source: str, config_dir: Path, registry: DriverRegistry | None = None,
) -> SetupConfig:
    """Validate a setup given as a mapping (the parsed TOML).

    Args:
        data: the document.
        source: how to name it in errors (the file path).
        config_dir: relative paths in the document are resolved against it.
        registry: drivers to validate device sections with (default: every installed plugin).

    Raises:
        ConfigError: one line per problem.
    """
    if registry is None:
        from plugins.manager import default_registry

        registry = default_registry()
    context = {"config_dir": config_dir}
    problems: list[str] = []
    doc = dict(data)
    for role in DRIVER_KINDS:
        if role not in doc:
            if role != "tracker":
                problems.append(f"{role}: required section missing")
            continue
        model, errs = _validate_device(role, doc[role], registry, context)
        problems += errs
        doc[role] = model
    try:
        setup = SetupConfig.model_validate(doc, context=context)
    except ValidationError as exc:
        problems += [p for p in _problems(exc) if p.split(":")[0] not in DRIVER_KINDS]
        setup = None
    if setup is not None:
        setup._config_dir = config_dir
        problems += _cross_checks(setup, doc)
    if problems or setup is None:
        raise ConfigError(source, problems or ["invalid setup"])
    return setup


def _cross_checks(setup: SetupConfig, doc: Mapping[str, Any]) -> list[str]:
    out = []
    for i, fault in enumerate(setup.faults):
        if fault.device == "tracker" and setup.tracker is None:
            out.append(f"faults[{i}].kind: {fault.kind.value} needs a [tracker] section")
    return out


def load_setup(path: str | Path, registry: DriverRegistry | None = None) -> SetupConfig:
    """Read and validate a setup TOML file.

    Relative paths inside it are resolved against the file's directory.

    Raises:
        InputFileError-like ConfigError: the file is missing, not TOML, or invalid (one line per
            problem: ``file: key.path: reason``).
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror or exc}"]) from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(str(path), ["not UTF-8 text"]) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), [f"not valid TOML: {exc}"]) from None
    except ValueError as exc:  # e.g. an integer literal beyond Python's 4300-digit limit
        raise ConfigError(str(path), [f"unusable TOML: {exc}"]) from None
    except RecursionError:
        raise ConfigError(str(path), ["unusable TOML: nested too deeply"]) from None
    return parse_setup(data, source=str(path), config_dir=p.resolve().parent, registry=registry)


class _FaultSchedule(BaseModel):
    model_config = STRICT

    name: str = ""
    faults: tuple[FaultSpec, ...] = ()


def load_fault_schedule(path: str | Path) -> tuple[FaultSpec, ...]:
    """Read a scenario file holding only ``[[faults]]`` tables (and an optional ``name``), to be
    played on any setup with :func:`with_faults`.

    Raises:
        ConfigError: unreadable, not TOML, or invalid (one line per problem).
    """
    p = Path(path)
    try:
        data = tomllib.loads(p.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror or exc}"]) from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(str(path), [f"not valid TOML: {exc}"]) from None
    except ValueError as exc:  # e.g. an integer literal beyond Python's 4300-digit limit
        raise ConfigError(str(path), [f"unusable TOML: {exc}"]) from None
    except RecursionError:
        raise ConfigError(str(path), ["unusable TOML: nested too deeply"]) from None
    try:
        return _FaultSchedule.model_validate(data).faults
    except ValidationError as exc:
        raise ConfigError(str(path), _problems(exc)) from None


def with_faults(setup: SetupConfig, faults: tuple[FaultSpec, ...], *, source: str = "faults") -> SetupConfig:
    """The setup with ``faults`` appended to its own schedule.

    Raises:
        ConfigError: a tracker fault for a setup without a tracker.
    """
    merged = setup.model_copy(update={"faults": (*setup.faults, *faults)})
    problems = _cross_checks(merged, {})
    if problems:
        raise ConfigError(source, problems)
    return merged


def default_setup_path() -> Path:
    """The embedded default setup, ``configs/sim.toml``.

    Looked up in order: ``$HIL_SETUP``; the ``configs/`` directory next to the ``hil`` package
    (a source checkout or an editable install); the installed ``configs`` package data
    (``importlib.resources``), for a wheel install that ships ``configs`` as package data.

    Raises:
        ConfigError: none of them exists.
    """
    env = os.environ.get(ENV_DEFAULT_SETUP)
    if env:
        return Path(env)
    here = Path(__file__).resolve().parents[2] / "configs" / DEFAULT_SETUP_NAME
    if here.is_file():
        return here
    try:
        from importlib.resources import as_file, files

        resource = files("configs") / DEFAULT_SETUP_NAME
        with as_file(resource) as f:
            if Path(f).is_file():
                return Path(f)
    except (ModuleNotFoundError, FileNotFoundError, TypeError):
        pass
    raise ConfigError(DEFAULT_SETUP_NAME, [f"default setup not found (looked at {here} and the "
                                           "installed 'configs' package); give a setup file"])
