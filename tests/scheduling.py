"""How the suite is shared by pytest-xdist workers (`scripts/test.sh`: `-n 2 --dist
loadgroup`): which tests run on one worker (a group), and in what order.

By default a group is a test module, so a module's fixtures (the live map's services, the
drifted merge, the demo merge) are built once; a long test of such a module that uses none
of them is a group of its own (APART). In the modules in PER_TEST, whose tests share only
session fixtures, each test is its own group, except the tests that share a costly session
fixture (SHARED): those run together, so it is built once.

Groups are handed out longest first (COST_S: what each took in a full run of the suite on
this 2-core machine; the others after them in collection order), so the last groups left
are short ones and neither worker waits long for the other at the end.

The groups are given to xdist by its scheduler hook (`pytest_xdist_make_scheduler`), from
the test ids alone: xdist's own `xdist_group` marks no longer reach its scheduler under
pytest 9 (they are appended to `Item._nodeid`, which pytest 9 no longer reads)."""

from __future__ import annotations

import pytest

#: Modules whose tests share no module-scoped fixture: each test may run on either worker.
PER_TEST = (
    "tests/e2e/test_merge.py",
    "tests/e2e/test_merge_parameters.py",
    "tests/e2e/test_recall.py",
    "tests/e2e/test_sun3d_alignment.py",
    "tests/process/test_bags.py",
    "tests/process/test_fuzz_api.py",
)

#: Tests of those modules that share a costly session fixture (named as the group).
SHARED = {
    "tests/e2e/test_merge.py::test_merge_sun3d_pair_recovers_ground_truth": "sun3d_merge",
    "tests/e2e/test_merge_parameters.py::test_merge_report_holds_both_services_parameters": (
        "sun3d_merge"
    ),
    "tests/process/test_bags.py::test_merge_with_a_ros2_bag_robot_gives_the_folder_transform": (
        "sun3d_merge"
    ),
    "tests/e2e/test_sun3d_alignment.py::test_sun3d_wide_baseline_recovers_the_ground_truth": (
        "sun3d_alignment"
    ),
    "tests/e2e/test_sun3d_alignment.py::test_sun3d_link_from_the_aligner_covers_robot_b": (
        "sun3d_alignment"
    ),
}

#: Tests of modules grouped whole that share none of the module's costly fixtures: each is a
#: group of its own, so it may run on the other worker (they are among the longest).
APART = (
    # only the drifted copies (hard links), not the module's drifted merge
    "tests/e2e/test_fleet_drift.py::test_bent_maps_merge_from_overlaps_that_once_refused",
    "tests/e2e/test_fleet_drift.py::"
    "test_a_map_that_holds_one_place_twice_merges_from_views_along_its_path",
    # its own place database: not the module's two replicas (`live`)
    "tests/e2e/test_live_map.py::test_restart_mid_stream_loses_nothing_and_resumes_the_map",
)

_PARTS = "tests/e2e/test_sun3d_alignment.py::test_sun3d_parts_are_merged_right_or_not_at_all"

