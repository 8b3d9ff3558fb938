"""``[expert.archive]``: off by default (the demo unchanged), bad values refused with the
field's name."""

import pytest

from humantele.archive.config import ArchiveConfig
from humantele.config import ConfigError, validate_config
from humantele.expert.config import ExpertConfig


def test_off_by_default():
    assert ExpertConfig().archive.enabled is False


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"called_ae": "A" * 17}, "called_ae"),
        ({"calling_ae": "BAD\\AE"}, "calling_ae"),
        ({"port": 0}, "port"),
        ({"protocol": "ftp"}, "protocol"),
        ({"protocol": "stow"}, "stow_url"),
        ({"tls": True}, "tls_ca_file"),
        ({"retry_min_s": 10, "retry_max_s": 5}, "retry_max_s"),
        ({"stow_url": "pacs/dicom-web"}, "stow_url"),
        ({"queue_max_mb": -1}, "queue_max_mb"),
    ],
)
def test_a_bad_value_is_refused_with_its_field(data, field):
    with pytest.raises(ConfigError, match=field):
        validate_config(ArchiveConfig, data, "[expert.archive]")
