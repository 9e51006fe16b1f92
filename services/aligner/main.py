"""Aligner app factory: settings, error handling, the merged-cloud cache."""

from __future__ import annotations

import logging
from collections import OrderedDict
from contextlib import asynccontextmanager

from fastapi import FastAPI

from fleetmap.services.aligner.budget import PixelBudget
from fleetmap.services.aligner.config import Settings
from fleetmap.services.aligner.routes import router
from fleetmap.services.auth import auth_summary
from fleetmap.services.docs import install_docs
from fleetmap.services.http_errors import install_error_handlers
from fleetmap.services.middleware import install_middleware


def create_app(settings: Settings | None = None, announce: bool = True) -> FastAPI:
    """The app; `announce`: log its access control at start-up (the caller does when it
    knows the listening address: `fleetmap serve`, the services `merge` starts itself)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        import open3d  # noqa: F401  heavy import at start-up, not on the first request

        # not torch (1.3-1.5 s of a core): the MLP is numpy; only the second look's
        # descriptor products use it (`fleetmap.matching._products`), and import it then

        app.state.clouds = OrderedDict()
        app.state.pixels = PixelBudget(
            settings.max_pixels_in_flight, requests=settings.max_requests_in_flight
        )
        if announce:
            logging.getLogger(__name__).warning("aligner: %s", auth_summary(settings))
        yield
        app.state.clouds.clear()

    app = FastAPI(
        title="fleetmap aligner",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,  # served from local files by install_docs
        redoc_url=None,
        description="Fits the transform between two robots' maps from RGB-D pairs.",
    )
    app.state.settings = settings
    install_error_handlers(app)
    install_middleware(app)
    install_docs(app)
    app.include_router(router)
    return app