#: Seconds of the costly groups, by group name: their wall seconds in a full run of the suite on
#: two workers (`bash scripts/test.sh --durations=0`, 2026-12-07, 457 tests in 629 s, quiet;
#: each group's setup, calls and teardown), which only order them; the others took under 7 s
#: there. A group's share moves between runs (the feature cache: whichever test extracts an
#: image first pays for it), and under load the merges' share grows, so the order is a guide,
#: not a promise. A long test missing here runs after every listed group: add it.
COST_S = {
    "tests/e2e/test_fleet_drift.py": 96,
    "tests/e2e/test_live_map.py": 78,
    "tests/e2e/test_demo_fleet.py": 59,
    "tests/e2e/test_recall.py::"
    "test_a_basin_depth_holds_short_of_the_place_is_carried_there_by_colour": 56,
    "tests/e2e/test_recall.py::"
    "test_a_pull_the_geometry_returns_from_does_not_refuse_a_room_at_1_5_times": 55,
    "tests/e2e/test_recall.py::"
    "test_a_slide_a_second_look_found_through_a_d435_and_another_camera_is_not_a_merge": 44,
    "tests/e2e/test_recall.py::test_room_a_pull_whose_icp_finds_no_place_is_merged": 44,
    "tests/e2e/test_recall.py::test_two_patches_of_one_plane_are_not_a_merge": 40,
    "tests/process/test_cli.py": 40,
    "tests/e2e/test_recall.py::test_a_merge_the_matches_pull_a_few_cm_moves_there": 39,
    "tests/e2e/test_recall.py::test_room_a_pull_the_maps_geometry_refuses_is_merged": 36,
    f"{_PARTS}[part_a3-part_b3-False]": 30,
    "tests/e2e/test_recall.py::test_room_a_handful_of_places_pull_elsewhere_is_merged": 27,
    "tests/e2e/test_recall.py::"
    "test_a_room_at_twice_its_size_is_judged_at_lengths_in_proportion": 26,
    "sun3d_merge": 25,
    "tests/e2e/test_recall.py::test_a_room_at_twice_its_size_is_merged_on_readings_beyond_6_m": 25,
    APART[2]: 22,
    "tests/e2e/test_recall.py::"
    "test_a_third_look_merge_through_a_d435_is_refined_on_depth_not_colour": 22,
    "tests/process/test_place_db_replicas.py": 22,
    "tests/e2e/test_recall.py::"
    "test_a_rival_that_refines_into_the_winners_place_does_not_refuse_a_desk": 21,
    "tests/e2e/test_recall.py::"
    "test_a_desk_seen_by_a_camera_exposing_otherwise_is_merged_where_it_is": 25,
    "tests/e2e/test_recall.py::test_room_seen_across_its_planes_is_merged": 20,
    "tests/e2e/test_sun3d_alignment.py::test_different_places_are_not_merged": 19,
    "tests/unit/test_matching_mutual.py": 18,
    "tests/e2e/test_recall.py::test_two_places_at_desk_scale_stay_unmerged": 17,
    f"{_PARTS}[part_a1-part_b1-False]": 17,
    "tests/process/test_reliability.py": 16,
    "tests/e2e/test_recall.py::test_a_desk_seen_from_1_5_times_as_far_through_a_d435_is_merged": 15,
    "tests/e2e/test_recall.py::test_room_walked_the_other_way_is_merged_on_a_second_look": 14,
    "sun3d_alignment": 13,
    "tests/e2e/test_merge.py::test_merge_hololens_robots_that_revisit_a_kitchen": 12,
    "tests/e2e/test_recall.py::"
    "test_a_room_at_0_4_of_its_size_through_a_d435_and_another_camera_is_not_merged_off": 12,
    "tests/e2e/test_recall.py::"
    "test_room_seen_from_elsewhere_is_merged_on_the_copies_asift_makes": 12,
    "tests/process/test_fuzz_api.py::test_no_5xx_and_no_hang[place-db]": 12,
    "tests/unit/test_align.py": 12,
    "tests/api/test_live_recall.py": 11,
    "tests/e2e/test_recall.py::"
    "test_a_room_seen_through_more_noise_than_the_third_look_can_judge_is_not_merged": 11,
    f"{_PARTS}[part_a4-part_b4-True]": 11,
    "tests/unit/test_manhattan.py": 11,
    "tests/e2e/test_recall.py::test_unverified_revisit_is_merged_and_another_building_is_not": 10,
    "tests/process/test_chaos.py": 10,
    APART[1]: 9,
    "tests/e2e/test_merge.py::test_merge_simulated_three_robot_fleet": 9,
    "tests/e2e/test_recall.py::test_a_desk_seen_from_0_4_m_is_merged_as_from_1_m": 9,
    "tests/e2e/test_recall.py::test_a_slide_along_the_rooms_planes_is_not_a_merge": 9,
    "tests/e2e/test_recall.py::"
    "test_lounge_and_study_room_stay_unmerged_when_a_basin_slides_away": 9,
    "tests/e2e/test_recall.py::test_second_look_merges_only_what_its_matches_pin": 9,
    "tests/process/test_robustness.py": 9,
    APART[0]: 8,
    f"{_PARTS}[part_a0-part_b0-False]": 8,
    "tests/api/test_live_reliability.py": 7,
    f"{_PARTS}[part_a2-part_b2-False]": 6,
}


def group_of(nodeid: str) -> str:
    """The group of a test, from its id."""
    module = nodeid.split("::", 1)[0]
    if nodeid in APART:
        return nodeid
    if module not in PER_TEST:
        return module
    return SHARED.get(nodeid, nodeid)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """On an xdist worker, the tests in their groups' order (the scheduler keeps the order
    collected): longest groups first. A run without xdist keeps the collection order."""
    if not hasattr(config, "workerinput"):
        return
    groups = {id(item): group_of(item.nodeid) for item in items}
    first: dict[str, int] = {}
    for k, item in enumerate(items):
        first.setdefault(groups[id(item)], k)
    items.sort(key=lambda it: (-COST_S.get(groups[id(it)], 0), first[groups[id(it)]]))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """`--dist loadgroup`: xdist's scope scheduler with these groups as its scopes, handed
    out in the order collected."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid)

    config.option.loadscopereorder = False  # longest first, as collected
    return GroupScheduling(config, log)
