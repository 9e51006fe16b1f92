"""The third look's starts from the maps' dominant planes (`fleetmap.align.manhattan`)."""

import numpy as np
from scipy.spatial.transform import Rotation

from fleetmap.align.manhattan import cube_rotations, dominant_frame, translation_peaks
from fleetmap.dataset import read_recording
from fleetmap.geometry import transform_error


def _box_normals(R: np.ndarray, rng) -> np.ndarray:
    """Noisy normals of a room's floor (many), two walls and a few stray ones, turned by R."""
    n = np.concatenate(
        [
            np.tile([0.0, 0.0, 1.0], (600, 1)),
            np.tile([1.0, 0.0, 0.0], (300, 1)) * rng.choice([-1, 1], (300, 1)),
            np.tile([0.0, 1.0, 0.0], (200, 1)),
            rng.normal(size=(100, 3)),
        ]
    )
    n += rng.normal(scale=0.03, size=n.shape)
    n /= np.linalg.norm(n, axis=1)[:, None]
    return n @ R.T


def test_dominant_frame_finds_a_rooms_axes_and_no_frame_in_one_plane():
    rng = np.random.default_rng(0)
    R = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    F = dominant_frame(_box_normals(R, rng))
    assert F is not None and np.allclose(F.T @ F, np.eye(3), atol=1e-9)
    # its axes are the room's (floor first, then the stronger wall), up to sign
    for k, axis in enumerate(np.eye(3)[[2, 0, 1]]):
        assert abs(F[:, k] @ (R @ axis)) > np.cos(np.radians(2)), k
    floor = np.tile([0.0, 0.0, 1.0], (500, 1)) + rng.normal(scale=0.03, size=(500, 3))
    assert dominant_frame(floor / np.linalg.norm(floor, axis=1)[:, None]) is None
    assert dominant_frame(np.zeros((500, 3))) is None  # normals Open3D could not estimate
    assert dominant_frame(np.zeros((10, 3))) is None  # too few to tell


def test_the_cube_has_24_rotations():
    rots = cube_rotations()
    assert len(rots) == 24 and all(np.isclose(np.linalg.det(P), 1.0) for P in rots)
    assert len({P.tobytes() for P in rots}) == 24


def test_translation_peaks_find_a_shift():
    rng = np.random.default_rng(1)
    A = rng.uniform(0, 3, size=(3000, 3))
    t = np.array([0.8, -0.4, 0.25])
    (best, cells), *_ = translation_peaks(A, A - t, 0.1, 3)
    assert np.linalg.norm(best - t) < 0.1 and cells > 0


def test_plane_starts_reach_the_truth_where_fpfh_matches_do_not(hololens):
    """Two windows of the real HoloLens walk (hl_a frames 60-120, hl_b 75-135) share 20-24%
    of their surfaces, seen from far apart: of the FPFH correspondences only a few agree
    with the truth and no RANSAC seed of the third look lands near it. Of the starts from
    the maps' dominant planes, one ICP lands within 10 cm of the truth."""
    from fleetmap.align.geometric_look import basins
    from fleetmap.align.hypotheses import probe_points
    from fleetmap.align.types import GeometricLook
    from fleetmap.geometry import displacement_rms

    clouds, T_true = _windows(hololens)
    voxel = 0.12  # the third look's: 5% of these views' median depth (2.4 m)
    probe = probe_points(clouds[1].at(voxel))
    planes_only = basins(clouds, voxel, GeometricLook(seeds=1, iterations=1, plane_starts=16))
    errors = [displacement_rms(T, T_true, probe) for T, _ in planes_only]
    assert min(errors) < 0.1, errors
    best = planes_only[int(np.argmin(errors))][0]
    assert transform_error(best, T_true)[1] < 2.0


def _windows(hololens):
    """Each robot's views of hl_a frames 60-120 and hl_b 75-135 (every 5th) as `ViewsCloud`s,
    and the true T_a_b."""
    from fleetmap.fleet.view_choice import load_view
    from fleetmap.mapcloud import ViewsCloud

    ra, rb = (read_recording(hololens / n) for n in ("hl_a", "hl_b"))
    clouds = (
        ViewsCloud([load_view(ra, i) for i in range(60, 120, 5)]),
        ViewsCloud([load_view(rb, i) for i in range(75, 135, 5)]),
    )
    return clouds, np.loadtxt(hololens / "T_a_b.txt")


def test_the_screens_skip_only_basins_that_could_not_pass(hololens):
    """The third look refines and judges only basins whose grey levels correlate at least
    `min_correlation` - `COARSE_SLACK` and whose firm free space holds at least
    `min_consistency` - `FIRM_SLACK` before refining (judged at the robots' depth noise, as
    the look judges). On the same windows, every basin either screen skips stays under its
    bar after refining too, and the basin at the truth is kept."""
    from fleetmap.align import geometric_look as G
    from fleetmap.align.hypotheses import probe_points
    from fleetmap.align.types import GeometricLook
    from fleetmap.depth_noise import DepthNoise
    from fleetmap.geometry import displacement_rms
    from fleetmap.mapcloud import SeenDepth

    clouds, T_true = _windows(hololens)
    voxel, look = 0.12, GeometricLook(seeds=4, iterations=20_000, plane_starts=16)
    probe = probe_points(clouds[1].at(voxel))
    ca, cb = (c.at(voxel) for c in clouds)
    fa, fb = (c.at(voxel / 2) for c in clouds)
    seen = [[SeenDepth(v) for v in c.views] for c in clouds]
    noise = DepthNoise.measure(clouds[0].views).between(DepthNoise.measure(clouds[1].views))
    floor = lambda depth: look.noise_k * noise(depth)  # noqa: E731 (as `noise_floor` gives)
    skipped = unfirm = kept_truth = 0
    for T, _ in G.basins(clouds, voxel, look, 0.1):
        before = G.grey_correlation(ca, cb, T, voxel)[0]
        fine = G.refine(T, clouds, voxel)
        if not before >= look.min_correlation - G.COARSE_SLACK:
            skipped += 1
            after = G.grey_correlation(fa, fb, fine, voxel / 2)[0]
            assert not after >= look.min_correlation, (before, after)
            continue
        firm = min(G.firm_ways(T, clouds, seen, voxel, floor))
        if firm < look.min_consistency - G.FIRM_SLACK:
            unfirm += 1
            after = min(G.firm_ways(fine, clouds, seen, voxel, floor))
            assert after < look.min_consistency, (firm, after)
        elif displacement_rms(fine, T_true, probe) < 0.1:
            kept_truth += 1
    assert skipped and unfirm and kept_truth, (skipped, unfirm, kept_truth)
