import pytest

from fleetmap.frame import decode
from fleetmap.services.cli import main


def test_extract_writes_one_decodable_frame_per_keyframe(tum_robot, tmp_path, capsys):
    out = tmp_path / "frames"
    assert main(["extract", f"scout={tum_robot}", "-o", str(out), "--kf-interval", "0.01"]) == 0
    files = sorted(out.glob("*.fmf"))
    assert len(files) == 2
    f = decode(files[0].read_bytes())
    assert f.robot_id == "scout" and f.intrinsics.fx == 517.3
    assert f.point_valid.sum() > 50
    assert "2 keyframes" in capsys.readouterr().out


def test_extract_draws_its_progress_bar_unless_quiet(tum_robot, tmp_path, capsys):
    """Issue 25: `-q` turned merge's bars off but not extract's."""
    for quiet in (False, True):
        args = ["extract", str(tum_robot), "-o", str(tmp_path / f"q{quiet}")]
        assert main(["-q", *args] if quiet else args) == 0
        captured = capsys.readouterr()
        assert ("extract" in captured.err and "kf/s" in captured.err) is not quiet
        assert "keyframes of" in captured.out  # the result line stays


def test_extract_reports_missing_folder(tmp_path, capsys):
    assert main(["extract", str(tmp_path / "nowhere"), "-o", str(tmp_path / "outs" / "o")]) == 1
    assert "Robot folder not found" in capsys.readouterr().err


def test_extract_applies_intrinsics_overrides(tum_robot, tmp_path):
    out = tmp_path / "frames"
    assert (
        main(
            [
                "extract",
                str(tum_robot),
                "-o",
                str(out),
                "--fx",
                "525",
                "--fy",
                "525",
                "--depth-scale",
                "5000",
            ]
        )
        == 0
    )
    f = decode(next(out.glob("*.fmf")).read_bytes())
    assert f.intrinsics.fx == 525.0 and f.intrinsics.cx == 318.6


def test_a_failed_extract_leaves_no_half_robot_and_an_empty_output_is_refused(
    tum_robot, tmp_path, capsys
):
    """A frame that cannot be read ended the run with the frames before it left in the
    output folder; `-o ''` wrote into the current folder (an outside tester's review)."""
    (tum_robot / "rgb").joinpath(sorted((tum_robot / "rgb").iterdir())[-1].name).write_bytes(b"x")
    out = tmp_path / "frames"
    assert main(["extract", str(tum_robot), "-o", str(out), "--kf-interval", "0.01"]) == 1
    assert "Cannot read colour image" in capsys.readouterr().err
    assert list(out.glob("*.fmf")) == []
    with pytest.raises(SystemExit):  # a usage error (tests/unit/test_out_folder.py)
        main(["extract", str(tum_robot), "-o", ""])
    assert "invalid folder name (not empty) value" in capsys.readouterr().err


def test_bag_topics_given_for_folders_alone_are_refused(tum_robot, tmp_path, capsys):
    """`--rgb-topic` on robots that are all folders was taken and ignored, unsaid (an
    outside tester's review); with a bag among them it chooses that bag's topics."""
    for args in (
        [
            "extract",
            str(tum_robot),
            "-o",
            str(tmp_path / "outs" / "f"),
            "--rgb-topic",
            "/camera/color",
        ],
        [
            "merge",
            f"a={tum_robot}",
            "-o",
            str(tmp_path / "outs" / "o"),
            "--pose-topic",
            "/o",
            "--info-topic",
            "/i",
        ],
    ):
        assert main(args) == 1
        err = capsys.readouterr().err
        assert "no robot given is a ROS bag" in err and args[-2] in err, err
        assert not (tmp_path / "outs").exists()
