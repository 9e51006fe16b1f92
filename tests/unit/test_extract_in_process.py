"""A small extraction runs in the caller's process (`extract_keyframes` with fewer than 8
keyframes): it must not leave that process's OpenCV on one thread, where the embedded
aligner and place database of `fleetmap merge` run after it."""

from pathlib import Path

import cv2

from fleetmap.dataset import read_recording
from fleetmap.extract import keyframe_indices
from fleetmap.extract_pool import extract_keyframes

PAIR = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


def test_in_process_extraction_leaves_opencv_threads_as_they_were():
    recs = [read_recording(PAIR / r, robot_id=r) for r in ("alpha", "bravo")]
    before = cv2.getNumThreads()
    kfs = list(extract_keyframes(recs, {r.robot_id: keyframe_indices(r) for r in recs}))
    assert {k.robot_id for k in kfs} == {"alpha", "bravo"}
    assert cv2.getNumThreads() == before
