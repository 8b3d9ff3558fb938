"""Every float in every configuration model is finite, every quaternion normalisable, and a
bad value is refused at load with the field's name (issue 9 §2)."""

from __future__ import annotations

import functools
import importlib
import math
import pkgutil
import types
import typing

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import humantele
from fuzz_examples import examples
from humantele.config import ConfigError, ConfigModel, load_config, validate_config
from humantele.expert.config import ExpertConfig
from humantele.haptics.servo_config import RegistrationConfig, ServoConfig

BAD = [math.nan, math.inf, -math.inf]


def _all_config_models() -> list[type[ConfigModel]]:
    for mod in pkgutil.walk_packages(humantele.__path__, "humantele."):
        if ".web" in mod.name or mod.name.endswith("__main__"):
            continue
        importlib.import_module(mod.name)
    seen, todo = [], list(ConfigModel.__subclasses__())
    while todo:
        cls = todo.pop()
        if cls not in seen:
            seen.append(cls)
            todo.extend(cls.__subclasses__())
    return sorted(seen, key=lambda c: c.__module__ + c.__qualname__)


def _is_float(tp: object) -> bool:
    if typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return tp is float


def _bad_values(tp: object, bad: float) -> list[object]:
    """Values of annotation ``tp`` with one non-finite float in them ([] if it holds none)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Annotated:
        return _bad_values(args[0], bad)
    if _is_float(tp):
        return [bad]
    if origin in (typing.Union, types.UnionType):
        return [v for a in args if a is not type(None) for v in _bad_values(a, bad)]
    if origin is tuple and args and args[-1] is not Ellipsis:
        if all(_is_float(a) for a in args):
            return [
                tuple(bad if i == j else 0.5 for i in range(len(args))) for j in range(len(args))
            ]
    if origin in (tuple, list) and args and _is_float(args[0]):
        return [[bad]]
    if origin is dict and len(args) == 2 and _is_float(args[1]):
        return [{"k": bad}]
    return []


@functools.cache
def float_fields() -> list[tuple[type[ConfigModel], str, object]]:
    """(model, field, annotation) of every field holding a float. Walked when a test first
    needs it, not at collection: the walk imports every module of humantele (matplotlib, the
    DICOM and bench modules with them), which each xdist worker paid again to collect."""
    return [
        (cls, name, info.annotation)
        for cls in _all_config_models()
        for name, info in cls.model_fields.items()
        if _bad_values(info.annotation, math.nan)
    ]


def test_the_walk_finds_the_fields_named_in_the_issue():
    found = {(c.__name__, n) for c, n, _ in float_fields()}
    assert {
        ("MappingConfig", "origin_offset_m"),
        ("MappingConfig", "stylus_to_probe_deg"),
        ("RegistrationConfig", "position_m"),
        ("ServoConfig", "kp"),
    } <= found
    assert len(float_fields()) > 100  # every configuration module was walked


@settings(max_examples=examples(300), deadline=None)
@given(
    field=st.deferred(lambda: st.sampled_from(float_fields())),
    bad=st.sampled_from(BAD),
    pick=st.integers(0, 3),
)
def test_every_float_field_refuses_non_finite_values_by_name(field, bad, pick):
    cls, name, annotation = field
    values = _bad_values(annotation, bad)
    value = values[pick % len(values)]
    with pytest.raises(ConfigError) as err:
        validate_config(cls, {name: value}, "t.toml")
    lines = [ln for ln in str(err.value).splitlines() if ln.startswith(f"t.toml: {name}")]
    assert lines and any("finite" in ln for ln in lines), str(err.value)


@settings(max_examples=examples(200), deadline=None)
@given(q=st.tuples(*[st.floats(-1e-7, 1e-7)] * 4))
def test_a_quaternion_that_is_not_a_rotation_is_refused(q):
    with pytest.raises(ConfigError, match=r"quaternion: .*not a rotation"):
        validate_config(RegistrationConfig, {"quaternion": q})


@settings(max_examples=examples(200), deadline=None)
@given(q=st.tuples(*[st.floats(-10, 10)] * 4).filter(lambda q: math.hypot(*q) > 1e-3))
def test_a_normalisable_quaternion_is_stored_as_a_unit_rotation(q):
    stored = validate_config(RegistrationConfig, {"quaternion": q}).quaternion
    assert math.isclose(math.hypot(*stored), 1.0, rel_tol=1e-12)


@pytest.mark.parametrize(
    "text, where",
    [
        ("[expert.mapping]\norigin_offset_m = [nan, 0.0, 0.0]\n", "mapping.origin_offset_m.0"),
        (
            "[expert.mapping]\nstylus_to_probe_deg = [inf, 0.0, 0.0]\n",
            "mapping.stylus_to_probe_deg.0",
        ),
        (
            "[expert.mapping]\nstylus_to_probe_deg = [1e308, 1e308, 0]\n",
            "mapping.stylus_to_probe_deg.0",
        ),
        ("[servo.registration]\nposition_m = [0.0, -inf, 0.0]\n", "registration.position_m.1"),
        ("[servo.registration]\nquaternion = [0.0, 0.0, 0.0, 0.0]\n", "registration.quaternion"),
    ],
)
def test_the_issue_s_config_values_fail_at_load_naming_the_field(tmp_path, text, where):
    f = tmp_path / "expert.toml"
    f.write_text(text)
    section = "expert" if text.startswith("[expert") else "servo"
    model = ExpertConfig if section == "expert" else ServoConfig
    with pytest.raises(ConfigError, match=rf"expert.toml \[{section}\]: {where}"):
        load_config(model, f, section)


def test_invalid_utf8_and_deep_nesting_are_clear_errors(tmp_path):
    f = tmp_path / "c.toml"
    f.write_bytes(b"[servo]\nkp = 300.0 # \xff\xfe\n")
    with pytest.raises(ConfigError, match=r"c.toml: not UTF-8 text \(byte 0xff at offset"):
        load_config(ServoConfig, f, "servo")
    f.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ConfigError, match="c.toml: not valid TOML: nested too deeply"):
        load_config(ServoConfig, f)
    f.write_text("[" + ".".join(["t"] * 40) + "]\nx = 1\n")
    with pytest.raises(ConfigError, match="nested deeper than 16 levels"):
        load_config(ServoConfig, f)
    j = tmp_path / "c.json"
    j.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ConfigError, match="c.json: not valid JSON"):
        load_config(ServoConfig, j)
