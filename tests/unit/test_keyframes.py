import numpy as np

from fleetmap.geometry import pose_from_tum
from fleetmap.keyframes import KeyframePolicy, select_keyframes


def _line(n, step_m):
    return [pose_from_tum([i * step_m, 0, 0], [0, 0, 0, 1]) for i in range(n)]


def test_translation_rotation_and_time():
    stamps = np.arange(21) * 0.01  # 0.2 s total: no time-triggered keyframe
    kf = select_keyframes(stamps, _line(21, 0.011), KeyframePolicy(0.05, 5.0, 1.0))
    assert kf == [0, 5, 10, 15, 20]
    half = np.radians(1.1 * np.arange(21)) / 2
    yaw = [pose_from_tum([0, 0, 0], [0, 0, np.sin(h), np.cos(h)]) for h in half]
    assert select_keyframes(stamps, yaw, KeyframePolicy(1.0, 5.0, 1.0)) == [0, 5, 10, 15, 20]
    still = _line(31, 0.0)
    assert select_keyframes(np.arange(31) * 0.1, still, KeyframePolicy()) == [0, 10, 20, 30]


def test_without_poses_only_time_counts():
    assert select_keyframes(np.arange(5) * 0.6, [None] * 5, KeyframePolicy()) == [0, 2, 4]
    assert select_keyframes([], [], KeyframePolicy()) == []


def test_real_recording_keyframes_are_spread(sun3d):
    from fleetmap.dataset import read_recording
    from fleetmap.extract import keyframe_indices

    rec = read_recording(sun3d / "robot_b")
    kf = keyframe_indices(rec)
    assert 8 <= len(kf) <= 25 and kf[0] == 0
