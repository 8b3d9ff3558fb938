"""Configuration: pydantic models loaded from TOML or JSON files in ``configs/``.

Every model derives from :class:`ConfigModel`: unknown fields are refused, every float (also
inside tuples, lists and tables) must be finite, and every field has a default that runs the
demo. Rotations are :data:`Quaternion` fields, refused unless normalisable. A bad value fails at
start with :class:`ConfigError`, whose message names the file, the field and the reason.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, TypeVar

from pydantic import AfterValidator, BaseModel, ConfigDict, ValidationError

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message says which and why."""


class ConfigModel(BaseModel):
    """Base of every configuration model: strict about unknown keys, validated on assignment."""

    model_config = ConfigDict(
        extra="forbid", validate_assignment=True, frozen=False, allow_inf_nan=False
    )


def _normalised(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    n = math.sqrt(math.fsum(c * c for c in q))
    if not 1e-6 < n < 1e6:
        raise ValueError(f"quaternion {q} is not a rotation (norm {n:.3g}); use (0, 0, 0, 1)")
    return tuple(c / n for c in q)  # type: ignore[return-value]


Quaternion = Annotated[tuple[float, float, float, float], AfterValidator(_normalised)]
"""A rotation (x, y, z, w): finite, normalisable, stored normalised."""


M = TypeVar("M", bound=BaseModel)


def describe_validation_error(err: ValidationError, source: str = "") -> str:
    """One line per bad field: ``source: field.path: reason``."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(part) for part in e["loc"]) or "(top level)"
        prefix = f"{source}: " if source else ""
        lines.append(f"{prefix}{loc}: {e['msg']}")
    return "\n".join(lines)


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The raw mapping in a .toml or .json file; ConfigError if unreadable or malformed."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"
        ) from exc
    kind = "JSON" if path.suffix == ".json" else "TOML"
    try:
        data = json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: not valid {kind}: {exc}") from exc
    except RecursionError as exc:
        raise ConfigError(f"{path}: not valid {kind}: nested too deeply") from exc
    if _depth(data) > MAX_DEPTH:
        raise ConfigError(f"{path}: tables nested deeper than {MAX_DEPTH} levels")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a table/object")
    return data


MAX_DEPTH = 16  # the deepest real config is 4 levels


def _depth(value: Any, level: int = 0) -> int:
    if level > MAX_DEPTH:
        return level
    if isinstance(value, dict):
        return max((_depth(v, level + 1) for v in value.values()), default=level + 1)
    if isinstance(value, list):
        return max((_depth(v, level + 1) for v in value), default=level + 1)
    return level


def validate_config(model: type[M], data: dict[str, Any], source: str = "") -> M:
    """Validate a mapping into ``model``; ConfigError naming each bad field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, source)) from exc


def load_config(model: type[M], path: str | Path | None = None, section: str | None = None) -> M:
    """Load ``model`` from ``path`` (optionally one ``[section]`` of it); defaults when no path."""
    if path is None:
        return model()
    data = read_config_file(path)
    if section is not None:
        data = data.get(section, {})
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: [{section}] must be a table")
    return validate_config(model, data, str(path) + (f" [{section}]" if section else ""))
