"""--out of `merge` and `map` checked before any work, and a previous run's outputs that
this run did not write again removed once it has written its own (outside testers' reviews)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from fleetmap.errors import BadInput
from fleetmap.services.cli import main
from fleetmap.services.outputs import prepare_out

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fr1_rpy_fleet"


def test_a_previous_runs_trajectories_and_pcd_do_not_stay_beside_this_runs(tmp_path):
    """A reused --out kept trajectories/alpha.txt of the last run beside this run's X.txt
    and Y.txt, while report.json listed X and Y only. What the last run's report.json names
    goes once this run has written its own, where this run did not write it again."""
    out = tmp_path / "out"
    (out / "trajectories").mkdir(parents=True)
    for name in ("alpha.txt", "bravo.txt", "X.txt"):
        (out / "trajectories" / name).write_text("0 0 0 0 0 0 0 1\n")
    (out / "trajectories" / "notes.txt").write_text("mine")  # no robot of the last run's
    (out / "merged.pcd").write_text("old")
    last = {"robots": {"alpha": {}, "bravo": {}, "X": {}}, "parameters": {"pcd": True}}
    (out / "report.json").write_text(json.dumps(last))
    previous = prepare_out(out)
    assert len(list((out / "trajectories").iterdir())) == 4  # nothing gone before the run
    time.sleep(0.01)
    (out / "trajectories" / "X.txt").write_text("1 0 0 0 0 0 0 1\n")  # this run's
    previous.remove_unwritten()
    assert sorted(p.name for p in (out / "trajectories").iterdir()) == ["X.txt", "notes.txt"]
    assert not (out / "merged.pcd").exists()
    assert not prepare_out(tmp_path / "new").files  # nothing there yet: nothing to remove
    assert not any((tmp_path / "new" / "trajectories").iterdir())  # made, probed, empty


def test_files_no_run_of_ours_wrote_are_never_removed(tmp_path, capsys):
    """An outside tester's trajectories/my_groundtruth.txt and merged.pcd in --out went with
    a merge that then could not reach its aligner. Without a report.json of ours, or where
    it names neither, nothing is removed, whether the run fails or succeeds."""
    out = tmp_path / "myproj"
    (out / "trajectories").mkdir(parents=True)
    mine = [out / "trajectories" / "my_groundtruth.txt", out / "merged.pcd"]
    for f in mine:
        f.write_text("mine")
    robots = [f"{r}={EXAMPLE / r}" for r in ("alpha", "bravo")]
    args = ["-q", "merge", *robots, "-o", str(out), "--place-db", "http://127.0.0.1:9"]
    assert main([*args, "--aligner", "http://127.0.0.1:9"]) == 1
    assert "Cannot reach http://127.0.0.1:9" in capsys.readouterr().err
    assert all(f.read_text() == "mine" for f in mine)
    (out / "report.json").write_text(json.dumps({"robots": ["alpha"], "parameters": {}}))
    prepare_out(out).remove_unwritten()  # names alpha, without --pcd: not these
    (out / "report.json").write_text("{not json")  # not one we can read: nothing ours
    prepare_out(out).remove_unwritten()
    for robots in ("my_groundtruth", ["../merged.pcd", "/etc/passwd", 3, None]):  # no ids
        (out / "report.json").write_text(json.dumps({"robots": robots}))
        assert not prepare_out(out).files
    assert all(f.read_text() == "mine" for f in mine)


def test_an_empty_out_folder_name_is_a_usage_error(tmp_path, capsys):
    """`merge -o ""` wrote its outputs into the working folder (Path("") is "."), as
    `extract -o ""` once did; every command that writes a folder refuses it."""
    robot = str(EXAMPLE / "alpha")
    for args in (
        ["merge", robot, "-o", ""],
        ["map", "--place-db", "http://127.0.0.1:9", "-o", " "],
        ["extract", robot, "-o", ""],
        ["simulate", ""],
        ["convert", "x.bag", "-o", ""],
    ):
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code == 2
        assert "invalid folder name (not empty) value" in capsys.readouterr().err


def test_an_out_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path):
    """A read-only --out, or trajectories/C.txt a folder, failed after the whole merge (an
    outside tester's review: 12-14 s of work, then "Read-only file system"). Both are
    refused by `prepare_out`, before anything is read: --out is made and written to once."""
    out = tmp_path / "out"
    (out / "trajectories" / "C.txt").mkdir(parents=True)
    with pytest.raises(BadInput, match="trajectories/C.txt is a folder"):
        prepare_out(out, ["A", "C"])
    # root writes into a read-only folder: a place where no folder can be made stands in
    (tmp_path / "file").write_text("")
    with pytest.raises(BadInput, match="cannot write there"):
        prepare_out(tmp_path / "file" / "out")


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
