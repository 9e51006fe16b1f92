"""Place database app factory: settings, lifespan (vocabulary and index), error handling."""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager

from fastapi import FastAPI

from fleetmap.fleet.map_render import MapRenderer
from fleetmap.fleet.map_scene import SceneCache
from fleetmap.fleet.merge_worker import LiveMap
from fleetmap.place import PlaceDB, RetrainPolicy
from fleetmap.place.store import open_store
from fleetmap.services.auth import auth_summary
from fleetmap.services.docs import install_docs
from fleetmap.services.http_errors import install_error_handlers
from fleetmap.services.middleware import install_middleware
from fleetmap.services.place_db import live_routes, scene_routes
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.routes import router
from fleetmap.vocabulary import load_vocabulary

log = logging.getLogger(__name__)


def single_threaded_kernels() -> None:
    """One thread per faiss search, OpenCV call and BLAS product: a query is one vector and
    one pair, so their thread pools buy little, and their spinning threads starve a second
    replica's overlap worker (top: one replica at 190% CPU on 2 cores; 2 replicas verified
    fewer keyframes a second than 1)."""
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    faiss.omp_set_num_threads(1)
    cv2.setNumThreads(1)
    threadpool_limits(1)  # OpenBLAS / OpenMP of numpy and scipy


def start_live_map(db: PlaceDB, settings: Settings) -> LiveMap | None:
    """The merge worker, when an aligner is configured (`--aligner URL`)."""
    if not settings.aligner:
        return None
    from fleetmap.client import AlignerClient

    token = settings.aligner_token or settings.operator_token
    client = AlignerClient(
        settings.aligner, timeout=900, token=token.get_secret_value() if token else None
    )
    live = LiveMap(db, client.align, settings.live)
    live.client = client
    live.start()
    log.warning("live map: merging robots through the aligner at %s", settings.aligner)
    return live


def create_app(settings: Settings | None = None, announce: bool = True) -> FastAPI:
    """The app; `announce`: log its access control at start-up (the caller does when it
    knows the listening address: `fleetmap serve`, the services `merge` starts itself)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        single_threaded_kernels()
        vocab = load_vocabulary(settings.vocabulary)
        app.state.db = PlaceDB(
            open_store(settings.store, vocab.vocab_id, settings.pg_timeout_s),
            vocab,
            settings.cascade,
            RetrainPolicy(enabled=settings.auto_retrain),
            background=settings.background_overlaps,
            defer_detection=settings.defer_overlaps,
            detect_threads=settings.overlap_threads,
        )
        where = app.state.db.stats()["db_path"]
        log.info("place database at %s, vocabulary %s", where, vocab.vocab_id)
        if announce:
            log.warning("place database: %s", auth_summary(settings))
        app.state.renderer = MapRenderer(app.state.db)
        app.state.scene3d = SceneCache(app.state.renderer)
        app.state.map_pool = ThreadPoolExecutor(2, thread_name_prefix="map-routes")
        app.state.health_pool = ThreadPoolExecutor(1, thread_name_prefix="healthz")
        app.state.live = start_live_map(app.state.db, settings)
        yield
        if app.state.live is not None:
            app.state.live.stop()
            app.state.live.client.close()
        for pool in (app.state.map_pool, app.state.health_pool):
            pool.shutdown(wait=False, cancel_futures=True)
        app.state.db.close()

    app = FastAPI(
        title="fleetmap place database",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,  # served from local files by install_docs
        redoc_url=None,
        description="Keyframes of a robot fleet and the overlaps between their maps.",
    )
    app.state.settings = settings
    install_error_handlers(app)
    install_middleware(app)
    install_docs(app)
    app.include_router(router)
    app.include_router(live_routes.router)
    app.include_router(scene_routes.router)  # the page's 3D view
    scene_routes.install_static(app)
    return app
