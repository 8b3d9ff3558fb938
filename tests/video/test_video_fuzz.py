"""Fuzz: arbitrary poses and forces (finite or not) never crash the sim sources; unusable
input gives a dark or blank frame and is counted."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from video_helpers import P

from fuzz_examples import examples
from humantele.geometry import Pose
from humantele.video.counter import patch_size
from humantele.video.scene import SceneSnapshot, pose_is_finite
from humantele.video.sim_pov import SimPov, SimPovConfig
from humantele.video.sim_ultrasound import SimUltrasound, SimUltrasoundConfig

US = SimUltrasound(SimUltrasoundConfig(width=192, height=144, beams=48, samples=96))
POV = SimPov(SimPovConfig(width=192, height=108))
CW, CH = patch_size()
US_MASK = US.geometry.fov_mask.copy()
US_MASK[:CH, :CW] = False  # the frame counter may lie over the field of view


def us_max(frame) -> int:
    return int(frame.image[..., 0][US_MASK].max())


anything = st.floats(allow_nan=True, allow_infinity=True, width=64)
near = st.floats(-2.0, 2.0)


def raw_pose(position, quaternion) -> Pose:
    """A Pose when the values make one, else one built around Pose's check (as a corrupted
    message or a bug elsewhere could hand over)."""
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return Pose(np.array(position), np.array(quaternion))
    except ValueError:
        pose = object.__new__(Pose)
        object.__setattr__(pose, "position", np.array(position, dtype=float))
        object.__setattr__(pose, "quaternion", np.array(quaternion, dtype=float))
        return pose


vec3 = st.one_of(st.tuples(near, near, near), st.tuples(anything, anything, anything))
quat = st.tuples(anything, anything, anything, anything)
poses = st.one_of(st.none(), st.builds(raw_pose, vec3, quat))
forces = st.one_of(st.floats(-10.0, 50.0), anything)


def expected_valid(force, *ps) -> bool:
    return math.isfinite(force) and all(p is None or pose_is_finite(p) for p in ps)


@settings(max_examples=examples(150), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tip=poses, force=forces)
def test_sim_us_never_crashes(tip, force):
    before = US.counters.invalid
    frame = US.render(SceneSnapshot(0.0, P, tip, force, None))
    assert frame.image.shape == (144, 192, 3) and frame.image.dtype == np.uint8
    q = frame.meta["quality"]
    assert 0.0 <= q <= 1.0
    if not expected_valid(force, tip):
        assert US.counters.invalid == before + 1 and not frame.meta["valid"]
        assert q == 0.0
        assert us_max(frame) < 40  # dark
    elif frame.meta["valid"]:
        assert US.counters.invalid == before


@settings(max_examples=examples(100), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(head=poses, tip=poses, virtual=poses, force=forces)
def test_sim_pov_never_crashes(head, tip, virtual, force):
    before = POV.counters.invalid
    frame = POV.render(SceneSnapshot(0.0, P, tip, force, head, virtual))
    assert frame.image.shape == (108, 192, 3) and frame.image.dtype == np.uint8
    if not expected_valid(force, head, tip, virtual):
        assert POV.counters.invalid == before + 1 and not frame.meta["valid"]
        rest = frame.image.copy()
        rest[:CH, :CW] = POV.config.wall  # all but the counter is the blank wall
        assert np.all(rest == np.array(POV.config.wall, dtype=np.uint8))
    else:
        assert POV.counters.invalid == before


@settings(max_examples=examples(40), deadline=None)
@given(x=st.floats(-0.3, 0.3), z=st.floats(-0.15, 0.15), f=st.floats(0.0, 30.0))
def test_sim_us_probe_anywhere_on_the_body(x, z, f):
    """Any place on the skin, any force: a frame, the quality in [0, 1], dark without force."""
    from humantele.video.scene import probe_on_skin

    frame = US.render(SceneSnapshot(0.0, P, probe_on_skin(P, (x, 0.0, z)), f, None))
    assert frame.meta["valid"] and 0.0 <= frame.meta["quality"] <= 1.0
    if f < US.config.min_force_n:
        assert us_max(frame) < 40
