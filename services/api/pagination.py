"""Limit/offset pagination shared by the list routes: `?limit=&offset=` in, `{items, total, limit, offset}`
out."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Generic, TypeVar

from fastapi import Depends, Query, Response
from pydantic import BaseModel

T = TypeVar("T")
Item = TypeVar("Item", bound=BaseModel)

MAX_LIMIT = 1000
MAX_OFFSET = 2**31 - 1  # Postgres OFFSET is bigint, but nobody pages this far; keeps values sane


@dataclass(frozen=True)
class PageParams:
    """Which slice of a list the caller wants."""

    limit: int
    offset: int


async def page_params(
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT, description="items per page")] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="items to skip")] = 0,
) -> PageParams:
    """Read `limit` and `offset` from the query string."""
    return PageParams(limit=limit, offset=offset)


PageDep = Annotated[PageParams, Depends(page_params)]


class Page(BaseModel, Generic[T]):
    """One page of a list and the size of the whole (filtered) list."""

    items: list[T]
    total: int
    limit: int
    offset: int


def page_response(page: Page[Item]) -> Response:
    """`page` as a JSON response, serialized by the caller (a route's worker thread) one item at a time.

    FastAPI serializes a returned model on the event loop: a page of 1000 views with their links held it (and
    /health, and every other tenant) for a few hundred milliseconds. Item by item, the event loop gets the
    interpreter between items. The bytes are those of `page.model_dump_json()`.
    """
    items = b",".join(item.model_dump_json().encode() for item in page.items)
    tail = f'],"total":{page.total},"limit":{page.limit},"offset":{page.offset}}}'.encode()
    return Response(b'{"items":[' + items + tail, media_type="application/json")
