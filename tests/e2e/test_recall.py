"""Recall (issue 21): a revisit the cascade cannot verify is merged through the place
database's nominated keyframe pairs, and a robot from another building stays unmerged."""

import json

import numpy as np
import pytest

from fleetmap.dataset import cut_recording, read_recording
from fleetmap.fleet.view_choice import load_view
from fleetmap.geometry import apply, rotation_angle_deg
from fleetmap.mapcloud import views_cloud
from fleetmap.services.cli import main
from fleetmap.simulate import D435_SIGMA_1M, other_camera, other_exposure
from tests.conftest import random_frame

pytestmark = pytest.mark.slow


def error_at_cameras(T, T_true, robot_dir) -> tuple[float, float]:
    """(metres, degrees): how far T puts the robot's cameras from where T_true does (the
    largest), and the rotation between them. Measured where the map is: a random map frame
    puts its origin metres away, where 0.4 deg alone reads as 4 cm."""
    cams = np.stack([f.T_map_cam[:3, 3] for f in read_recording(robot_dir).frames])
    err = np.linalg.norm(apply(T, cams) - apply(T_true, cams), axis=1).max()
    return float(err), rotation_angle_deg(np.linalg.inv(T_true)[:3, :3] @ T[:3, :3])


def merge_windows(
    tmp_path,
    a,
    b,
    seed: int,
    T_true_src: np.ndarray,
    seen_as=None,
    other=True,
    map_frames=None,
    exposure=None,
):
    """Windows `a`, `b` ((recording folder, slice)) cut as robots A and B in random map
    frames (`seed`, `seed` + 1), merged; (its one fit, the error of B's transform at B's
    cameras (`error_at_cameras`) against the truth; T_true_src maps b's source frame into
    a's). `seen_as`: (scale, depth noise) for `cut_recording`, B then seen by another
    camera (`simulate.other_camera`) unless not `other`; the error at the recording's size.
    `map_frames`: {"A": 4x4, "B": 4x4} instead of the seed's; `exposure`: B's colour as a
    camera exposing x that would record it (`simulate.other_exposure`)."""
    M = map_frames or {r: random_frame(s) for s, r in enumerate("AB", start=seed)}
    scale, noise = seen_as or (1.0, 0.0)
    for r, (src, frames) in zip("AB", (a, b), strict=True):
        cut_recording(src, frames, tmp_path / r, M[r], scale, noise)
    if seen_as and other:
        other_camera(tmp_path / "B")
    if exposure is not None:
        other_exposure(tmp_path / "B", exposure)
    out = tmp_path / "out"
    assert (
        main(["-q", "merge", f"A={tmp_path / 'A'}", f"B={tmp_path / 'B'}", "--out", str(out)]) == 0
    )
    report = json.loads((out / "report.json").read_text())
    (fit,) = report["fits"]
    if not fit["merged"]:
        return fit, None
    T_true = true_transform(M, T_true_src, scale)
    dt, dr = error_at_cameras(np.array(report["transforms"]["B"]), T_true, tmp_path / "B")
    return fit, (dt / scale, dr)


def true_transform(M: dict, T_true_src: np.ndarray, scale: float) -> np.ndarray:
    """B's map into A's as the truth has it, for robots cut in map frames M ({"A", "B"}:
    robot map <- source map) at `scale`; T_true_src maps B's source frame into A's."""
    T_true = M["A"] @ T_true_src @ np.linalg.inv(M["B"])
    T_true[:3, 3] *= scale
    return T_true


def frame(rotvec, t) -> np.ndarray:
    """A map frame (robot map <- source map) from a rotation vector and a translation."""
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3], M[:3, 3] = Rotation.from_rotvec(rotvec).as_matrix(), t
    return M


def mean_map_error(tmp_path, T_true: np.ndarray, scale: float) -> float:
    """The mean displacement (metres, at the recording's size) of B's map points between
    the merge's transform and T_true, as `bench/recall.py` scores a merge: every 5th view,
    a 5 cm voxel at the recording's size."""
    rec = read_recording(tmp_path / "B")
    views = [load_view(rec, i) for i in range(0, len(rec), 5)]
    pts = np.asarray(views_cloud(views, voxel=0.05 * scale, with_color=False).points)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    T = np.array(report["transforms"]["B"])
    return float(np.linalg.norm(apply(T, pts) - apply(T_true, pts), axis=1).mean()) / scale


def pair_windows(
    tmp_path, folder, robots: tuple[str, str], a: tuple, b: tuple, seed: int, seen_as=None
):
    """`merge_windows` of a two-robot recording's robots (`robots`, in `folder` with its
    T_a_b.txt): the first's frames a[0]:a[1], the second's b[0]:b[1]."""
    T = np.loadtxt(folder / "T_a_b.txt")
    ra, rb = robots
    A, B = (folder / ra, slice(*a)), (folder / rb, slice(*b))
    return merge_windows(tmp_path, A, B, seed, T, seen_as)


def hololens_windows(tmp_path, hololens, a: tuple, b: tuple, seed: int, seen_as=None):
    """`pair_windows` of hl_a frames a[0]:a[1] and hl_b frames b[0]:b[1]."""
    return pair_windows(tmp_path, hololens, ("hl_a", "hl_b"), a, b, seed, seen_as)


