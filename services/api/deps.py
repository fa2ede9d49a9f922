"""Dependencies of the API routes, declared once: settings, a database session per request and
bearer API key access by scope.

`create_app` keeps the settings, the engine and a session factory on `app.state`; routes take
`SettingsDep`, `SessionDep` and one of `ReadAccess`, `SubmitAccess`, `AdminAccess`.
Access: `Authorization: Bearer KEY`; the key's SHA-256 must be an unrevoked `api_key` with the
scope (admin implies all, submit implies read). A missing or unknown key is 401 (with
`WWW-Authenticate: Bearer`), a key without the scope 403. With `settings.api_read_open`, GET and
HEAD requests need no key (a key that is given is still checked).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from db.service_records import authenticate, grants
from db.settings import Settings


def get_settings_dep(request: Request) -> Settings:
    """The app's settings (created once by `create_app`)."""
    return request.app.state.settings


def get_engine(request: Request) -> Engine:
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


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(401, detail, headers={"WWW-Authenticate": 'Bearer realm="citytherm"'})


def _access(scope: str) -> Callable[..., Principal]:
    def check(
        request: Request,
        session: SessionDep,
        settings: SettingsDep,
        creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> Principal:
        """Checks the request's API key for the scope."""
        if creds is None or not creds.credentials:
            if scope == "read" and settings.api_read_open and request.method in ("GET", "HEAD"):
                return Principal(None, "anonymous", ("read",))
            raise _unauthorized("an API key is needed: Authorization: Bearer KEY")
        key = authenticate(session, key=creds.credentials)
        session.rollback()  # end the read transaction; the route's unit of work starts afresh
        if key is None:
            raise _unauthorized("unknown or revoked API key")
        if not grants(key.scopes, scope):
            raise HTTPException(403, f"the API key {key.prefix}… lacks the {scope!r} scope")
        return Principal(key.id, key.name, key.scopes)

    check.__name__ = f"require_{scope}"
    return check


ReadAccess = Annotated[Principal, Depends(_access("read"))]
SubmitAccess = Annotated[Principal, Depends(_access("submit"))]
AdminAccess = Annotated[Principal, Depends(_access("admin"))]
