"""The console's key never reaches a log (issue 34 §4: the expert wrote its console's address
with the key into expert.log, systemd's journal): on a terminal the whole address, else the
address alone and where the key is."""

import os
import stat

from humantele.expert.console.hook import console_line, console_url_file


class _Server:
    address = "http://127.0.0.1:8767/"
    key = "k" * 22
    url = f"{address}#key={key}"

    def banner(self) -> str:
        return f"console {self.url}"


def test_a_terminal_gets_the_whole_address(monkeypatch):
    monkeypatch.delenv("HUMANTELE_CONSOLE_KEY", raising=False)
    assert console_line(_Server(), tty=True) == f"console {_Server.url}"


def test_a_log_gets_the_address_without_the_key_and_where_it_is(monkeypatch, tmp_path):
    monkeypatch.delenv("HUMANTELE_CONSOLE_KEY", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    line = console_line(_Server(), tty=False)
    assert _Server.key not in line and "#key" not in line
    assert _Server.address in line and str(console_url_file()) in line
    kept = console_url_file()
    assert kept.read_text().strip() == _Server.url
    assert stat.S_IMODE(os.stat(kept).st_mode) == 0o600
    monkeypatch.setenv("HUMANTELE_CONSOLE_KEY", _Server.key)
    line = console_line(_Server(), tty=False)
    assert _Server.key not in line and "$HUMANTELE_CONSOLE_KEY" in line
