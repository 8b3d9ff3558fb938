"""Ports in the configuration files (``humantele.config.Port`` and ``RemotePort``): a port this
process listens on may be 0 (the system picks one), another host's may not; above 65535 or not
an integer is refused at load, naming the field."""

from __future__ import annotations

import pytest

from humantele.archive.config import ArchiveConfig
from humantele.config import ConfigError, validate_config
from humantele.expert.console.config import ConsoleConfig
from humantele.follower.feed import FeedConfig
from humantele.interop.igtl import IgtlConfig
from humantele.signaling.server import SignalConfig
from humantele.tracking.hl2ss_source import Hl2ssFrameConfig

LISTENED_ON = [(ConsoleConfig, "port"), (FeedConfig, "port"), (SignalConfig, "port"),
               (IgtlConfig, "port")]  # fmt: skip
REMOTE = [(ArchiveConfig, "port"), (ArchiveConfig, "worklist_port"), (Hl2ssFrameConfig, "port")]


@pytest.mark.parametrize("model, field", LISTENED_ON + REMOTE)
def test_ports_above_65535_or_not_integers_are_refused_naming_the_field(model, field):
    assert getattr(validate_config(model, {field: 65535}), field) == 65535
    with pytest.raises(ConfigError, match=rf"^cfg: {field}: .*less than or equal to 65535"):
        validate_config(model, {field: 65536}, "cfg")
    with pytest.raises(ConfigError, match=rf"^cfg: {field}: .*greater than or equal to"):
        validate_config(model, {field: -1}, "cfg")
    with pytest.raises(ConfigError, match=rf"^cfg: {field}: must be an integer"):
        validate_config(model, {field: "8080"}, "cfg")


@pytest.mark.parametrize("model, field", LISTENED_ON)
def test_a_port_listened_on_may_be_0(model, field):
    assert getattr(validate_config(model, {field: 0}), field) == 0


@pytest.mark.parametrize("model, field", REMOTE)
def test_another_hosts_port_may_not_be_0(model, field):
    with pytest.raises(ConfigError, match=rf"^cfg: {field}: .*greater than or equal to 1"):
        validate_config(model, {field: 0}, "cfg")


def test_the_worklist_port_may_be_left_to_the_archives():
    assert ArchiveConfig().worklist_port is None
    assert validate_config(ArchiveConfig, {"worklist_port": None}).worklist_port is None
