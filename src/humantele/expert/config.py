"""The expert daemon's configuration: ``[expert]`` of configs/expert.toml (the servo has
``[servo]``, :class:`humantele.haptics.servo_config.ServoConfig`)."""

from __future__ import annotations

from pydantic import Field

from humantele.archive.config import ArchiveConfig
from humantele.config import ConfigError, ConfigModel, validate_config
from humantele.daemons.session import SessionConfig
from humantele.expert.console import ConsoleConfig
from humantele.expert.mapping import MappingConfig
from humantele.expert.scans import ScanScriptConfig
from humantele.haptics.servo_config import ServoConfig
from humantele.interop.igtl import IgtlConfig
from humantele.media.config import ExpertVideoConfig
from humantele.recording import RecorderConfig
from humantele.transport import LinkConfig


class ExpertConfig(ConfigModel):
    """The expert daemon (``[expert]`` of configs/expert.toml; the servo has ``[servo]``)."""

    servo_restart_s: float = Field(2.0, gt=0, le=60, description="retry a dead servo after")
    # Poses at 100 Hz, as the published system (C&G 2024, Table 1; docs/references.md).
    link: LinkConfig = LinkConfig(pose_rate_hz=100.0)
    mapping: MappingConfig = MappingConfig()
    scans: ScanScriptConfig = ScanScriptConfig()
    video: ExpertVideoConfig = ExpertVideoConfig()
    session: SessionConfig = SessionConfig()
    recording: RecorderConfig = RecorderConfig()
    console: ConsoleConfig = ConsoleConfig()
    igtl: IgtlConfig = IgtlConfig()
    archive: ArchiveConfig = ArchiveConfig()  # the hospital's PACS (off by default)


def servo_config_for(mapping: MappingConfig, servo: ServoConfig) -> ServoConfig:
    """The servo's configuration with the mapping's motion scale: ``[expert.mapping] scale`` is
    the one setting (the passivity check then sees the scale actually used). A non-default
    ``[servo] motion_scale`` is refused with a ConfigError saying where to set it."""
    default = ServoConfig.model_fields["motion_scale"].default
    if servo.motion_scale not in (default, mapping.scale):
        raise ConfigError(
            f"[servo] motion_scale = {servo.motion_scale:g}: the expert daemon takes the motion "
            f"scale from the mapping; remove it and set [expert.mapping] scale = "
            f"{servo.motion_scale:g} instead"
        )
    data = servo.model_dump()
    data["motion_scale"] = mapping.scale
    return validate_config(ServoConfig, data, "[servo] with [expert.mapping] scale")
