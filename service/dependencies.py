"""FastAPI dependencies: the served dataset and the settings, for route handlers.

All ``async def``: FastAPI runs a plain ``def`` dependency in its thread pool, a thread
hop per dependency per request that cost more CPU than the planning itself.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Header, Request

from schema.api import OtherBuildBody

from .guard import BUILD_HEADER, answered_from
from .settings import Settings
from .store import Store

BuildHeader = Annotated[str | None, Header(
    alias=BUILD_HEADER.decode(),
    description="The build (manifest SHA-256, as answers' x-toppledb-build names it) that this request's action "
    "indices (failed_actions, action) were recorded under: the request is refused with 412 when another build would "
    "answer it. Without it, any build answers.",
)]


async def get_store(request: Request, requested: BuildHeader = None) -> Store:
    """The store being served when the request arrived: taken once, so a dataset swap
    during the request never mixes two builds in one answer; the answer names it (``guard.BUILD_HEADER``),
    and a request naming another build is refused (412, ``errors.OtherBuild``)."""
    return answered_from(request.scope, request.app.state.live.store, requested)


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

BUILD_RESPONSES = {412: {"model": OtherBuildBody, "description": "The request names another build (x-toppledb-build) "
                         "than the one that would answer it: its action indices name other candidates"}}
"""The answer every route that takes ``StoreDep`` may give, for its router's OpenAPI ``responses``."""
