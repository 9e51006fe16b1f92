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
