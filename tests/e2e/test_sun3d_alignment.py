"""The alignment pipeline on the real SUN3D pair (wide baseline, self-similar study room):
every keyframe pair of the two robots at once, parts of them, the robots swapped, another
building; and the aligner's gated transform registered as a link in the place database.
Real alignments of dozens of view pairs each: seconds to a minute apiece."""

import numpy as np
import pytest

from fleetmap.align import align_views
from fleetmap.camera import TUM_FR1
from fleetmap.correspondences import RGBDView
from fleetmap.dataset import read_recording
from fleetmap.frame import encode
from fleetmap.geometry import transform_error
from fleetmap.place import PlaceDB
from tests.conftest import imread, read_tum_pose
from tests.covis import covisibility

pytestmark = pytest.mark.slow


def test_sun3d_wide_baseline_recovers_the_ground_truth(sun3d, sun3d_alignment):
    """Self-similar study room seen 60-90 degrees apart: the largest visual consensus is a
    look-alike cubicle 0.9 m away; per-pair hypotheses judged by free space find the right
    one, and a rival is reported."""
    T_gt = np.loadtxt(sun3d / "T_a_b.txt")
    res = sun3d_alignment
    assert res.merged, res.reason
    dt, dr = transform_error(res.T_a_b, T_gt)
    assert dt < 0.05 and dr < 2.0, (dt, dr, res.to_dict())
    assert res.hypotheses[0]["consistency"] > 0.7
    assert any(h["score"] < 0.8 * res.hypotheses[0]["score"] for h in res.hypotheses[1:])


def test_different_places_are_not_merged(sun3d_views, tum_pairs):
    """The study room against a TUM office desk: no pair of them overlaps."""
    va = sun3d_views["robot_a"]
    vb = []
    for case in sorted(tum_pairs.glob("case_*")):
        for k in ("prev", "curr"):
            vb.append(
                RGBDView(
                    imread(case / f"img_{k}.png"),
                    imread(case / f"dep_{k}.png"),
                    TUM_FR1,
                    read_tum_pose(case / f"pose_{k}.txt"),
                )
            )
    res = align_views([(a, b) for a in va for b in vb])
    assert not res.merged and res.reason, res.to_dict()
    # the desk's few frames laid on the room's planes fit at 0.95 consistency on half the
    # desk, but cover a few % of the room: the geometry does not decide on its own
    assert "need 6" not in res.reason, res.reason


@pytest.mark.parametrize(
    "part_a, part_b, swap",
    [
        (slice(None), slice(0, 7), False),
        (slice(None), slice(7, None), False),  # once merged 0.77 m off: the free-space gate
        (slice(0, 5), slice(None), False),
        # a verdict at the margin: refused as ambiguous in the recordings' frames (a rival
        # at 0.906 of the best); in 4 of 6 random frame pairs merged 19-30 cm off the SfM
        # truth, over this test's 15 cm (10 cm RMS over B's points in one); ICP started at the
        # truth slides there too (docs/ALIGNER.md, session 25)
        (slice(5, None), slice(None), False),
        (slice(None), slice(None), True),
    ],
)
def test_sun3d_parts_are_merged_right_or_not_at_all(sun3d, sun3d_views, part_a, part_b, swap):
    """Less overlap (parts of either robot) or the robots' roles swapped: the answer is
    near the ground truth (15 cm / 3 deg, i.e. not a look-alike place) or no merge."""
    T_gt = np.loadtxt(sun3d / "T_a_b.txt")
    va = sun3d_views["robot_a"][part_a]
    vb = sun3d_views["robot_b"][part_b]
    if swap:
        va, vb, T_gt = vb, va, np.linalg.inv(T_gt)
    res = align_views([(a, b) for a in va for b in vb])
    if res.merged:
        dt, dr = transform_error(res.T_a_b, T_gt)
        assert dt < 0.15 and dr < 3.0, (dt, dr, res.to_dict())
    else:
        assert res.reason


def test_sun3d_link_from_the_aligner_covers_robot_b(
    sun3d, sun3d_keyframes, sun3d_alignment, vocabulary, tmp_path
):
    """Keyframe-level verification finds one pair across this wide baseline; once the
    aligner's gated transform is registered as a link, the place database records the
    co-visible pairs: most of robot B's keyframes get one, every one true by the ground
    truth, also for keyframes that arrive after the link, and they survive a restart."""
    res = sun3d_alignment  # the aligner's answer for every keyframe pair of A and B
    assert res.merged, res.reason
    recs = {r: read_recording(sun3d / r) for r in ("robot_a", "robot_b")}
    frames = sun3d_keyframes
    db = PlaceDB(tmp_path / "l.sqlite", vocabulary, background=False)
    for f in frames["robot_a"] + frames["robot_b"][:6]:
        db.add_keyframe(f.robot_id, encode(f))
    db.process_pending()
    assert db.add_link("robot_a", "robot_b", res.T_a_b) > 0
    for f in frames["robot_b"][6:]:  # arriving after the link
        db.add_keyframe("robot_b", encode(f))
    db.process_pending()

    T_gt = np.loadtxt(sun3d / "T_a_b.txt")
    by_stamp = {r: {f.stamp: f for f in recs[r].frames} for r in recs}
    pairs = db.overlaps("robot_a", "robot_b")
    assert {p.source for p in pairs} == {"cascade", "link"}
    for p in pairs:
        fa, fb = by_stamp["robot_a"][p.stamp_a], by_stamp["robot_b"][p.stamp_b]
        assert covisibility(fa, fb, T_gt, recs["robot_a"].intrinsics) >= 0.05, p
    covered = {p.stamp_b for p in pairs}
    assert len(covered) >= len(frames["robot_b"]) / 2, (len(covered), len(frames["robot_b"]))
    assert {f.stamp for f in frames["robot_b"][6:]} & covered
    (link,) = db.links()
    np.testing.assert_allclose(link["transform"], res.T_a_b, atol=1e-9)
    db.close()
    again = PlaceDB(tmp_path / "l.sqlite", vocabulary, background=False)
    assert again.overlaps("robot_a", "robot_b") == pairs and len(again.links()) == 1
    again.close()
