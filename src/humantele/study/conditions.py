"""The study's conditions file (TOML): what to run, how many scans, which seeds.

::

    [study]
    scans = 2          # scans per session (the expert's scripted scans)
    scan_s = 20.0      # each scan's length (s)
    gap_s = 3.0        # between scans (s)
    seeds = [1, 2]     # each condition runs once per seed (emulator, sim devices, novice)

    [[condition]]
    name = "750km"
    delay_ms = 4.0     # one way, added each way (ms)
    jitter_ms = 1.5    # std dev of the added delay (ms; FIFO: no reordering)
    loss_pct = 0.0     # datagrams lost each way (%)
    bandwidth_kbps = 0 # link rate each way (kbit/s); 0: no cap

A condition with a seed is a *run*: one whole session (``run_id`` = ``NAME-sSEED``). Every
field is checked strictly (a string is never a number); a bad value is refused with the
file, the field (``condition.3.loss_pct``) and the reason.
"""

from __future__ import annotations

from pathlib import Path
from typing import Self

from pydantic import Field, model_validator

from humantele.config import ConfigError, ConfigModel, read_config_file, validate_config

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,47}$"


class StudySettings(ConfigModel):
    """``[study]``: the sessions' shape, the same for every condition."""

    scans: int = Field(2, ge=1, le=50)
    scan_s: float = Field(20.0, ge=2.0, le=3600.0)
    gap_s: float = Field(3.0, ge=2.0, le=600.0)  # >= 2 s: the runner stops in the last gap
    seeds: list[int] = Field(default_factory=lambda: [1], min_length=1, max_length=50)
    video: bool = True  # the follower's US and POV tracks over the link
    setup_timeout_s: float = Field(180.0, ge=10.0, le=3600.0)  # start to scan 1, at most

    @model_validator(mode="after")
    def _distinct_seeds(self) -> Self:
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds: each seed once ({self.seeds})")
        return self


class Condition(ConfigModel):
    """One ``[[condition]]``: the link's impairment, applied each way (SI at the edges: ms, %,
    kbit/s, as people write them)."""

    name: str = Field(pattern=NAME_PATTERN)
    delay_ms: float = Field(0.0, ge=0.0, le=1000.0)
    jitter_ms: float = Field(0.0, ge=0.0, le=500.0)
    loss_pct: float = Field(0.0, ge=0.0, le=50.0)
    bandwidth_kbps: float = Field(0.0, ge=0.0, le=1_000_000.0)

    @property
    def impaired(self) -> bool:
        return bool(self.delay_ms or self.jitter_ms or self.loss_pct or self.bandwidth_kbps)

    def label(self) -> str:
        """``4 ms +- 1.5, 1 % loss, 2000 kbit/s`` (what differs from a clean link)."""
        parts = [f"{self.delay_ms:g} ms" + (f" ± {self.jitter_ms:g}" if self.jitter_ms else "")]
        if self.loss_pct:
            parts.append(f"{self.loss_pct:g} % loss")
        if self.bandwidth_kbps:
            parts.append(f"{self.bandwidth_kbps:g} kbit/s")
        return ", ".join(parts)


class StudyFile(ConfigModel):
    """The whole file: ``[study]`` and at least one ``[[condition]]`` (names unique)."""

    study: StudySettings = Field(default_factory=StudySettings)
    condition: list[Condition] = Field(min_length=1, max_length=200)

    @model_validator(mode="after")
    def _unique_names(self) -> Self:
        seen: set[str] = set()
        for c in self.condition:
            if c.name in seen:
                raise ValueError(f"condition name {c.name!r} is used twice")
            seen.add(c.name)
        return self

    def runs(self) -> list[Run]:
        """Every (condition, seed), conditions in file order, seeds inner."""
        return [Run(c, s) for c in self.condition for s in self.study.seeds]


class Run:
    """One session to record: a condition with one seed."""

    def __init__(self, condition: Condition, seed: int) -> None:
        self.condition = condition
        self.seed = seed

    @property
    def run_id(self) -> str:
        return f"{self.condition.name}-s{self.seed}"

    def spec(self, settings: StudySettings) -> dict:
        """What the run is, as JSON (kept with its recordings; a later run compares it)."""
        return {
            "condition": self.condition.model_dump(),
            "seed": self.seed,
            "scans": settings.scans,
            "scan_s": settings.scan_s,
            "gap_s": settings.gap_s,
            "video": settings.video,
        }

    def __repr__(self) -> str:
        return f"Run({self.run_id})"


def load_conditions(path: str | Path) -> StudyFile:
    """Read and check a conditions file; ConfigError naming the file, field and reason."""
    data = read_config_file(path)
    if "condition" not in data:
        raise ConfigError(f"{path}: condition: no [[condition]] table (at least one is needed)")
    return validate_config(StudyFile, data, str(path))
