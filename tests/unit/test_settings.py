"""One settings tree: the services' settings nest the core's parameter dataclasses."""

import pytest

from fleetmap.align.types import AlignParams
from fleetmap.matching import MatchParams
from fleetmap.place import CascadeParams
from fleetmap.services.aligner.config import Settings as AlignerSettings
from fleetmap.services.place_db.config import Settings as PlaceDBSettings


def test_defaults_are_the_core_dataclasses_themselves():
    assert AlignerSettings().align == AlignParams()
    assert PlaceDBSettings().cascade == CascadeParams()
    assert isinstance(PlaceDBSettings().cascade.match, MatchParams)


def test_every_parameter_is_settable_by_its_nested_name(monkeypatch):
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS", "31")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__TRY_MLP", "false")  # not settable before
    monkeypatch.setenv("FLEETMAP_PLACE_DB_CASCADE__GIST_THRESHOLD", "0.6")
    monkeypatch.setenv("FLEETMAP_PLACE_DB_CASCADE__MATCH__MIN_EPIPOLAR_INLIERS", "25")
    al, db = AlignerSettings().align, PlaceDBSettings().cascade
    assert al.min_inliers == 31 and al.try_mlp is False and isinstance(al, AlignParams)
    assert db.gist_threshold == 0.6 and db.match.min_epipolar_inliers == 25
    assert db.match.ratio == MatchParams().ratio  # the others keep their defaults


def test_unreadable_and_old_flat_names_are_refused(monkeypatch):
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS", "many")
    with pytest.raises(ValueError, match="min_inliers"):
        AlignerSettings()
    monkeypatch.delenv("FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS")
    monkeypatch.setenv("FLEETMAP_ALIGNER_MIN_INLIERS", "20")
    with pytest.raises(ValueError, match="FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS"):
        AlignerSettings()
    monkeypatch.setenv("FLEETMAP_PLACE_DB_MIN_INLIERS", "20")
    with pytest.raises(ValueError, match="CASCADE__MATCH__MIN_EPIPOLAR_INLIERS"):
        PlaceDBSettings()
