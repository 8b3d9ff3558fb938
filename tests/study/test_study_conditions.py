"""The study's conditions file: the shipped ones parse; bad input is refused naming the field."""

from pathlib import Path

import pytest

from humantele.config import ConfigError
from humantele.study.cli import auto_jobs, parse_jobs, servo_ok
from humantele.study.conditions import load_conditions
from humantele.study.session import netem_config, scans_done, write_configs

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

GOOD = """
[study]
scans = 3
scan_s = 10.0
gap_s = 2.5
seeds = [4, 7]

[[condition]]
name = "a"
delay_ms = 120.0
jitter_ms = 10.0
loss_pct = 2.5
bandwidth_kbps = 1500

[[condition]]
name = "b"
"""


def _load(tmp_path, text: str):
    path = tmp_path / "c.toml"
    path.write_text(text)
    return load_conditions(path)


def test_a_good_file_gives_one_run_per_condition_and_seed(tmp_path):
    study = _load(tmp_path, GOOD)
    assert [r.run_id for r in study.runs()] == ["a-s4", "a-s7", "b-s4", "b-s7"]
    a = study.condition[0]
    assert (a.delay_ms, a.jitter_ms, a.loss_pct, a.bandwidth_kbps) == (120.0, 10.0, 2.5, 1500.0)
    assert study.condition[1].delay_ms == 0.0 and not study.condition[1].impaired
    spec = study.runs()[1].spec(study.study)
    assert spec["seed"] == 7 and spec["scans"] == 3 and spec["condition"]["name"] == "a"
    # the emulator gets SI units and the run's seed
    n = netem_config(spec)
    assert (n.delay_s, n.jitter_s, n.loss, n.bandwidth_kbps, n.seed) == (0.12, 0.01, 0.025,
                                                                          1500.0, 7)  # fmt: skip


def test_the_shipped_conditions_files_parse():
    delays = load_conditions(CONFIGS / "study-delays.toml")
    assert len(delays.condition) == 10
    assert {c.name for c in delays.condition} >= {"lan", "750km", "d400", "d50-loss10"}
    assert max(c.delay_ms for c in delays.condition) == 400.0
    assert max(c.loss_pct for c in delays.condition) == 10.0
    assert any(c.bandwidth_kbps for c in delays.condition)
    tiny = load_conditions(CONFIGS / "study-tiny.toml")
    assert len(tiny.runs()) == 2 and tiny.study.scans == 1


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('[[condition]]\nname = "x"\nloss_pct = 60.0\n', "condition.0.loss_pct"),
        ('[[condition]]\nname = "x"\ndelay_ms = -1.0\n', "condition.0.delay_ms"),
        ('[[condition]]\nname = "x"\ndelay_ms = "40"\n', "condition.0.delay_ms"),
        ('[[condition]]\nname = "x"\njitter_ms = nan\n', "condition.0.jitter_ms"),
        ('[[condition]]\nname = "x"\nbandwidth_kbps = -5\n', "condition.0.bandwidth_kbps"),
        ('[[condition]]\nname = "x"\n[[condition]]\nname = "y"\nlos_pct = 1.0\n',
         "condition.1.los_pct"),
        ('[[condition]]\nname = "has space"\n', "condition.0.name"),
        ('[[condition]]\ndelay_ms = 1.0\n', "condition.0.name"),
        ('[[condition]]\nname = "x"\n[[condition]]\nname = "x"\n', "used twice"),
        ('[study]\nscans = 0\n[[condition]]\nname = "x"\n', "study.scans"),
        ('[study]\nscans = 1.5\n[[condition]]\nname = "x"\n', "study.scans"),
        ('[study]\nseeds = [1, 1]\n[[condition]]\nname = "x"\n', "seeds"),
        ('[study]\nseeds = []\n[[condition]]\nname = "x"\n', "study.seeds"),
        ('[study]\ngap_s = 0.5\n[[condition]]\nname = "x"\n', "study.gap_s"),
        ('[study]\nvideo = "yes"\n[[condition]]\nname = "x"\n', "study.video"),
        ('[study]\nscans = 1\n', "condition"),
        ("[study\n", "not valid TOML"),
    ],
)  # fmt: skip
def test_bad_input_is_refused_with_the_field(tmp_path, text, field):
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, text)
    assert field in str(e.value)
    assert "c.toml" in str(e.value)  # and the file


def test_the_run_configs_carry_the_condition_seed_scans_and_relay(tmp_path):
    from humantele.config import load_config
    from humantele.expert.daemon import ExpertConfig
    from humantele.follower.daemon import FollowerConfig
    from humantele.haptics.servo_config import ServoConfig
    from humantele.transport.config import IceServer

    study = _load(tmp_path, GOOD)
    spec = study.runs()[0].spec(study.study)
    ice = {
        r: IceServer(urls=[f"turn:127.0.0.1:{p}?transport=udp"], username="u", credential="pw")
        for r, p in (("expert", 4000), ("follower", 4001))
    }
    write_configs(tmp_path / "conf", spec, ice)
    e = load_config(ExpertConfig, tmp_path / "conf" / "expert.toml", "expert")
    f = load_config(FollowerConfig, tmp_path / "conf" / "follower.toml", "follower")
    s = load_config(ServoConfig, tmp_path / "conf" / "expert.toml", "servo")
    assert e.link.relay_only and e.link.ice_servers[0].urls == ["turn:127.0.0.1:4000?transport=udp"]
    assert f.link.relay_only and f.link.ice_servers[0].urls == ["turn:127.0.0.1:4001?transport=udp"]
    assert e.scans.repeat and e.scans.length_s == 10.0 and e.scans.gap_s == 2.5
    assert e.video.enabled and f.video.enabled
    # the US picture's SSIM (study/quality.py) needs the expert's encoded US frames and the
    # follower's JPEG of the captures: without them the study's SSIM column stayed empty
    assert e.video.record_encoded and f.video.record_us_hz > 0
    assert s.device.seed == 4 and f.clinic.novice.seed == 4
    assert (tmp_path / "conf").stat().st_mode & 0o077 == 0  # the TURN credential is private


def test_jobs_follow_the_free_cores_and_the_servo_budget():
    assert auto_jobs(2, 0.0, 10) == 2
    assert auto_jobs(2, 0.4, 10) == 1
    assert auto_jobs(2, 6.0, 10) == 1  # a busy machine: still one at a time
    assert auto_jobs(8, 1.0, 3) == 3  # never more than there are runs
    assert parse_jobs("3", 10) == 3
    for bad in ("x", "0", "65"):
        with pytest.raises(ConfigError, match="--jobs"):
            parse_jobs(bad, 10)
    good = {"demo": {"servo_rate_hz": 1000.0, "servo_overruns": 5, "duration_s": 60.0}}
    assert servo_ok(good)
    assert not servo_ok({"demo": {"servo_rate_hz": 950.0, "servo_overruns": 0}})
    assert not servo_ok({"demo": {"servo_rate_hz": 1000.0, "servo_overruns": 500,
                                  "duration_s": 60.0}})  # fmt: skip
    assert not servo_ok({"demo": {}})


def test_the_run_stops_once_the_expert_stopped_its_last_scan():
    assert not scans_done(None, 2)
    assert not scans_done({"scans_started": 1, "scan": None}, 2)  # between scans
    assert not scans_done({"scans_started": 2, "scan": 2}, 2)  # the last one runs
    assert scans_done({"scans_started": 2, "scan": None}, 2)
