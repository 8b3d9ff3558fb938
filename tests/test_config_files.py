"""The configuration files: packaged named definitions and the repository's editable examples.

Named definitions (tools, HID profiles, force sensor set-ups) have one copy, inside the package
(src/humantele/defaults/), read through importlib.resources; configs/ holds the daemons'
example files, which must load with their models (a renamed or moved field shows up here).
"""

import subprocess
import sys
from pathlib import Path

import pytest

from humantele.config import ConfigError, defaults_dir, load_config, named_config_path
from humantele.expert.config import ExpertConfig
from humantele.follower.daemon import FollowerConfig
from humantele.follower.sensing import SensingConfig
from humantele.forcesense.sensors import ForceSensorConfig, load_force_config
from humantele.haptics.devices.hid import HidProfile, load_profile
from humantele.haptics.servo_config import ServoConfig
from humantele.signaling.server import SignalConfig
from humantele.tracking.tool import ToolDefinition, load_tool

EXAMPLES = Path(__file__).resolve().parents[1] / "configs"
PACKAGED = {"tools": ToolDefinition, "hid": HidProfile, "forcesense": ForceSensorConfig}


def test_every_packaged_definition_loads_by_name_and_lives_in_the_package():
    import humantele

    package = Path(humantele.__file__).parent
    assert defaults_dir() == package / "defaults"
    found = set()
    for folder, model in PACKAGED.items():
        for f in sorted(defaults_dir(folder).glob("*.toml")):
            assert named_config_path(folder, f.stem) == f
            load_config(model, f)
            found.add(f"{folder}/{f.stem}")
    assert {"tools/probe_default", "hid/spacemouse", "forcesense/sim", "forcesense/hid"} <= found
    assert load_tool("probe_default").markers.shape == (4, 3)
    assert load_profile("spacemouse").vendor_ids
    assert load_force_config("hid").sensor.backend == "hid"
    assert not (EXAMPLES / "tools").exists()  # one copy: no second one to drift


def test_unknown_names_list_the_packaged_ones_and_paths_are_read_as_given(tmp_path):
    with pytest.raises(
        ConfigError, match=r"'probe_x': no such tool \(known tools: probe_default, reference_"
    ):
        load_tool("probe_x")
    with pytest.raises(
        ConfigError, match=r"no such force sensor set-up \(known force sensor set-ups: hid, sim\)"
    ):
        load_force_config("usb")
    with pytest.raises(ConfigError, match="no such HID profile"):
        load_profile("../tools/probe_default")  # a name is a name, never a path inside
    mine = tmp_path / "mine.toml"
    mine.write_text((defaults_dir("tools") / "probe_default.toml").read_text())
    assert load_tool(str(mine)).tip.tolist() == load_tool().tip.tolist()
    with pytest.raises(ConfigError, match="no such tool definition file"):
        load_tool(str(tmp_path / "absent.toml"))


@pytest.mark.parametrize(
    ("name", "sections"),
    [
        ("expert.toml", {"expert": ExpertConfig, "servo": ServoConfig}),
        ("follower.toml", {"follower": FollowerConfig, "sensing": SensingConfig}),
        ("follower_hololens.toml", {"follower": FollowerConfig, "sensing": SensingConfig}),
        ("signal.toml", {None: SignalConfig}),
    ],
)
def test_example_configs_load_with_their_models(name, sections):
    for section, model in sections.items():
        load_config(model, EXAMPLES / name, section)


def test_the_follower_example_shows_the_sensing_defaults_with_their_backends():
    sensing = load_config(SensingConfig, EXAMPLES / "follower.toml", "sensing")
    assert sensing == SensingConfig()
    assert sensing.camera.backend == "sim" and sensing.force.sensor.backend == "sim"
    servo = load_config(ServoConfig, EXAMPLES / "expert.toml", "servo")
    assert servo.device.backend == "sim"


def test_the_hololens_example_is_a_real_clinic_with_every_device_it_needs():
    """configs/follower_hololens.toml (README "With real hardware"): the devices clinic, hl2ss
    with the rig pose and a saved calibration, the HID force board with its calibration, a
    capture card for the US with its pixel spacing, a camera for the POV; no sim backend."""
    path = EXAMPLES / "follower_hololens.toml"
    follower = load_config(FollowerConfig, path, "follower")
    sensing = load_config(SensingConfig, path, "sensing")
    assert follower.clinic.backend == "devices" and follower.probe_source == "pipeline"
    assert follower.feed.enabled and follower.feed.tls  # WebXR needs https
    camera = sensing.camera
    assert camera.backend == "hl2ss" and camera.mode == 1 and camera.port == 3804
    assert camera.calibration_file == "hl2ss_ahat.json"
    assert sensing.force.sensor.backend == "hid" and sensing.force.calibration_file
    assert follower.video.enabled and not follower.video.stamp_counter
    assert follower.video.us.backend == "opencv" and follower.video.us.pixel_spacing_mm
    assert follower.video.pov.backend == "opencv"


@pytest.mark.e2e  # runs a Python process (the fast lane leaves it out)
def test_loading_the_hololens_example_imports_nothing_of_the_simulator():
    """Reading a real clinic's file builds no simulated world (checked in a fresh process:
    this one has the simulator loaded by other tests)."""
    code = (
        "import sys; from humantele.config import load_config; "
        "from humantele.follower.daemon import FollowerConfig; "
        "from humantele.follower.sensing import SensingConfig; "
        "from humantele.follower.clinic import simulator_modules; "
        f"p = {str(EXAMPLES / 'follower_hololens.toml')!r}; "
        "load_config(FollowerConfig, p, 'follower'); load_config(SensingConfig, p, 'sensing'); "
        "print(','.join(simulator_modules()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


def test_the_configs_readme_lists_every_example_file():
    listed = (EXAMPLES / "README.md").read_text()
    for f in sorted(EXAMPLES.glob("*.toml")):
        assert f"`{f.name}`" in listed, f"configs/README.md does not describe {f.name}"
