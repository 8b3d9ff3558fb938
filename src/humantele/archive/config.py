"""``[expert.archive]``: where the exam goes (a PACS by C-STORE or STOW-RS), the queue's
folder and budget, how the patient is chosen, and the names DICOM records for the
tele-operation. Off by default (the demo is unchanged)."""

from __future__ import annotations

import re

from pydantic import Field, field_validator, model_validator

from humantele.config import ConfigModel, DirectoryField, RemotePort

_AE = re.compile(r"^[\x20-\x5b\x5d-\x7e]{1,16}$")  # DICOM AE: 16 chars, no backslash, no control


def _ae_title(v: str) -> str:
    if not _AE.match(v) or not v.strip():
        raise ValueError(f"AE title {v!r}: 1-16 printable characters, not all spaces, no backslash")
    return v


class ArchiveConfig(ConfigModel):
    """The hospital's archive (``[expert.archive]``)."""

    enabled: bool = Field(False, description="send the exam's DICOM objects to the archive")
    protocol: str = Field(
        "dimse", pattern=r"^(dimse|stow)$", description="'dimse': C-STORE; 'stow': STOW-RS"
    )
    host: str = Field("127.0.0.1", min_length=1, description="the archive's DICOM host")
    port: RemotePort = Field(104, description="the archive's DICOM port")
    called_ae: str = Field("ORTHANC", description="the archive's AE title")
    calling_ae: str = Field("HUMANTELE", description="this expert's AE title")
    tls: bool = Field(False, description="DICOM over TLS (PS3.15 B.1): needs tls_ca_file")
    tls_ca_file: str | None = Field(None, description="CA bundle the archive's cert is checked on")
    tls_cert_file: str | None = Field(None, description="this expert's certificate (mutual TLS)")
    tls_key_file: str | None = Field(None, description="its key")
    stow_url: str | None = Field(
        None, description="DICOMweb base URL for protocol = 'stow' (e.g. http://pacs/dicom-web)"
    )
    queue_dir: DirectoryField = Field(
        "~/.local/state/humantele/archive",
        description="the send queue and the exam (identity lives here and in the archive only)",
    )
    queue_max_mb: float = Field(
        2000.0, gt=0, le=1e7, description="disk budget of the queue (MB); beyond: refused"
    )
    retry_min_s: float = Field(2.0, gt=0, le=3600, description="first wait after a failure")
    retry_max_s: float = Field(60.0, gt=0, le=86400, description="longest wait (doubling)")
    timeout_s: float = Field(30.0, gt=0, le=600, description="association / request timeout")
    identity: str = Field(
        "ask",
        pattern=r"^(ask|worklist)$",
        description="'ask': the console asks for the patient; 'worklist': it may pick one "
        "from the Modality Worklist (worklist_*)",
    )
    worklist_host: str | None = Field(None, description="None: the archive's host")
    worklist_port: RemotePort | None = Field(None, description="None: the archive's")
    worklist_ae: str | None = Field(None, description="None: called_ae")
    station_ae: str | None = Field(
        None, description="Scheduled Station AE Title the worklist is asked for (None: any)"
    )
    institution: str = Field("", max_length=64, description="Institution Name")
    station_name: str = Field("humantele", max_length=16, description="Station Name")
    operator: str = Field("", max_length=64, description="the expert (Operators' Name)")
    performing_physician: str = Field(
        "", max_length=64, description="Performing Physician's Name (the expert sonographer)"
    )
    remote_site: str = Field(
        "", max_length=64, description="the clinic where the follower scans (recorded in DICOM)"
    )
    clip_quality: int = Field(
        88, ge=30, le=100, description="JPEG quality of a whole scan's frames (sent live)"
    )
    send_scans: bool = Field(
        False,
        description="archive every scan whole at its end (false: only a scan the console's "
        "'Archive scan' asks for)",
    )
    scan_fps: float = Field(
        10.0, gt=0, le=60, description="frames a second kept of a scan for its multi-frame"
    )
    scan_max_frames: int = Field(
        1200, ge=2, le=100_000, description="frames kept of one scan; beyond: every other "
        "dropped and the rate halved (the whole scan, at a lower rate)",
    )  # fmt: skip
    scan_max_mb: float = Field(
        60.0, gt=0, le=4000, description="JPEG bytes kept of one scan (MB); beyond: as above"
    )

    @field_validator("called_ae", "calling_ae")
    @classmethod
    def _ae(cls, v: str) -> str:
        return _ae_title(v)

    @field_validator("worklist_ae", "station_ae")
    @classmethod
    def _ae_opt(cls, v: str | None) -> str | None:
        return None if v is None else _ae_title(v)

    @field_validator("stow_url")
    @classmethod
    def _url(cls, v: str | None) -> str | None:
        if v is not None and not re.match(r"^https?://[^\s/]+", v):
            raise ValueError(f"stow_url {v!r}: an http(s) URL")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> ArchiveConfig:
        if self.protocol == "stow" and not self.stow_url:
            raise ValueError("stow_url: protocol = 'stow' needs the DICOMweb base URL")
        if self.tls and not self.tls_ca_file:
            raise ValueError("tls_ca_file: tls = true needs the CA the archive's cert is on")
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            raise ValueError("tls_key_file: give both tls_cert_file and tls_key_file, or none")
        if self.retry_max_s < self.retry_min_s:
            raise ValueError("retry_max_s: must be >= retry_min_s")
        return self
