"""Place database app factory: settings, lifespan (vocabulary and index), error handling."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI

from fleetmap.matching import MatchParams
from fleetmap.place import CascadeParams, PlaceDB, RetrainPolicy
from fleetmap.services import common
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.routes import router
from fleetmap.vocabulary import load_vocabulary

log = logging.getLogger(__name__)


def cascade_params(st: Settings) -> CascadeParams:
    return CascadeParams(
        m_clusters=st.m_clusters,
        gist_threshold=st.gist_threshold,
        max_candidates=st.max_candidates,
        bow_threshold=st.bow_threshold,
        max_verify=st.max_verify,
        max_verify_per_robot=st.max_verify_per_robot,
        match=MatchParams(
            ratio=st.ratio,
            min_inliers=st.min_inliers,
            min_inlier_ratio=st.min_inlier_ratio,
            min_inliers_3d_check=st.min_inliers_3d_check,
            min_rigid_inliers=st.min_rigid_inliers,
        ),
    )


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        vocab = load_vocabulary(settings.vocabulary)
        app.state.db = PlaceDB(
            settings.db_path,
            vocab,
            cascade_params(settings),
            RetrainPolicy(enabled=settings.auto_retrain),
            background=settings.background_overlaps,
        )
        log.info("place database at %s, vocabulary %s", settings.db_path, vocab.vocab_id)
        log.warning("place database: %s", common.auth_summary(settings))
        yield
        app.state.db.close()

    app = FastAPI(
        title="fleetmap place database",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,  # served from local files by common.install_docs
        redoc_url=None,
        description="Keyframes of a robot fleet and the overlaps between their maps.",
    )
    app.state.settings = settings
    common.install(app)
    common.install_docs(app)
    app.include_router(router)
    return app
