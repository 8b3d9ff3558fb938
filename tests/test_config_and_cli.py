import pytest
from pydantic import Field

from humantele.cli import main
from humantele.config import ConfigError, ConfigModel, load_config
from humantele.report import markdown_table, section_rows, write_section


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


def test_section_rows_are_the_body_rows_of_tables_of_that_width(tmp_path):
    md = tmp_path / "b.md"
    wide = markdown_table(["setting", "a", "b"], [["x", "1", "2"], ["y", "3", "4"]])
    narrow = markdown_table(["setting", "a"], [["z", "5"]])
    write_section("s", f"## s\n\n{wide}\n\ntext | with a bar\n\n{narrow}", md)
    write_section("other", markdown_table(["setting", "a", "b"], [["w", "0", "0"]]), md)
    assert section_rows("s", 3, md) == [["x", "1", "2"], ["y", "3", "4"]]
    assert section_rows("s", 2, md) == [["z", "5"]]  # its header is not a row
    assert section_rows("missing", 3, md) == []
    assert section_rows("s", 3, tmp_path / "none.md") == []


def test_cli_without_command_prints_help(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
