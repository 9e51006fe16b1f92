"""`fleetmap merge` records both services' parameters in force (their `GET /config`) in
report.json's `parameters`, beside its own: from the session's SUN3D merge (its services
embedded, so their settings resolve from this process's environment as here)."""

from __future__ import annotations

import dataclasses

from fleetmap.services.aligner.config import Settings as AlignerSettings
from fleetmap.services.place_db.config import Settings


def test_merge_report_holds_both_services_parameters(sun3d_merge):
    _, report = sun3d_merge
    params = report["parameters"]
    for key in ("keyframes", "vocabulary", "max_views", "voxel_m", "align_method", "cycles"):
        assert key in params, key  # the command's own, as before
    db, al = params["place_db"], params["aligner"]
    place, aligner = Settings(), AlignerSettings()
    assert db["cascade"] == dataclasses.asdict(place.cascade)
    assert db["live"] == dataclasses.asdict(place.live)
    assert db["database"] is None and db["aligner"] is None  # SQLite, no merge worker
    assert db["max_body_bytes"] == place.max_body_bytes
    assert al["align"] == dataclasses.asdict(aligner.align)
    assert al["max_views"] == aligner.max_views >= params["max_views"]  # merge's fit in
    for secret in ("operator_token", "robot_tokens", "aligner_token"):
        assert secret not in db and secret not in al


def test_merge_with_its_own_vocabulary(tmp_path):
    """README's "Training a vocabulary for your own site": `merge --vocab FILE` extracted
    with FILE while the place database it started itself loaded the shipped one, and
    refused ("pass the same file with --vocab": it was). Now both use FILE."""
    import json
    from pathlib import Path

    from fleetmap.services.cli import main

    examples = Path(__file__).resolve().parents[2] / "examples"
    example = examples / "fr1_pair"
    vocab = tmp_path / "site.npz"  # from another robot's 16 keyframes
    train = ["vocab", "train", str(examples / "fr1_rpy_fleet" / "alpha"), "--words", "64"]
    assert main(["-q", *train, "-o", str(vocab)]) == 0
    robots = [str(example / "alpha"), str(example / "bravo")]
    assert main(["-q", "merge", *robots, "--vocab", str(vocab), "-o", str(tmp_path / "o")]) == 0
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["unmerged"] == []
    assert report["parameters"]["place_db"]["vocabulary"] == str(vocab)
