"""The follower's pose-stream figures: the recent tail apart from the whole run's."""

from humantele.follower.figures import RECENT_POSES, PoseStreamFigures


def test_the_recent_p99_is_the_last_poses_alone():
    """A slow start (the first poses 50 ms old) stays in the run's p99 and leaves the recent
    one, which is the last ``RECENT_POSES`` poses' (1 ms, one in a hundred at 3 ms)."""
    f = PoseStreamFigures()
    for i in range(2 * RECENT_POSES):
        late = i < RECENT_POSES
        f.add(i * 0.01, 0.050 if late else (0.003 if i % 100 == 0 else 0.001))
    s = f.stats(2 * RECENT_POSES * 0.01)
    assert s["pose_age_p99_ms"] == 50.0
    assert s["pose_age_recent_p99_ms"] == 1.0
    f.add(99.0, 0.004)  # the newest counts at once
    assert f.stats(99.0)["pose_age_last_ms"] == 4.0
