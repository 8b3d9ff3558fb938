import json
import math
import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from humantele.geometry import Pose, quat_from_axis_angle
from humantele.wire import (
    POSE_SIZE,
    PROTOCOL_VERSION,
    STATE_SIZE,
    TRACKING_CODES,
    Bye,
    CalibrationProgress,
    EllipsoidModel,
    Hello,
    Ping,
    Pong,
    PoseMessage,
    Scan,
    StateMessage,
    TrackingStatus,
    UsScale,
    WireError,
    encode_control,
    parse_control,
)

Q = (0.0, 0.0, 0.0, 1.0)
ELL = '{"type": "ellipsoid", "model": {"center": %s, "semi_axes": %s, "heading": 0}}'


def _pose(**kw):
    base = dict(seq=7, t_sent=12.5, position=(0.1, -0.2, 0.3), quaternion=Q, buttons=2, clutch=True)
    base.update(kw)
    return PoseMessage(**base)


def _state(**kw):
    base = dict(
        seq=9,
        t_sent=3.25,
        position=(0.01, 0.02, 0.03),
        quaternion=Q,
        tracking=TrackingStatus.PREDICTED,
        force=(0.5, -1.0, 4.0),
        contact=True,
    )
    base.update(kw)
    return StateMessage(**base)


finite = st.floats(-5.0, 5.0, allow_nan=False)


@given(
    seq=st.integers(0, 2**32 - 1),
    t=st.floats(0, 1e9),
    p=st.tuples(finite, finite, finite),
    axis=st.tuples(finite, finite, finite).filter(lambda a: math.hypot(*a) > 1e-3),
    angle=st.floats(-math.pi, math.pi),
    buttons=st.integers(0, 255),
    clutch=st.booleans(),
)
def test_pose_round_trip(seq, t, p, axis, angle, buttons, clutch):
    q = tuple(float(v) for v in quat_from_axis_angle(axis, angle))
    m = PoseMessage(seq, t, p, q, buttons, clutch)
    b = m.encode()
    assert len(b) == POSE_SIZE == 72
    assert PoseMessage.decode(b) == m


def test_state_round_trip_and_pose_helpers():
    s = _state()
    b = s.encode()
    assert len(b) == STATE_SIZE == 96
    back = StateMessage.decode(b)
    assert back == s and back.tracking is TrackingStatus.PREDICTED
    pose = Pose(np.array([0.1, 0.2, 0.3]), quat_from_axis_angle([0, 1, 0], 0.5))
    m = PoseMessage.from_pose(2**32 + 5, 1.0, pose)
    assert m.seq == 5  # wraps into u32
    assert np.allclose(PoseMessage.decode(m.encode()).pose.position, pose.position)


@pytest.mark.parametrize(
    "data, reason",
    [
        (b"", "size"),
        (_pose().encode()[:-1], "size"),
        (_pose().encode() + b"\0", "size"),
        (bytes([PROTOCOL_VERSION + 1]) + _pose().encode()[1:], "version"),
        (_state().encode()[:1] + bytes([2]) + _pose().encode()[2:], "kind"),
        (_pose().encode()[:-1] + b"\x02", "field"),  # clutch flag must be 0/1
        ("text", "type"),
    ],
)
def test_bad_pose_bytes(data, reason):
    with pytest.raises(WireError) as err:
        PoseMessage.decode(data)
    assert err.value.reason == reason


def _patch_double(data: bytes, offset: int, value: float) -> bytes:
    return data[:offset] + struct.pack("<d", value) + data[offset + 8 :]


@pytest.mark.parametrize(
    "offset, value, reason",
    [
        (6, math.nan, "nonfinite"),  # t_sent
        (14, math.inf, "nonfinite"),  # position x
        (22, 11.0, "range"),  # position y beyond 10 m
        (38, 0.5, "quaternion"),  # x component: not unit any more
        (62, math.nan, "nonfinite"),  # w
    ],
)
def test_bad_pose_numbers_are_refused(offset, value, reason):
    with pytest.raises(WireError) as err:
        PoseMessage.decode(_patch_double(_pose().encode(), offset, value))
    assert err.value.reason == reason


