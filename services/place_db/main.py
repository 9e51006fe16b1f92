"""Place database app factory: settings, lifespan (vocabulary and index), error handling."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

from fastapi import FastAPI

from fleetmap.place import PlaceDB, RetrainPolicy
from fleetmap.services import common
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.routes import router
from fleetmap.vocabulary import load_vocabulary

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        vocab = load_vocabulary(settings.vocabulary)
        app.state.db = PlaceDB(
            settings.store,
            vocab,
            settings.cascade,
            RetrainPolicy(enabled=settings.auto_retrain),
            background=settings.background_overlaps,
        )
        where = app.state.db.stats()["db_path"]
        log.info("place database at %s, vocabulary %s", where, vocab.vocab_id)
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
