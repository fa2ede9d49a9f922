"""Engine and session factory for the city model database.

In: a `db.settings.Settings` (its `database_url`) or a URL string. Out: SQLAlchemy
`Engine` / `sessionmaker`. Plain `postgresql://` URLs are turned into the psycopg 3 driver URL.
Nothing is read at import time.
"""

from __future__ import annotations

from sqlalchemy import Engine, create_engine
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from db.settings import Settings

__all__ = ["as_engine", "make_engine", "make_session_factory", "psycopg_url", "sqlalchemy_url"]


def sqlalchemy_url(url: str) -> str:
    """`postgresql://...` or `postgres://...` -> `postgresql+psycopg://...`; other URLs unchanged.

    >>> sqlalchemy_url("postgresql://postgres@127.0.0.1:5432/citytherm")
    'postgresql+psycopg://postgres@127.0.0.1:5432/citytherm'
    """
    if url.startswith("postgres://"):
        url = "postgresql://" + url[len("postgres://") :]
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url[len("postgresql://") :]
    return url


def psycopg_url(url: str) -> str:
    """A SQLAlchemy URL -> the plain libpq URL psycopg accepts (driver suffix dropped)."""
    u = make_url(sqlalchemy_url(url))
    return u.set(drivername="postgresql").render_as_string(hide_password=False)


def make_engine(settings_or_url: Settings | str, *, echo: bool = False) -> Engine:
    """Engine for `settings.database_url` (or a URL string); pool pre-ping on, the pool sized by
    `database_pool_size` / `database_max_overflow` (a URL string: the settings' defaults)."""
    if isinstance(settings_or_url, str):
        url = settings_or_url
        pool = Settings.model_fields["database_pool_size"].default
        overflow = Settings.model_fields["database_max_overflow"].default
    else:
        url = settings_or_url.database_url
        pool, overflow = settings_or_url.database_pool_size, settings_or_url.database_max_overflow
    return create_engine(
        sqlalchemy_url(url), echo=echo, pool_pre_ping=True, future=True, pool_size=pool, max_overflow=overflow
    )


def make_session_factory(engine_or_settings: Engine | Settings | str) -> sessionmaker[Session]:
    """`sessionmaker` bound to an engine (made from settings or a URL when one is given);
    `expire_on_commit=False` so objects stay readable after the unit of work commits."""
    engine = engine_or_settings if isinstance(engine_or_settings, Engine) else make_engine(engine_or_settings)
    return sessionmaker(bind=engine, expire_on_commit=False)


def as_engine(db: Engine | sessionmaker[Session] | Settings | str) -> Engine:
    """An Engine from an Engine, a sessionmaker bound to one, settings or a URL string."""
    if isinstance(db, Engine):
        return db
    if isinstance(db, str | Settings):
        return make_engine(db)
    bind = db.kw.get("bind") if isinstance(db, sessionmaker) else None
    if isinstance(bind, Engine):
        return bind
    raise TypeError(f"cannot get a database engine from {db!r}")