def sun3d_windows(tmp_path, sun3d, a: tuple, b: tuple, seed: int):
    """`pair_windows` of SUN3D robot_a frames a[0]:a[1] and robot_b frames b[0]:b[1]."""
    return pair_windows(tmp_path, sun3d, ("robot_a", "robot_b"), a, b, seed)


def desk_windows(tmp_path, tum_rpy, seed: int, seen_as: tuple):
    """`merge_windows` of TUM fr1_rpy frames 0:50 and 130:180 (27% of the desk shared), both
    seen by the recording's camera at `seen_as` (scale, depth noise)."""
    a, b = (tum_rpy, slice(0, 50)), (tum_rpy, slice(130, 180))
    return merge_windows(tmp_path, a, b, seed, np.eye(4), seen_as, other=False)


def right_or_refused(fit: dict, err) -> None:
    """Merged with B's cameras within 5 cm of the truth, or refused with a reason."""
    if fit["merged"]:
        assert err[0] < 0.05, (err, fit)
    else:
        assert fit["reason"], fit


def merged_near_truth(fit: dict, err, method: str) -> None:
    """The fit merged, by the look `method` names ("+asift": the second look, whose method
    ends so; "fpfh": the third, whose method starts so), and B's transform lies within
    5 cm / 2 deg of the truth at B's cameras."""
    how = fit.get("method", "")
    named = how.endswith(method) if method == "+asift" else how.startswith(method)
    assert fit["merged"] and named, fit
    dt, dr = err
    assert dt < 0.05 and dr < 2.0, (dt, dr, fit)


def test_unverified_revisit_is_merged_and_another_building_is_not(
    hololens, sun3d, tmp_path, monkeypatch, capsys
):
    """Two windows of the HoloLens walk sharing half their surfaces (hl_a frames 15-75, hl_b
    15-75) get no keyframe pair verified by the cascade (so they stayed unmerged before);
    aligned where the bags of words point, they merge within 5 cm / 2 deg of the truth. A
    SUN3D window (another building, another sensor) is nominated pairs too, and refused by
    the first look. The second and third looks, which A and B do not need (the first merges
    them) and which refuse C again, are off: the other tests of different places run them
    (test_different_places_are_not_merged every look,
    test_two_places_at_desk_scale_stay_unmerged the third); 51 -> 39 s beside a benchmark
    without the third, 43 -> 17 s of CPU alone without the second too."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC_LOOK", "false")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    T_hl = np.loadtxt(hololens / "T_a_b.txt")  # hl_b's map into hl_a's
    M = {r: random_frame(seed) for seed, r in enumerate("ABC", start=21)}  # robot <- source
    cut_recording(hololens / "hl_a", slice(15, 75), tmp_path / "A", M["A"])
    cut_recording(hololens / "hl_b", slice(15, 75), tmp_path / "B", M["B"])
    cut_recording(sun3d / "robot_b", slice(0, 20), tmp_path / "C", M["C"])
    out = tmp_path / "out"
    args = ["-q", "merge", *(f"{r}={tmp_path / r}" for r in "ABC"), "--out", str(out)]
    assert main(args) == 0
    report = json.loads((out / "report.json").read_text())
    verified = [o for o in report["overlaps"] if o["source"] == "cascade" and o["robot_b"] == "B"]
    assert not verified  # the cascade alone leaves this revisit unmerged
    T_true = M["A"] @ T_hl @ np.linalg.inv(M["B"])
    dt, dr = error_at_cameras(np.array(report["transforms"]["B"]), T_true, tmp_path / "B")
    assert dt < 0.05 and dr < 2.0, (dt, dr, report["fits"])
    assert report["unmerged"] == ["C"], report["fits"]
    refused = [f for f in report["fits"] if "C" in (f["robot_a"], f["robot_b"])]
    assert refused and all(not f["merged"] and f["reason"] for f in refused)
    # the summary says why (it said "no trustworthy overlap" beside 30 verified overlaps)
    assert f"unmerged C: {report['unmerged_reasons']['C'][:60]}" in capsys.readouterr().out


def test_room_walked_the_other_way_is_merged_on_a_second_look(hololens, tmp_path):
    """hl_a frames 15-75 and hl_b 30-90 share half their surfaces, seen from the other
    direction: 1 of 730 raw MSER+SIFT matches agreed with the truth and the gate refused
    ("0 inlier correspondences"). Affine-simulated SIFT on a few views of each (the second
    look) finds matches that agree; merged within 5 cm / 2 deg of the truth."""
    fit, err = hololens_windows(tmp_path, hololens, (15, 75), (30, 90), 31)
    merged_near_truth(fit, err, "+asift")


def test_second_look_merges_only_what_its_matches_pin(sun3d, tmp_path, monkeypatch):
    """SUN3D robot_a frames 15-35 and robot_b 20-40 share 44% of their surfaces. Before the
    second look's merges had to be pinned by their matches, ICP from an ASIFT pair's
    hypothesis slid along the study room's walls and floor to a merge 14.6 cm from the
    truth at B's cameras (these frames; in the recall bench: 77 matches agreed with an
    alignment 0.22 m away, 31 with the merge). Now: merged within 5 cm, or refused. The
    third look, which would judge a refusal again on the maps' geometry alone, is off: this
    test is the second look's (18 -> 12 s alone)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC_LOOK", "false")
    right_or_refused(*sun3d_windows(tmp_path, sun3d, (15, 35), (20, 40), 42))


