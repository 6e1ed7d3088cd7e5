"""Routes of the ``recordings`` resource: what can be replayed."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from fastapi.concurrency import run_in_threadpool

from .deps import CatalogDep, errors
from .models import RecordingInfo, RecordingList, RecordingName, RecordingSummary

router = APIRouter(prefix="/api/recordings", tags=["recordings"])


@router.get("", response_model=RecordingList, summary="List the recordings")
def list_recordings(catalog: CatalogDep) -> RecordingList:
    """The recordings of the recordings directory and the default one."""
    infos = []
    for entry in catalog.entries().values():
        m = entry.manifest or {}
        files = m.get("files") if isinstance(m.get("files"), dict) else {}

        def number(key: str, m: dict = m) -> float | None:
            value = m.get(key)
            return float(value) if isinstance(value, int | float) and not isinstance(
                value, bool) else None

        infos.append(RecordingInfo(
            name=entry.name, default=entry.default,
            scenario=m.get("scenario") if isinstance(m.get("scenario"), str) else None,
            seed=m.get("seed") if isinstance(m.get("seed"), int) else None,
            start_gpst=number("start_gpst"), duration_s=number("duration_s"),
            has_reference=bool(files.get("reference")), problem=entry.problem))
    return RecordingList(recordings=infos, default=catalog.default_name())


# ``:path`` so that a name with a slash reaches the validation and gets a precise 422 rather
# than the router's bare 404.
@router.get("/{name:path}", response_model=RecordingSummary, responses=errors(404),
            summary="Summary of one recording")
async def recording_summary(name: Annotated[RecordingName, Path()],
                            catalog: CatalogDep) -> RecordingSummary:
    """What the recording holds (``berthing-aid info``): duration, sensors, satellites per
    epoch, frames, reference. The first call loads the recording (a few seconds)."""
    catalog.resolve(name)  # reject bad names before touching anything
    return RecordingSummary(**await run_in_threadpool(catalog.summary, name))
