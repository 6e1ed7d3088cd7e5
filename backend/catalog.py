"""The recordings the server may open (the catalogue): names to paths, loaded recordings
cached. Requests name a recording; only names from this listing are ever turned into paths."""

from __future__ import annotations

import json
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recordings.format import Recording, RecordingError, check_manifest, load, summary

from . import models
from .errors import BadRequest, NotFound, Unprocessable

RECORDING_NAME = re.compile(models.RECORDING_NAME)



@dataclass(frozen=True)
class RecordingEntry:
    name: str
    path: Path
    default: bool
    manifest: dict[str, Any] | None  # None when manifest.json cannot be read
    problem: str | None


class RecordingCatalog:
    """The recordings the server may open: the sub-directories of ``directory`` that hold a
    ``manifest.json``, plus the default recording. Requests name a recording; only names
    from this listing are ever turned into paths."""

    def __init__(self, directory: Path | None, default: Path | None, cache_size: int = 2) -> None:
        self.directory = directory.resolve() if directory else None
        self.default = default.resolve() if default else None
        self._cache: OrderedDict[Path, Recording] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        self._loading: dict[Path, threading.Lock] = {}
        # why a recording could not be loaded, by path, with its files' latest change then
        self._failed: dict[Path, tuple[float, str]] = {}

    def _read_manifest(self, path: Path) -> tuple[dict[str, Any] | None, str | None]:
        """The manifest's JSON, and why the recording cannot be opened: what the manifest
        says without reading the data, else what the last attempt to load it said (until
        its files change)."""
        try:
            data = json.loads((path / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            return None, f"manifest.json cannot be read: {exc}"
        if not isinstance(data, dict):
            return None, "manifest.json is not a JSON object"
        try:
            check_manifest(path)
        except RecordingError as exc:
            return data, str(exc)
        failed = self._failed.get(path.resolve())
        if failed is not None and failed[0] == _last_change(path):
            return data, failed[1]
        return data, None

    def entries(self) -> dict[str, RecordingEntry]:
        """Name → entry, rescanned on each call (recordings may be added while running)."""
        found: dict[str, RecordingEntry] = {}
        if self.directory is not None and self.directory.is_dir():
            for child in sorted(self.directory.iterdir()):
                if (child.is_dir() and RECORDING_NAME.match(child.name)
                        and (child / "manifest.json").is_file()):
                    manifest, problem = self._read_manifest(child)
                    found[child.name] = RecordingEntry(child.name, child.resolve(),
                                                       child.resolve() == self.default,
                                                       manifest, problem)
        if self.default is not None and not any(e.default for e in found.values()):
            name = self.default.name
            if name in found or not RECORDING_NAME.match(name):
                name = "default"
            manifest, problem = (self._read_manifest(self.default)
                                 if self.default.is_dir() else (None, "directory not found"))
            found[name] = RecordingEntry(name, self.default, True, manifest, problem)
        return found

    def default_name(self) -> str | None:
        return next((e.name for e in self.entries().values() if e.default), None)

    def resolve(self, name: str) -> RecordingEntry:
        """The entry named ``name``; 400 for a name that is not a plain directory name (the
        API's validation rejects those first), 404 for an unknown one. Nothing from ``name``
        reaches the file system: it is only looked up in the listing."""
        if not isinstance(name, str) or not name:
            raise BadRequest("recording name is empty")
        if "/" in name or "\\" in name:
            raise BadRequest(f"recording name {name!r} contains a path separator; use a name "
                             "from GET /api/recordings")
        if not RECORDING_NAME.match(name):
            raise BadRequest(f"recording name {name!r} is not a plain name (letters, digits, "
                             "'.', '_', '-'; at most 128 characters)")
        entries = self.entries()
        if name not in entries:
            known = ", ".join(sorted(entries)) or "none"
            raise NotFound(f"no recording named {name!r} (available: {known})")
        return entries[name]

    def load(self, name: str) -> Recording:
        """The loaded recording (cached, most recently used first)."""
        entry = self.resolve(name)
        with self._lock:
            if entry.path in self._cache:
                self._cache.move_to_end(entry.path)
                return self._cache[entry.path]
            path_lock = self._loading.setdefault(entry.path, threading.Lock())
        with path_lock:  # one load per recording even when requests race
            with self._lock:
                if entry.path in self._cache:
                    return self._cache[entry.path]
            try:
                rec = load(entry.path)
            except RecordingError as exc:
                self._failed[entry.path] = (_last_change(entry.path), str(exc))
                raise Unprocessable(f"recording {name!r} cannot be read: {exc}") from None
            with self._lock:
                self._failed.pop(entry.path, None)
                self._cache[entry.path] = rec
                while len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
            return rec

    def summary(self, name: str) -> dict[str, Any]:
        info = summary(self.load(name))
        info.pop("path", None)  # the server's file layout is none of the client's business
        return info


def _last_change(path: Path) -> float:
    """The latest modification time of the recording directory's files (a dozen)."""
    try:
        return max((f.stat().st_mtime for f in path.rglob("*")), default=0.0)
    except OSError:
        return 0.0
