"""``GET /v1/categories``: every knowledge-graph class with its number of objects."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from wardmap.server.api.deps import ObjectMapDep
from wardmap.server.api.schemas import CategoryList, CategoryOut, Flag
from wardmap.shared.errors import KnowledgeGraphError

router = APIRouter()


@router.get("/v1/categories", response_model=CategoryList)
def categories(
    objects: ObjectMapDep,
    include_unconfirmed: Annotated[Flag, Query(description="also count unconfirmed objects")] = "false",
) -> CategoryList:
    """Every knowledge-graph class with its number of (confirmed) objects in the map."""
    counts = objects.categories(include_unconfirmed == "true")
    out = []
    for name, n in counts.items():
        try:
            mobility: str | None = str(objects.knowledge.mobility(name))
        except KnowledgeGraphError:
            mobility = None
        out.append(CategoryOut(name=name, mobility=mobility, count=n))
    return CategoryList(categories=out, total=sum(counts.values()))
