"""FastAPI dependencies: the loaded dataset for route handlers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .store import Store


def get_store(request: Request) -> Store:
    """The store ``create_app`` loaded at start (tests may override this dependency)."""
    return request.app.state.store


StoreDep = Annotated[Store, Depends(get_store)]
