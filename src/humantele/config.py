"""Configuration: pydantic models loaded from TOML or JSON files.

Where the files are: the daemons' own files are wherever ``--config`` says (``configs/`` in the
repository holds editable examples); named definitions (probe tools ``tools/``, HID profiles
``hid/``, force sensor set-ups ``forcesense/``) ship inside the package as
``humantele/defaults/<folder>/<name>.toml``, read through :mod:`importlib.resources`
(:func:`named_config_path`), so an installed package finds them; a path in their place reads
the user's own file.

Every model derives from :class:`ConfigModel`: unknown fields are refused, every float (also
inside tuples, lists and tables) must be finite, and every field has a default that runs the
demo. What a file or the command line gives (:func:`validate_config`) is read with strict
scalar types: a string is never taken for a number or a boolean (``port = "8767"``,
``enabled = "yes"``), nor a number for a boolean, a boolean for a number, or a float for an
integer; an integer is a float, and arrays fill tuples and lists (pydantic's own strict mode
would refuse those TOML arrays, and its JSON mode is lost under a model's "before" validator).
Rotations are :data:`Quaternion` fields, refused unless normalisable; ports are :data:`Port`
(listened on) or :data:`RemotePort` (another host's); directories written into are
:data:`DirectoryField`. A bad value fails at start with :class:`ConfigError`, whose message
names the file, the field and the reason.
"""

from __future__ import annotations

import json
import math
import tomllib
import types
import typing
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, ClassVar, TypeVar

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    model_validator,
)
from pydantic_core import PydanticCustomError

STRICT_CONTEXT = {"strict_scalars": True}
"""Validation context of :func:`validate_config`: the models check scalar types strictly."""


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
    def _refuse_moved_fields(cls, data: Any, info: ValidationInfo) -> Any:
        if isinstance(data, dict):
            for name, hint in cls.moved_fields.items():
                if name in data:
                    raise PydanticCustomError(
                        "moved_field", "no longer set here: {hint}", {"field": name, "hint": hint}
                    )
            if info.context and info.context.get("strict_scalars"):
                _check_scalars(cls, data)
        return data


# --- strict scalar types for what files and command lines give -----------------------------

_Kind = Any  # "bool" | "int" | "float" | ("seq", tuple[_Kind, ...], repeat) | ("map", _Kind) | None
_kinds: dict[type, dict[str, _Kind]] = {}


def _kind(tp: Any) -> _Kind:
    """What scalar check an annotation asks for (None: leave it to pydantic)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        return _kind(args[0])
    if tp is bool:
        return "bool"
    if tp is int:
        return "int"
    if tp is float:
        return "float"
    if origin in (typing.Union, types.UnionType):
        kinds = {_kind(a) for a in args if a is not type(None)}
        if len(kinds) == 1:
            return kinds.pop()
        return "float" if kinds == {"int", "float"} else None
    if origin in (tuple, list, set, frozenset) and args:
        if origin is tuple and args[-1] is not Ellipsis:
            return ("seq", tuple(_kind(a) for a in args), False)
        return ("seq", (_kind(args[0]),), True)
    if origin is dict and len(args) == 2:
        return ("map", _kind(args[1]))
    return None


def _field_kinds(cls: type[BaseModel]) -> dict[str, _Kind]:
    kinds = _kinds.get(cls)
    if kinds is None:
        kinds = {n: _kind(f.annotation) for n, f in cls.model_fields.items()}
        _kinds[cls] = kinds = {n: k for n, k in kinds.items() if k is not None}
    return kinds


_WORDS = {"bool": "true or false", "int": "an integer", "float": "a number"}


def _wrong(kind: _Kind, value: Any) -> str | None:
    """Why ``value`` does not fit ``kind`` strictly, or None."""
    if kind in _WORDS:
        is_bool = isinstance(value, bool)
        ok = (
            is_bool
            if kind == "bool"
            else not is_bool and isinstance(value, int | float if kind == "float" else int)
        )
        if ok:
            return None
        if not isinstance(value, str | int | float):
            return None  # a table or an array: pydantic says what it wants
        shown = f"the string {value!r}" if isinstance(value, str) else repr(value)
        return f"must be {_WORDS[kind]}, not {shown}"
    if isinstance(kind, tuple) and kind[0] == "seq" and isinstance(value, list | tuple):
        _, items, repeat = kind
        for i, v in enumerate(value):
            item = items[0] if repeat else (items[i] if i < len(items) else None)
            why = _wrong(item, v)
            if why is not None:
                return f"item {i} {why}"
    if isinstance(kind, tuple) and kind[0] == "map" and isinstance(value, dict):
        for k, v in value.items():
            why = _wrong(kind[1], v)
            if why is not None:
                return f"{k!r} {why}"
    return None


def _check_scalars(cls: type[BaseModel], data: dict[str, Any]) -> None:
    """Refuse the first field of ``data`` whose scalar type is wrong (names the field)."""
    for name, kind in _field_kinds(cls).items():
        if name in data:
            why = _wrong(kind, data[name])
            if why is not None:
                raise PydanticCustomError("strict_type", "{why}", {"field": name, "why": why})


def _normalised(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    n = math.sqrt(math.fsum(c * c for c in q))
    if not 1e-6 < n < 1e6:
        raise ValueError(f"quaternion {q} is not a rotation (norm {n:.3g}); use (0, 0, 0, 1)")
    return tuple(c / n for c in q)  # type: ignore[return-value]


Quaternion = Annotated[tuple[float, float, float, float], AfterValidator(_normalised)]
"""A rotation (x, y, z, w): finite, normalisable, stored normalised."""


def _directory(v: str) -> str:
    """A directory field's value: not empty, no NUL, and no file where a directory must be."""
    if not v.strip():
        raise ValueError("empty: give a directory (e.g. ~/.local/state/humantele/...)")
    if "\0" in v:
        raise ValueError("a path cannot hold a NUL character")
    p = Path(v).expanduser()
    for q in (p, *p.parents):
        try:
            if q.exists():
                if not q.is_dir():
                    raise ValueError(f"{str(q)!r} is a file, not a directory")
                break
        except OSError as exc:  # e.g. a name too long for the file system
            raise ValueError(f"{v[:60]!r}: {exc.strerror or exc}") from None
    return v


DirectoryField = Annotated[str, AfterValidator(_directory)]
"""A directory a daemon writes into (``~`` allowed; made when needed): refused at load when
empty or when a file stands where it or one of its parents must be."""

Port = Annotated[int, Field(ge=0, le=65535)]
"""A port this process listens on, 0-65535 (0: the system picks a free one)."""

RemotePort = Annotated[int, Field(ge=1, le=65535)]
"""A port of another host's service this process connects to, 1-65535."""


def directory_problem(path: str | Path) -> str | None:
    """Why the daemon cannot write files into ``path`` (made if missing), or None: for the check
    at start of a :data:`DirectoryField` (whose owner says which field it is)."""
    import tempfile

    p = Path(path).expanduser()
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as exc:
        return f"cannot be written: {exc.strerror or exc}"
    return None


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
        if e["type"] in ("moved_field", "strict_type"):  # the field, not the section it is in
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
    """Validate a mapping (from a file or the command line) into ``model``, scalar types
    strictly (see the module docstring); ConfigError naming each bad field."""
    try:
        return model.model_validate(data, context=STRICT_CONTEXT)
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
