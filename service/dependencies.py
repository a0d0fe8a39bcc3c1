"""FastAPI dependencies: the served dataset and the settings, for route handlers.

All ``async def``: FastAPI runs a plain ``def`` dependency in its thread pool, a thread
hop per dependency per request that cost more CPU than the planning itself.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .guard import answered_from
from .settings import Settings
from .store import Store


async def get_store(request: Request) -> Store:
    """The store being served when the request arrived: taken once, so a dataset swap
    during the request never mixes two builds in one answer; the answer names it (``guard.BUILD_HEADER``)."""
    return answered_from(request.scope, request.app.state.live.store)


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
