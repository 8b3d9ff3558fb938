"""What a configuration file gives is read with strict scalar types (issue 20 item 5): a string
is never a number or a boolean, a number never a boolean; an integer is a float and TOML
arrays fill tuples and lists. Each refusal names the field."""

from __future__ import annotations

import pytest

from humantele.config import ConfigError, load_config, validate_config
from humantele.expert.config import ExpertConfig
from humantele.follower.daemon import FollowerConfig
from humantele.haptics.servo_config import ServoConfig


def _load(tmp_path, model, section, text):
    f = tmp_path / "c.toml"
    f.write_text(text)
    return load_config(model, f, section)


@pytest.mark.parametrize(
    "text, where",
    [
        ('[expert.console]\nport = "8767"\n', r"console\.port: must be an integer, not the string"),
        ('[expert.console]\nenabled = "yes"\n', r"console\.enabled: must be true or false"),
        ("[expert.console]\nenabled = 1\n", r"console\.enabled: must be true or false, not 1"),
        ("[expert.console]\nport = 8767.0\n", r"console\.port: must be an integer, not 8767\.0"),
        ("[expert.console]\nport = true\n", r"console\.port: must be an integer, not True"),
        ('[expert.console]\nstate_rate_hz = "20"\n', r"console\.state_rate_hz: must be a number"),
        ("[expert.console]\nstate_rate_hz = false\n", r"console\.state_rate_hz: must be a number"),
        (
            '[expert.mapping]\norigin_offset_m = [0.0, "0.1", 0.0]\n',
            r"mapping\.origin_offset_m: item 1 must be a number, not the string '0.1'",
        ),
        ('[expert.igtl]\nenabled = "true"\n', r"igtl\.enabled: must be true or false"),
    ],
)
def test_strings_and_wrong_scalars_are_refused_naming_the_field(tmp_path, text, where):
    with pytest.raises(ConfigError, match=rf"c\.toml \[expert\]: {where}"):
        _load(tmp_path, ExpertConfig, "expert", text)


def test_integers_fill_floats_and_arrays_fill_tuples(tmp_path):
    c = _load(
        tmp_path,
        ExpertConfig,
        "expert",
        "[expert.console]\nstate_rate_hz = 10\nus_pixel_spacing_mm = [1, 0.5]\n"
        "[expert.mapping]\norigin_offset_m = [0, 0.1, 0]\n",
    )
    assert c.console.state_rate_hz == 10.0 and isinstance(c.console.state_rate_hz, float)
    assert c.console.us_pixel_spacing_mm == (1.0, 0.5)
    assert c.mapping.origin_offset_m == (0.0, 0.1, 0.0)
    f = _load(tmp_path, FollowerConfig, "follower", '[follower.feed]\nhosts = ["scanner.lan"]\n')
    assert f.feed.hosts == ["scanner.lan"]


def test_servo_and_follower_sections_are_strict_too(tmp_path):
    with pytest.raises(ConfigError, match=r"\[servo\]: kp: must be a number"):
        _load(tmp_path, ServoConfig, "servo", '[servo]\nkp = "300"\n')
    with pytest.raises(ConfigError, match=r"\[follower\]: feed\.port: must be an integer"):
        _load(tmp_path, FollowerConfig, "follower", '[follower.feed]\nport = "8766"\n')


def test_the_command_line_path_is_strict_and_code_built_configs_still_work():
    # validate_config is what the daemons' command lines go through (after model_dump).
    data = ExpertConfig().model_dump()
    assert validate_config(ExpertConfig, data) == ExpertConfig()
    data["console"]["port"] = "1"
    with pytest.raises(ConfigError, match="console.port: must be an integer"):
        validate_config(ExpertConfig, data, "command line")
    # Python code constructing a model is not affected (e.g. numpy scalars).
    assert ExpertConfig.model_validate({"console": {"port": 0}}).console.port == 0