def test_a_slide_along_the_rooms_planes_is_not_a_merge(sun3d, tmp_path, monkeypatch):
    """SUN3D robot_a frames 30-50 and robot_b 10-30 share 35% of their surfaces. The first
    look's best basin put B's cameras 27 cm from the truth (the whole recordings' own merge
    agrees with `T_a_b.txt` within 2 cm): ICP slid along the study room's floor and walls,
    where the free space stays consistent (firm 0.99, so the geometry decided alone), while
    the matches agreed better with an alignment 24 cm away (24 against 7). A merge the
    geometry carried alone, with fewer matches at it than a merge needs, must be pinned by
    them too (`pinning.carried`, session 23). Merged within 5 cm of the truth, or
    refused. The wrong merge was the first look's: the later looks, which refuse this pair
    too (ASIFT's basin is the same and unpinned: `test_second_look_merges_only_what_its_
    matches_pin`), are off here (84 -> 13 s in the suite)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC_LOOK", "false")
    right_or_refused(*sun3d_windows(tmp_path, sun3d, (30, 50), (10, 30), 11))


def test_room_seen_from_elsewhere_is_merged_on_the_copies_asift_makes(hololens, tmp_path):
    """hl_a frames 30-90 and hl_b 90-150 share 27% of their surfaces, seen from directions
    far apart: no keyframe pair verified, and through session 21 both image looks refused
    it (6 of 1,110 raw matches agreed with the truth) and the third look merged it on the
    views' depth. ASIFT describes a point once per simulated tilt; with the ratio test's
    second nearest taken among other points (`SecondLook.distinct_px`), the second look
    finds the evidence and merges it where the third look did (3.5 cm / 0.38 deg at B's
    cameras either way; 27 s instead of 45 s). Within 5 cm / 2 deg of the truth. (The third
    look keeps its own real pair below, and its unit tests.)"""
    fit, err = hololens_windows(tmp_path, hololens, (30, 90), (90, 150), 51)
    merged_near_truth(fit, err, "+asift")


def test_room_seen_across_its_planes_is_merged(hololens, tmp_path, monkeypatch):
    """hl_a frames 60-120 and hl_b 75-135 share 20% of B's surfaces, seen from far apart:
    no match agrees with the truth (ASIFT's included) and only 3-13 of thousands of FPFH
    correspondences do, so every look refused it through session 15. The rotation between
    the two maps' dominant planes and the best translation of their occupancy grids start
    ICP at the truth, whose free space (off depth edges) and grey levels agree; merged
    within 5 cm / 2 deg of the truth. The pair sits at the bar: of three random map frames
    tried, these (71, 72) and 81's merge, 61's is refused at firm consistency 0.89 (clouds
    voxelised in each map's own frame differ a little: docs/ALIGNER.md). The second look,
    which refuses this pair before the third merges it (no ASIFT match agrees with the
    truth), is off here: the suite's longest test (97 s); alone, beside a benchmark, 74 -> 45 s."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    fit, err = hololens_windows(tmp_path, hololens, (60, 120), (75, 135), 71)
    merged_near_truth(fit, err, "fpfh")


def test_room_a_handful_of_places_pull_elsewhere_is_merged(hololens, tmp_path):
    """hl_a frames 60-120 and hl_b 90-150 share 19% of B's surfaces, seen from far apart:
    both image looks refuse, the third finds the truth (free space firm 0.95-0.97, grey
    levels 0.60-0.63), and through session 32 the pinning refused it (recall seeds 29, 32)
    because 8 raw matches agreed with an alignment 24 cm away against 3 at the merge. Those
    8 are four places, three of them matched two or three times; the floor counts places
    now (`validation.distinct`). In four pairs of random map frames (seeds 61-67) refused
    at 83a0ec6, merged at 4.3-4.5 cm / 0.3 deg since. Within 5 cm / 2 deg of the truth."""
    fit, err = hololens_windows(tmp_path, hololens, (60, 120), (90, 150), 61)
    merged_near_truth(fit, err, "fpfh")


def test_room_a_pull_the_maps_geometry_refuses_is_merged(hololens, tmp_path):
    """hl_a frames 60-120 and hl_b 30-90 share 18% of B's surfaces, seen from far apart:
    both image looks refuse, the third finds the truth (free space firm 0.92-0.96, grey
    levels 0.59-0.62), and through session 33 the pinning refused it in 8 of 10 pairs of
    random map frames (seeds 61-79; the other two the look refuses on grey levels): about a
    dozen raw matches, ASIFT's among them, at six or more places agree with an alignment
    some 20 cm away against half as many at the merge. The maps' geometry refuses that
    alignment (firm 0.52-0.58) and ICP started there lands 0.5-1.9 cm from the merge
    (`pulls.falls_back`): merged in all 8 since, 3.9-4.3 cm / 0.4 deg at B's
    cameras. Within 5 cm / 2 deg of the truth."""
    fit, err = hololens_windows(tmp_path, hololens, (60, 120), (30, 90), 71)
    merged_near_truth(fit, err, "fpfh")


def test_room_a_pull_whose_icp_finds_no_place_is_merged(hololens, tmp_path):
    """hl_a frames 75-135 and hl_b 120-180 (26% of B shared) at 0.4 of their size, B seen by
    another camera (recall seed 52's conditions): the third look merges 3.0 cm from the
    truth (firm 0.96 at the robots' depth noise, the truth's too), and through session 39
    the pinning refused it: 24 raw matches agree with an alignment 55 cm off (at the
    recording's size) against 12 at the merge. The maps' geometry refuses that alignment
    (firm 0.21) and ICP from it lands 17 cm off, where the look's own judging refuses too
    (firm 0.85 at the noise, need 0.9): neither is a place (`pulls.falls_back`).
    Within 5 cm / 2 deg of the truth at the recording's size."""
    fit, err = hololens_windows(tmp_path, hololens, (75, 135), (120, 180), 61, (0.4, 0.0))
    merged_near_truth(fit, err, "fpfh")


def test_a_room_at_twice_its_size_is_merged_on_readings_beyond_6_m(hololens, tmp_path, monkeypatch):
    """hl_a frames 15-75 and hl_b 120-180 (31% of B shared) at twice their size, B seen by
    another camera, in recall seed 61's map frames (pair 11): the views' median depth is 5.1
    m, and the aligner's clouds, cut at 6 m as set on rooms seen from 1-3 m, held half of
    each view: every look refused ("the maps overlap on 0.09 of B's cloud"; the third look's
    best firm 0.72). With the clouds reaching twice the scene's median depth, as far as the
    robots' readings agree within 8 cm (`AlignParams.cloud_depth_cap`), the third look
    merges. The second look, which refuses this pair before the third merges it, is off
    here. Within 5 cm / 2 deg of the truth at the recording's size."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {  # the draw's random map frames (bench/recall.py --seed 61), kept as it drew them
        "A": [[-0.547516950453, -0.232645464288, 0.803804252858, 1.329145894533],
              [-0.836526423349, 0.176488551790, -0.518724719023, 2.680591448814],
              [-0.021183295414, -0.956414073001, -0.291244551815, -0.631385203514],
              [0.0, 0.0, 0.0, 1.0]],
        "B": [[-0.849536204179, 0.083614569716, -0.520861633758, 0.153511138531],
              [-0.290025411431, -0.898779866216, 0.328755247577, 3.590078977373],
              [-0.440651220938, 0.430352594760, 0.787796385921, -2.408671960657],
              [0.0, 0.0, 0.0, 1.0]],
    }  # fmt: skip
    M = {r: np.array(T) for r, T in M.items()}
    A, B = (hololens / "hl_a", slice(15, 75)), (hololens / "hl_b", slice(120, 180))
    T = np.loadtxt(hololens / "T_a_b.txt")
    fit, err = merge_windows(tmp_path, A, B, 0, T, (2.0, 0.0), map_frames=M)
    merged_near_truth(fit, err, "fpfh")


def test_a_room_at_twice_its_size_is_judged_at_lengths_in_proportion(
    hololens, tmp_path, monkeypatch
):
    """hl_a frames 105-165 and hl_b 90-150 (17% of B shared) at twice their size, in recall
    seed 68's map frames (pair 3): the views' median depth is 5.2 m, past the 1-3.5 m where
    the gate's lengths (8 cm RANSAC tolerance, 3 and 8 cm voxels, ...) were set. With them
    as set, every look refused ("no rigid consensus among the correspondences", the third
    look's best firm free space 0.65); with every length x depth / 3.5 m
    (`AlignParams.at_depth`: the same share of the scene as in the rooms they were set on),
    the third look merges. The second look, which refuses it either way, is off here.
    At the recording's size: B's map points within 5 cm of the truth on average (as the
    recall bench scores a merge), 2 deg, and its cameras within 8 cm."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {  # the draw's random map frames (bench/recall.py --seed 68 --only hololens)
        "A": [[0.328259442056, -0.271785611783, -0.90464264764, 1.885596879536],
              [0.808793185649, 0.575605604025, 0.120547797419, 0.556934728045],
              [0.487954220751, -0.77123976158, 0.408766325189, 3.13578111202],
              [0.0, 0.0, 0.0, 1.0]],
        "B": [[0.556326539825, -0.750629616001, 0.356449099689, 4.514032460454],
              [0.61320101606, 0.660336452738, 0.433520798911, 1.397876752184],
              [-0.560789884885, -0.022604175897, 0.827649537088, 0.611742607885],
              [0.0, 0.0, 0.0, 1.0]],
    }  # fmt: skip
    M = {r: np.array(T) for r, T in M.items()}
    A, B = (hololens / "hl_a", slice(105, 165)), (hololens / "hl_b", slice(90, 150))
    T = np.loadtxt(hololens / "T_a_b.txt")
    fit, err = merge_windows(tmp_path, A, B, 0, T, (2.0, 0.0), other=False, map_frames=M)
    assert fit["merged"] and fit["method"].startswith("fpfh"), fit
    # judged as the recall bench judges (the truth between the two HoloLens folders holds
    # to 4-5 cm at the cameras, session 28: this pair at its own size lands 4.6 cm off there)
    T_true = true_transform(M, T, 2.0)
    assert mean_map_error(tmp_path, T_true, 2.0) < 0.05 and err[1] < 2.0, (err, fit)
    assert err[0] < 0.08, (err, fit)


def test_a_slide_a_second_look_found_through_a_d435_and_another_camera_is_not_a_merge(
    hololens, tmp_path, monkeypatch
):
    """hl_a frames 60-120 and hl_b 120-180 (21% of B shared) at 0.6 of their size, through
    a D435's depth noise, B as a 16:9 camera of 848 x 477 (recall seed 45's conditions):
    through session 34 the second look merged them 43-45 cm from the truth (at the
    recording's size) in three of four pairs of these tests' map frames (seeds 61-67), 16
    ASIFT matches agreeing, free space 0.72 at the first look's margin. Judged as the third
    look judges (at a sensor's noise for the depth), that merge's free space is firm
    0.59-0.61 (`geometric_look.unfirm`, the first look's bar 0.7; right second-look merges
    0.91-0.98): refused now in all three. Right within 5 cm at the recording's size, or
    refused. The third look, which the wrong merge never reached, is off here (136 s in a
    full run with it)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC_LOOK", "false")
    fit, err = hololens_windows(tmp_path, hololens, (60, 120), (120, 180), 63, (0.6, D435_SIGMA_1M))
    right_or_refused(fit, err)


def test_a_room_at_0_4_of_its_size_through_a_d435_and_another_camera_is_not_merged_off(
    sun3d, tmp_path
):
    """SUN3D robot_a frames 10-30 and robot_b 30-50 (38% of B shared) at 0.4 of their size
    (the room then seen from 1.1-1.4 m), through a D435's depth noise, B by another camera
    (recall seed 75's conditions): with the gate's lengths held at a room's down to 1 m the
    second look merged it 17.4 cm from the truth (at the recording's size; 113 ASIFT inliers,
    held-out residual 3.9 cm, 7% of the depth allowed), and with the pose tolerances alone in
    proportion the third look found the same basin (firm free space 0.96 on 3 cm voxels).
    Every length in proportion below 2 m (`AlignParams.reference_depth_m`): refused on
    its free space. Right within 5 cm at the recording's size, or refused."""
    T = np.loadtxt(sun3d / "T_a_b.txt")
    A, B = (sun3d / "robot_a", slice(10, 30)), (sun3d / "robot_b", slice(30, 50))
    fit, err = merge_windows(tmp_path, A, B, 75, T, (0.4, D435_SIGMA_1M))
    right_or_refused(fit, err)


def test_a_rival_that_refines_into_the_winners_place_does_not_refuse_a_desk(tum_rpy, tmp_path):
    """TUM fr1_rpy windows [130:180] and [180:230] (47% of the desk shared) at 0.4 of their
    size through a D435, B by another camera, in recall seed 75's map frames for them (pair
    21; a rotation vector and a translation a robot, to 6 digits): the first look's winner
    had a rival 7 cm / 6 deg away (over the rivals' 15% of the depth since session 49) at
    0.901 of its score, unrefined, and the pair was refused as ambiguous. Refined as the
    winner is, the rival lands in the winner's place: one basin the coarse ICP left apart
    (`hypotheses._rivals`). Merged within 5 cm / 2 deg at B's cameras (0.3 cm / 0.3 deg)."""
    M = {
        "A": frame([-2.181796, 2.178051, 0.391745], [1.182389, -3.311672, 4.90913]),
        "B": frame([1.343507, 2.47126, 1.106478], [-2.951789, 1.370605, -2.181718]),
    }
    A, B = (tum_rpy, slice(130, 180)), (tum_rpy, slice(180, 230))
    fit, err = merge_windows(tmp_path, A, B, 0, np.eye(4), (0.4, D435_SIGMA_1M), map_frames=M)
    assert fit["merged"], fit["reason"]
    assert err[0] < 0.05 and err[1] < 2.0, err  # at the recording's size


def test_a_desk_seen_by_a_camera_exposing_otherwise_is_merged_where_it_is(tum_rpy, tmp_path):
    """TUM fr1_rpy windows [90:140] and [170:220] (54% of the desk shared) at half their
    size through a D435, B by another camera exposing 1.3 times as bright through another
    gamma and white balance, in recall seed 113's map frames for them (pair 25): coloured
    ICP took the brightness for a displacement and the merge went 13.6 cm (mean map-point
    error) off the truth, a wrong merge. B's grey levels matched to A's where the maps
    meet, the mapping explaining most of their difference (`hypotheses.exposure_matched`):
    merged 2.4 cm off. Within 5 cm / 2 deg at B's cameras."""
    M = {
        "A": frame([2.281470, -0.340462, 0.110415], [-1.944776, 4.315885, 3.478679]),
        "B": frame([1.064821, 0.951804, -0.916003], [2.226578, 3.002235, 0.316666]),
    }
    A, B = (tum_rpy, slice(90, 140)), (tum_rpy, slice(170, 220))
    seen_as = (0.5, D435_SIGMA_1M)
    fit, err = merge_windows(tmp_path, A, B, 0, np.eye(4), seen_as, map_frames=M, exposure=1.3)
    assert fit["merged"], fit["reason"]
    assert err[0] < 0.05 and err[1] < 2.0, err  # at the recording's size


def test_a_desk_seen_from_0_4_m_is_merged_as_from_1_m(tum_rpy, tmp_path):
    """TUM fr1_rpy windows [0:50] and [130:180] (27% of the desk shared), the scene at 0.4
    of its size (depths and poses x 0.4, `cut_recording`'s scale: the desk from 0.4 m, as a
    RealSense at a workbench sees it) merge as near the truth, in proportion, as at full
    size. With the gate's lengths in metres set for rooms the coarse ICP (8 cm voxels, 32 cm
    reach) slid the best hypothesis off the desk: in these map frames refused ("free-space
    consistency 0.41"); over six pairs of frames 2 refused and 4 merged at 1.6-2.4 deg,
    against 6 merged at 0.3-0.7 cm / 0.4-1.5 deg now."""
    fit, err = desk_windows(tmp_path, tum_rpy, 5, (0.4, 0.0))
    assert fit["merged"], fit["reason"]
    assert err[0] < 0.05 and err[1] < 2.0, err  # at the recording's size


def test_a_desk_seen_from_1_5_times_as_far_through_a_d435_is_merged(tum_rpy, tmp_path, monkeypatch):
    """TUM fr1_rpy windows [0:50] and [130:180] (27% shared) at 1.5 times their size through
    a D435's depth noise (3.3 cm RMS a reading at 3 m, on the recording's own). At the
    fixed margin (1.5 voxels and 2% of the depth) the first look's winner scored 0.68
    free-space consistency (need 0.7) and was refused unrefined (as was the draw's, recall
    seed 51's pair 21); judged at the robots' measured depth noise it holds (0.79, firm
    0.97: `pipeline.at_noise`), is refined and merges: 0.6 cm / 0.7 deg at B's cameras (at
    the recording's size). The second and third looks, which this first-look merge does not
    reach, are off. Within 5 cm / 2 deg of the truth."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC_LOOK", "false")
    fit, err = desk_windows(tmp_path, tum_rpy, 21, (1.5, D435_SIGMA_1M))
    assert fit["merged"], fit["reason"]
    assert err[0] < 0.05 and err[1] < 2.0, err  # at the recording's size


def test_two_places_at_desk_scale_stay_unmerged(hololens, tum_rpy, tmp_path, monkeypatch):
    """The HoloLens lounge (hl_b[0:60]) and the TUM desk (fr1_rpy[180:230]), both at 0.4 of
    their size (`cut_recording`'s scale), share no place. The free-space gate alone merged them in
    these map frames (consistency 0.70, firm 0.83: a wrong merge, before and after the gate's
    lengths followed the scene); their grey levels where they meet correlate 0.08. The first
    look refuses them so, and the third finds no alignment; the second (ASIFT), which adds
    nothing the test asks about, is off (39 -> 28 s beside a benchmark). Since every length
    follows the scene below 2 m (session 49), the first look refuses them on free space
    already (0.57 on the desk's own margins)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {r: random_frame(s) for s, r in enumerate("AB", start=3)}
    dirs = {}
    for r, src, frames in (("A", hololens / "hl_b", slice(0, 60)), ("B", tum_rpy, slice(180, 230))):
        dirs[r] = cut_recording(src, frames, tmp_path / r, M[r], scale=0.4)
    out = tmp_path / "out"
    assert main(["-q", "merge", f"A={dirs['A']}", f"B={dirs['B']}", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["unmerged"] == ["B"] and "B" not in report["transforms"]
    first = report["fits"][0]["reason"].split(";")[0]  # the first look's refusal
    assert first.startswith("free-space consistency"), first


def test_a_room_seen_through_more_noise_than_the_third_look_can_judge_is_not_merged(
    hololens, tmp_path, monkeypatch
):
    """hl_a frames 0-60 and hl_b 120-180 (28% of B shared) at twice their size through a
    D435's depth noise: the robots' readings spread 11.7 cm at the median depth (4.8 m), so
    the third look's free-space margin (two spreads) is wider than its 15 cm voxel. In these
    map frames (recall seed 53's, pair 13) it merged them 24 cm from the truth (at the
    recording's size) on free space firm 0.98 and grey levels 0.52, the truth firm 0.99:
    at that noise the free space cannot tell them apart. Refused now before any basin is
    judged (`geometric_look.blurred`). The second look, which refused the pair, is off."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {  # the draw's random map frames (bench/recall.py --seed 53), kept as it drew them
        "A": [[0.375355783701, -0.329717573212, -0.866253056305, 4.111311933198],
              [0.785886414898, -0.382290683274, 0.48604153769, -0.923671507987],
              [-0.491416909071, -0.863215011105, 0.115625542518, -0.78567747296],
              [0.0, 0.0, 0.0, 1.0]],
        "B": [[-0.473487388184, 0.04448377349, 0.879676580981, -0.708332085198],
              [-0.857962620925, -0.249245232616, -0.449195898372, -1.738969879322],
              [0.199273265457, -0.967418217688, 0.156179889101, -1.609461685978],
              [0.0, 0.0, 0.0, 1.0]],
    }  # fmt: skip
    dirs = {}
    for r, src, frames in (("A", "hl_a", slice(0, 60)), ("B", "hl_b", slice(120, 180))):
        dirs[r] = cut_recording(
            hololens / src, frames, tmp_path / r, np.array(M[r]), 2.0, D435_SIGMA_1M
        )
    out = tmp_path / "out"
    assert main(["-q", "merge", f"A={dirs['A']}", f"B={dirs['B']}", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["unmerged"] == ["B"] and "B" not in report["transforms"], report["fits"]
    assert "cannot tell alignments a voxel apart" in report["fits"][0]["reason"]


def test_two_patches_of_one_plane_are_not_a_merge(hololens, tmp_path, monkeypatch):
    """hl_b frames 0-60 and 75-135 (18% of B shared) at 0.7 of their size through a D435's
    noise, in recall seed 80's map frames: both image looks refuse, and through session 51
    the third look merged them 6.6 m / 180 deg off at B's cameras (4.6 m mean map-point
    error in the draw): B's patch of one plane laid on A's, free space firm 1.00 both ways
    (nothing of one plane lies in front of another), grey levels 0.53. The surfaces that
    meet there stand 0.01 m off one plane, under the look's 0.09 m voxel; the look's right
    merges stand 3-6 voxels off (`surfaces.relief`). Right or refused. The second look,
    which refuses it (3 inliers) and leaves the third look's verdict as it is, is off here
    (83 -> 49 s beside a benchmark, session 56)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {
        "A": frame(
            [-1.68034590583457, 1.6095352738488449, 1.991428985897193],
            [-2.4494929856182344, 1.7786857266564038, 1.6052039933932445],
        ),
        "B": frame(
            [1.5082230281558715, 0.1129269055543432, -1.7092211646734106],
            [-0.2733530949630545, 3.9259725239711543, -0.0573647852477821],
        ),
    }
    a, b = (hololens / "hl_b", slice(0, 60)), (hololens / "hl_b", slice(75, 135))
    seen_as = (0.7, D435_SIGMA_1M)
    fit, err = merge_windows(tmp_path, a, b, 0, np.eye(4), seen_as, other=False, map_frames=M)
    right_or_refused(fit, err)


def test_a_basin_depth_holds_short_of_the_place_is_carried_there_by_colour(
    hololens, tmp_path, monkeypatch
):
    """hl_a frames 45-105 and hl_b 45-105 (32% of B shared) at 0.7 of their size through a
    D435's noise, in recall seed 80's map frames: both image looks refuse (3 and 8 inliers),
    and through session 52's first change the third look refused too: of its 30 basins the
    nearest to the truth lay 0.22 m off, where point-to-plane ICP settles (firm free space
    0.75), while the truth itself passes (firm 0.95, grey levels 0.68). Coloured ICP from
    that basin lands 3 cm from the truth, and passes (`hypotheses.colour_icp`,
    opt-in: `GeometricLook.colour_refine`): merged 6.2 cm / 0.5 deg off at B's cameras at
    the recording's size, where ICP of the maps from the truth itself moves 3.3 cm (recall
    seed 80's `truth_basin`); within 8 cm / 3 deg, short of the bench's wrong line. The
    second look, which refuses it and changes nothing of the third's merge (the same
    transform to 1e-14), is off here (51 -> 38 s beside a benchmark, session 56)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC__COLOUR_REFINE", "true")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {
        "A": frame(
            [-0.4652380680752535, 2.2084377212918107, 0.939428738610333],
            [-2.9778229861184844, -2.4586220701547203, 1.2189738465432898],
        ),
        "B": frame(
            [1.3989383976092875, 2.605841006328444, -0.3153867541115261],
            [1.4794852612850047, -4.067442883701064, -2.7662117129489805],
        ),
    }
    a, b = (hololens / "hl_a", slice(45, 105)), (hololens / "hl_b", slice(45, 105))
    T = np.loadtxt(hololens / "T_a_b.txt")
    seen_as = (0.7, D435_SIGMA_1M)
    fit, err = merge_windows(tmp_path, a, b, 0, T, seen_as, other=False, map_frames=M)
    assert fit["merged"] and fit["method"].startswith("fpfh"), fit
    assert err[0] < 0.08 and err[1] < 3.0, (err, fit)


def test_lounge_and_study_room_stay_unmerged_when_a_basin_slides_away(
    hololens, sun3d, tmp_path, monkeypatch
):
    """The HoloLens lounge (hl_b[15:75]) and the SUN3D study room (robot_b[15:35]) share no
    place. In these map frames (recall.py's seed 14, pair 26, frame 1) the third look merged
    them on a basin at overlap 0.11, firm free-space consistency 0.99 and grey-level
    correlation 0.62, whose refinement slid 0.79 m / 14 deg to where the gate refused it;
    the basin was kept. A basin whose refinement slides as far as a rival is not an
    alignment: refused (`geometric_look`). The second look, which refuses the pair before
    the third, is off here: without it the code before the rule merged the same basin
    (0.99 / 0.62 / 0.11) and the test takes 20 s instead of 43. Since session 52 the basin
    no longer passes at all: its meeting points stand 0.02 m off one plane at a 0.12 m
    voxel (`surfaces.relief`), so the look refuses it before any refinement; either
    way the third look judges and refuses it."""
    from scipy.spatial.transform import Rotation

    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")

    rng = np.random.default_rng([14, 26, 1])  # bench/real_pairs.random_frame's draws
    dirs = {}
    for r, src, frames in (
        ("A", hololens / "hl_b", slice(15, 75)),
        ("B", sun3d / "robot_b", slice(15, 35)),
    ):
        M = np.eye(4)
        M[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        M[:3, 3] = rng.uniform(-5, 5, 3)
        dirs[r] = cut_recording(src, frames, tmp_path / r, M)
    out = tmp_path / "out"
    assert main(["-q", "merge", f"A={dirs['A']}", f"B={dirs['B']}", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["unmerged"] == ["B"] and "B" not in report["transforms"]
    reason = report["fits"][0]["reason"]
    assert "on the maps' geometry" in reason and "no alignment passes" in reason, reason


def test_a_merge_the_matches_pull_a_few_cm_moves_there(hololens, tmp_path):
    """hl_a frames 15-75 and hl_b 45-105 (51% of B shared) through a D435's noise (the
    room from 2.5-5 m, 2-9 cm a reading), in recall seed 81's map frames: the first look
    finds no rigid consensus; the second and third looks both passed the maps' geometry
    7.2 cm (mean map-point error) from the truth, where 20 raw matches agree, against 28
    with an alignment 9 cm from it, and were refused as unpinned through session 52 (the
    same pair missed in seeds 79 and 81). A look's merge now follows the pull where the
    third look would merge there (`pinning.moved_by_pull`, `pulls.follow`): that
    alignment, refined as a basin is, passes the third look (firm 0.98, grey levels 0.77)
    and the matches pin it: merged 1.7 cm off, on the second look. Within 5 cm / 2 deg at
    B's cameras, judged as the third look judges."""
    M = {
        "A": frame(
            [1.6777895965458318, 0.845833605282452, -1.345240419579721],
            [-2.6553272962307286, -4.503051608390081, -1.8525304946748058],
        ),
        "B": frame(
            [-1.182318323652087, 1.5907938038586311, -0.47588920282787994],
            [-4.866757186513025, 4.599404242675947, 4.213687932823419],
        ),
    }
    a, b = (hololens / "hl_a", slice(15, 75)), (hololens / "hl_b", slice(45, 105))
    T = np.loadtxt(hololens / "T_a_b.txt")
    seen_as = (1.0, D435_SIGMA_1M)
    fit, err = merge_windows(tmp_path, a, b, 0, T, seen_as, other=False, map_frames=M)
    merged_near_truth(fit, err, "fpfh")
    assert "moved where the raw matches agree" in fit["reason"], fit


def test_a_third_look_merge_through_a_d435_is_refined_on_depth_not_colour(
    hololens, tmp_path, monkeypatch
):
    """hl_a frames 45-105 and hl_b 105-165 (18% of B shared) through a D435's noise (the
    room from 2.5-5 m), in recall seed 81's map frames: both image looks refuse, and the
    third look's basin passes (firm 0.97, grey levels 0.52). Through session 53 its merge
    was refined by coloured ICP, chosen over point-to-plane by `hypotheses.ranked` with no
    match to tell them apart: 6.8 cm (mean map-point error) from the truth, loose, where
    point-to-plane from the same basin stood 3.2 cm. The look now refines on depth alone
    (`geometric_look.settle`): merged within 5 cm / 2 deg at B's cameras. The second look,
    which refuses it and changes nothing of the third's merge (the same transform to
    1e-14), is off here (51 -> 37 s beside a benchmark, session 56)."""
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK", "false")
    M = {
        "A": frame(
            [-0.19711784077443004, -0.29228087984037715, 2.899374530764923],
            [-1.4579654493234848, -4.795498419865224, 1.4270225303866626],
        ),
        "B": frame(
            [-1.200230611615194, 1.3235957275236614, 0.10455985425096362],
            [-3.5620968081467232, -3.717595654930715, -1.1188725188308957],
        ),
    }
    a, b = (hololens / "hl_a", slice(45, 105)), (hololens / "hl_b", slice(105, 165))
    T = np.loadtxt(hololens / "T_a_b.txt")
    fit, err = merge_windows(tmp_path, a, b, 0, T, (1.0, D435_SIGMA_1M), other=False, map_frames=M)
    merged_near_truth(fit, err, "fpfh")
    assert fit["method"] == "fpfh+icp+icp", fit
    assert mean_map_error(tmp_path, true_transform(M, T, 1.0), 1.0) < 0.05, fit


def test_a_pull_the_geometry_returns_from_does_not_refuse_a_room_at_1_5_times(hololens, tmp_path):
    """hl_a frames 15-75 and hl_b 45-105 (51% of B shared) at 1.5 times their size through a
    D435's noise, in recall seed 85's map frames: both image looks refuse, the third look's
    basin passes (firm 0.97, grey levels 0.76), and 17 raw matches against 11 prefer an
    alignment 16 cm away (12 cm from the truth) at firm 0.83, from which ICP returns to the
    merge. Through session 54 that pull refused the pair (`pulls.falls_back` let only a pull
    under firm 0.7 fall back); now merged within 5 cm of the truth (mean map-point error, at
    the recording's size)."""
    M = {
        "A": frame(
            [0.24251860645131382, 1.4760827598518798, 1.8490519785385229],
            [0.18411689054182911, -3.142632872442391, -1.8101906789628064],
        ),
        "B": frame(
            [1.0450075325586903, -1.4150652154182783, 1.8394939587451675],
            [-0.517325341076317, -0.16361326201768556, 1.292417394021614],
        ),
    }
    a, b = (hololens / "hl_a", slice(15, 75)), (hololens / "hl_b", slice(45, 105))
    T = np.loadtxt(hololens / "T_a_b.txt")
    fit, err = merge_windows(tmp_path, a, b, 0, T, (1.5, D435_SIGMA_1M), other=False, map_frames=M)
    assert fit["merged"] and fit["method"].startswith("fpfh"), fit
    assert mean_map_error(tmp_path, true_transform(M, T, 1.5), 1.5) < 0.05, (err, fit)
    assert err[1] < 2.0, (err, fit)