def test_every_tracking_status_has_one_wire_code_and_round_trips():
    assert sorted(TRACKING_CODES.values()) == list(range(len(TrackingStatus)))
    for status in TrackingStatus:
        raw = _state(tracking=status).encode()
        assert raw[70] == TRACKING_CODES[status]
        back = StateMessage.decode(raw).tracking
        assert back is status and back == str(status)  # the same words as the tracker's
    assert StateMessage.decode(_state(tracking="ambiguous").encode()).tracking == "ambiguous"
    with pytest.raises(WireError, match="tracking status 'searching' is unknown"):
        _state(tracking="searching").encode()


def test_bad_state_fields():
    good = _state().encode()
    with pytest.raises(WireError, match="tracking"):
        StateMessage.decode(good[:70] + b"\x07" + good[71:])
    with pytest.raises(WireError) as err:
        StateMessage.decode(_patch_double(good, 71, math.nan))  # force x
    assert err.value.reason == "nonfinite"
    with pytest.raises(WireError) as err:
        StateMessage.decode(_patch_double(good, 71, 1000.0))
    assert err.value.reason == "range"
    with pytest.raises(WireError) as err:
        StateMessage.decode(good[:-1] + b"\x05")
    assert err.value.reason == "field"
    with pytest.raises(WireError) as err:
        PoseMessage.decode(good)  # a state on the pose channel
    assert err.value.reason == "size"


def test_encode_refuses_what_decode_would():
    for bad in (
        _pose(position=(math.nan, 0, 0)),
        _pose(quaternion=(0, 0, 0, 2.0)),
        _pose(seq=-1),
        _pose(buttons=300),
        _pose(position=(0.0, 0.0)),
    ):
        with pytest.raises(WireError):
            bad.encode()
    with pytest.raises(WireError):
        _state(force=(0.0, math.inf, 0.0)).encode()


def test_control_round_trip():
    msgs = [
        Hello(role="expert", software="x"),
        EllipsoidModel(model={"center": [0, 0.1, 0], "semi_axes": [10, 0.1, 0.15], "heading": 0.2}),
        CalibrationProgress(event="point", index=2, point=(0.1, 0.0, -0.2)),
        Scan(action="start", scan_id="s-01"),
        Ping(seq=3, t0=1.5),
        Pong(seq=3, t0=1.5, t1=2.0, t2=2.1),
        Bye(reason="done"),
        UsScale(pixel_spacing_mm=(0.2, 0.25), depth_origin_row=96.0),
    ]
    for m in msgs:
        assert parse_control(encode_control(m)) == m


def test_ellipsoid_payload_matches_haptics_to_dict():
    from humantele.haptics.ellipsoid import Ellipsoid

    e = Ellipsoid.from_dict(
        {"center": [0.0, 0.1, 0.2], "semi_axes": [10.0, 0.1, 0.15], "heading": 0.3}
    )
    text = json.dumps({"type": "ellipsoid", "model": e.to_dict()})
    msg = parse_control(text)
    assert Ellipsoid.from_dict(msg.model.model_dump()).to_dict() == e.to_dict()


@pytest.mark.parametrize(
    "text, reason",
    [
        ("{not json", "json"),
        ('{"type": "nope"}', "schema"),
        ('{"type": "ping", "seq": 1}', "schema"),
        ('{"type": "ping", "seq": 1, "t0": NaN}', "schema"),
        ('{"type": "ping", "seq": 1, "t0": 1, "extra": 2}', "schema"),
        (
            ELL % ("[0, 0]", "[1, 1, 1]"),
            "schema",
        ),
        (
            ELL % ("[0, 0, 0]", "[1, -1, 1]"),
            "schema",
        ),
        ('{"type": "scan", "action": "start", "scan_id": "Jane Doe"}', "schema"),
        ('{"type": "hello", "role": "expert", "software": "' + "x" * 20000 + '"}', "too_long"),
        ("[]", "schema"),
        ('{"type": "us_scale", "pixel_spacing_mm": [0, 0.2], "depth_origin_row": 9}', "schema"),
        ('{"type": "us_scale", "pixel_spacing_mm": [0.2, 0.2], "depth_origin_row": -1}', "schema"),
        ('{"type": "us_scale", "pixel_spacing_mm": [0.2], "depth_origin_row": 9}', "schema"),
    ],
)
def test_bad_control(text, reason):
    with pytest.raises(WireError) as err:
        parse_control(text)
    assert err.value.reason == reason
