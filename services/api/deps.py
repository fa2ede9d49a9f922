"""Dependencies of the API routes, declared once: settings, a database session per request and
bearer API key access by scope.

`create_app` keeps the settings, the engine and a session factory on `app.state`; routes take
`SettingsDep`, `SessionDep` and one of `ReadAccess`, `SubmitAccess`, `AdminAccess`.
Access: `Authorization: Bearer KEY`; the key's SHA-256 must be an unrevoked `api_key` with the
scope (admin implies all, submit implies read). A missing or unknown key is 401 (with
`WWW-Authenticate: Bearer`), a key without the scope 403. With `settings.api_read_open`, GET and
HEAD requests need no key (a key that is given is still checked).

Authenticated keys are kept `settings.api_key_cache_s` seconds (default 5) per process
(`KeyCache`: the key's SHA-256 -> its record, at most `KEY_CACHE_SIZE` keys), so that a
request with a known key costs no database round trip: **a revoked key is refused within that
time** (not at once). Unknown and revoked keys are never kept. The access checks and the
settings / engine dependencies are `async` (no thread hop); a cache miss looks the key up in
the thread pool.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from db.service_records import ApiKeyInfo, authenticate, grants, hash_key
from db.settings import Settings

KEY_CACHE_SIZE = 1024


async def get_settings_dep(request: Request) -> Settings:
    """The app's settings (created once by `create_app`)."""
    return request.app.state.settings


async def get_engine(request: Request) -> Engine:
    """The app's database engine."""
    return request.app.state.engine


def get_session(request: Request) -> Iterator[Session]:
    """A session for this request; rolled back (if the unit of work did not commit) and closed
    at the end."""
    session: Session = request.app.state.session_factory()
    try:
        yield session
    finally:
        session.close()


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
EngineDep = Annotated[Engine, Depends(get_engine)]
SessionDep = Annotated[Session, Depends(get_session)]

_bearer = HTTPBearer(auto_error=False, bearerFormat="API key", description="`citytherm apikey create`")


@dataclass(frozen=True)
class Principal:
    """Who is calling: an API key (id, name, scopes), or anonymous (id None) on an open read."""

    key_id: int | None
    name: str
    scopes: tuple[str, ...]


class KeyCache:
    """Authenticated API keys of this process: SHA-256 of the key -> its record, each kept `ttl_s`
    seconds after its database lookup, at most `size` keys (the oldest lookups go first).
    Thread-safe. A revoked key is refused once its entry expires (within `ttl_s`)."""

    def __init__(self, ttl_s: float, size: int = KEY_CACHE_SIZE) -> None:
        self.ttl_s = ttl_s
        self.size = size
        self._keys: OrderedDict[str, tuple[float, ApiKeyInfo]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, digest: str) -> ApiKeyInfo | None:
        """The record of the key with SHA-256 `digest` if looked up less than `ttl_s` ago."""
        with self._lock:
            hit = self._keys.get(digest)
            if hit is None:
                return None
            if time.monotonic() >= hit[0]:
                del self._keys[digest]
                return None
            return hit[1]

    def put(self, digest: str, key: ApiKeyInfo) -> None:
        """Keep `key` (just found unrevoked in the database) for `ttl_s` seconds."""
        if self.ttl_s <= 0:
            return
        with self._lock:
            self._keys.pop(digest, None)
            self._keys[digest] = (time.monotonic() + self.ttl_s, key)
            while len(self._keys) > self.size:
                self._keys.popitem(last=False)


def _key_cache(app: FastAPI, settings: Settings) -> KeyCache:
    """The app's `KeyCache` (made on first use with `settings.api_key_cache_s`)."""
    cache = getattr(app.state, "api_key_cache", None)
    if cache is None:
        cache = app.state.api_key_cache = KeyCache(settings.api_key_cache_s)
    return cache


def _lookup(session_factory: sessionmaker[Session], key: str) -> ApiKeyInfo | None:
    """The unrevoked key `key` from the database (a short session of its own), or None."""
    with session_factory() as session:
        return authenticate(session, key=key)


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(401, detail, headers={"WWW-Authenticate": 'Bearer realm="citytherm"'})


def _access(scope: str) -> Callable[..., object]:
    async def check(
        request: Request,
        settings: SettingsDep,
        creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> Principal:
        """Checks the request's API key for the scope (`KeyCache` first, then the database)."""
        if creds is None or not creds.credentials:
            if scope == "read" and settings.api_read_open and request.method in ("GET", "HEAD"):
                return Principal(None, "anonymous", ("read",))
            raise _unauthorized("an API key is needed: Authorization: Bearer KEY")
        cache = _key_cache(request.app, settings)
        digest = hash_key(creds.credentials)
        key = cache.get(digest)
        if key is None:
            key = await run_in_threadpool(_lookup, request.app.state.session_factory, creds.credentials)
            if key is None:
                raise _unauthorized("unknown or revoked API key")
            cache.put(digest, key)
        if not grants(key.scopes, scope):
            raise HTTPException(403, f"the API key {key.prefix}… lacks the {scope!r} scope")
        return Principal(key.id, key.name, key.scopes)

    check.__name__ = f"require_{scope}"
    return check


ReadAccess = Annotated[Principal, Depends(_access("read"))]
SubmitAccess = Annotated[Principal, Depends(_access("submit"))]
AdminAccess = Annotated[Principal, Depends(_access("admin"))]
