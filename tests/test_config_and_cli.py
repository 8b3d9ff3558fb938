import pytest
from pydantic import Field

from humantele.cli import main
from humantele.config import ConfigError, ConfigModel, load_config
from humantele.report import write_section


class _Demo(ConfigModel):
    rate_hz: float = Field(250.0, gt=0, le=1000)
    name: str = "x"


def test_defaults_without_file():
    assert load_config(_Demo).rate_hz == 250.0


def test_bad_value_names_the_field(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("rate_hz = 5000\n")
    with pytest.raises(ConfigError, match=r"c.toml: rate_hz: .*less than or equal to 1000"):
        load_config(_Demo, f)


def test_unknown_key_and_bad_syntax(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("rate_hzz = 5\n")
    with pytest.raises(ConfigError, match="rate_hzz"):
        load_config(_Demo, f)
    f.write_text("rate_hz = = 5\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(_Demo, f)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(_Demo, tmp_path / "missing.toml")


def test_bench_sections_are_replaced_not_duplicated(tmp_path):
    md = tmp_path / "b.md"
    write_section("a", "first", md)
    write_section("b", "other", md)
    write_section("a", "second", md)
    text = md.read_text()
    assert "second" in text and "first" not in text and "other" in text
    assert text.count("<!-- bench:a -->") == 1


def test_cli_without_command_prints_help(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
