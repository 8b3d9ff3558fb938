"""Configuration: pydantic models loaded from TOML or JSON files.

Where the files are: the daemons' own files are wherever ``--config`` says (``configs/`` in the
repository holds editable examples); named definitions (probe tools ``tools/``, HID profiles
``hid/``, force sensor set-ups ``forcesense/``) ship inside the package as
``humantele/defaults/<folder>/<name>.toml``, read through :mod:`importlib.resources`
(:func:`named_config_path`), so an installed package finds them; a path in their place reads
the user's own file.

Every model derives from :class:`ConfigModel`: unknown fields are refused, every float (also
inside tuples, lists and tables) must be finite, and every field has a default that runs the
demo. Rotations are :data:`Quaternion` fields, refused unless normalisable. A bad value fails at
start with :class:`ConfigError`, whose message names the file, the field and the reason.
"""

from __future__ import annotations

import json
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, ClassVar, TypeVar

from pydantic import AfterValidator, BaseModel, ConfigDict, ValidationError, model_validator
from pydantic_core import PydanticCustomError


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message says which and why."""


class ConfigModel(BaseModel):
    """Base of every configuration model: strict about unknown keys, validated on assignment.

    ``moved_fields`` names fields a model no longer has and where their setting went; a file
    that still sets one is refused with that hint rather than a bare "extra field".
    """

    model_config = ConfigDict(
        extra="forbid", validate_assignment=True, frozen=False, allow_inf_nan=False
    )
    moved_fields: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _refuse_moved_fields(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, hint in cls.moved_fields.items():
                if name in data:
                    raise PydanticCustomError(
                        "moved_field", "no longer set here: {hint}", {"field": name, "hint": hint}
                    )
        return data


def _normalised(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    n = math.sqrt(math.fsum(c * c for c in q))
    if not 1e-6 < n < 1e6:
        raise ValueError(f"quaternion {q} is not a rotation (norm {n:.3g}); use (0, 0, 0, 1)")
    return tuple(c / n for c in q)  # type: ignore[return-value]


Quaternion = Annotated[tuple[float, float, float, float], AfterValidator(_normalised)]
"""A rotation (x, y, z, w): finite, normalisable, stored normalised."""


M = TypeVar("M", bound=BaseModel)


def _backend_message(e: Any, loc: str) -> tuple[str, str] | None:
    """(field path, reason) for a device/source section whose ``backend`` is bad, else None."""
    ctx = e.get("ctx") or {}
    if ctx.get("discriminator") != "'backend'":
        return None
    where = f"{loc}.backend" if loc else "backend"
    if e["type"] == "union_tag_invalid":
        return where, f"unknown backend {ctx['tag']!r}; choose one of: {ctx['expected_tags']}"
    data = e.get("input")
    if isinstance(data, dict) and "kind" in data:
        return where, (
            f"the field 'kind' is now called 'backend': write backend = {data['kind']!r} "
            "instead of kind = ... (every device and source family picks its backend this way)"
        )
    return where, "missing: say which backend this section configures (backend = ...)"


def describe_validation_error(err: ValidationError, source: str = "") -> str:
    """One line per bad field: ``source: field.path: reason``.

    A section whose ``backend`` is unknown or missing (a discriminated union of backend
    configurations) gets one line naming ``section.backend`` and the backends to choose from.
    """
    lines = []
    prefix = f"{source}: " if source else ""
    for e in err.errors():
        parts = [str(part) for part in e["loc"]]
        if e["type"] == "moved_field":  # name the field itself, not the section it was in
            parts.append(e["ctx"]["field"])
        loc = ".".join(parts)
        special = _backend_message(e, loc)
        if special is not None:
            lines.append(f"{prefix}{special[0]}: {special[1]}")
        else:
            msg = e["msg"].removeprefix("Value error, ")  # our own validators' words
            lines.append(f"{prefix}{loc or '(top level)'}: {msg}")
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


def defaults_dir(folder: str = "") -> Path:
    """The packaged defaults folder ``humantele/defaults/<folder>`` (installed or checkout)."""
    return Path(str(resources.files("humantele").joinpath("defaults"))) / folder


def named_config_path(folder: str, name_or_path: str | Path, what: str = "definition") -> Path:
    """The file for ``name_or_path``: a path as given when it ends in .toml or .json (relative:
    from the current directory), else the packaged ``defaults/<folder>/<name>.toml``.
    ConfigError naming the known names when the name has no packaged file."""
    p = Path(name_or_path)
    if p.suffix in (".toml", ".json"):
        return p
    f = defaults_dir(folder) / f"{p.name}.toml"
    if p.name != str(name_or_path) or not f.is_file():
        known = ", ".join(sorted(x.stem for x in defaults_dir(folder).glob("*.toml")))
        raise ConfigError(
            f"{str(name_or_path)!r}: no such {what} (known {what}s: {known or 'none'}); or give "
            "the path of your own .toml file"
        )
    return f
