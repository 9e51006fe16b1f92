"""--out of `merge` and `map` checked before any work, and a previous run's outputs that
this run may not write again removed (an outside tester's review)."""

from __future__ import annotations

import pytest

from fleetmap.errors import BadInput
from fleetmap.services.outputs import prepare_out


def test_a_previous_runs_trajectories_and_pcd_do_not_stay_beside_this_runs(tmp_path):
    """A reused --out kept trajectories/alpha.txt of the last run beside this run's X.txt
    and Y.txt, while report.json listed X and Y only."""
    out = tmp_path / "out"
    (out / "trajectories").mkdir(parents=True)
    for name in ("alpha.txt", "bravo.txt"):
        (out / "trajectories" / name).write_text("0 0 0 0 0 0 0 1\n")
    (out / "trajectories" / "notes.md").write_text("mine")  # not ours: kept
    (out / "merged.pcd").write_text("old")
    (out / "report.json").write_text("{}")  # written again by the run
    prepare_out(out)
    assert sorted(p.name for p in (out / "trajectories").iterdir()) == ["notes.md"]
    assert not (out / "merged.pcd").exists() and (out / "report.json").exists()
    prepare_out(tmp_path / "new")  # nothing there yet: nothing to check
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize(
    ("make", "named"),
    [
        (lambda out: (out / "report.json").mkdir(parents=True), "report.json is a folder"),
        (lambda out: (out / "fleet.mcap").mkdir(parents=True), "fleet.mcap is a folder"),
        (lambda out: out.mkdir() or (out / "trajectories").write_text(""), "trajectories is a"),
        (lambda out: out.write_text(""), "exists and is not a folder"),
    ],
)
def test_an_out_folder_the_run_cannot_write_is_refused_first(tmp_path, make, named):
    """A `report.json` folder failed the merge at its very end, every other file written."""
    out = tmp_path / "out"
    make(out)
    with pytest.raises(BadInput, match=named):
        prepare_out(out)
