"""Alembic migrations of the city model database: the only way the schema is created or changed.

In: a database URL. Out: the schema at a revision. `alembic_config(url)` builds an Alembic
`Config` pointing at this package's folder, so migrations run from an installed package too (no
`alembic.ini` needed; the repository's `alembic.ini` is for the `alembic` command line).
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from db.session import make_engine, sqlalchemy_url

__all__ = ["MIGRATIONS_DIR", "alembic_config", "current_revision", "downgrade", "head_revision", "upgrade"]

MIGRATIONS_DIR = Path(__file__).resolve().parent


def alembic_config(database_url: str) -> Config:
    """Alembic configuration for `database_url` with this package's migration scripts."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.set_main_option("sqlalchemy.url", sqlalchemy_url(database_url).replace("%", "%%"))
    return cfg


def upgrade(database_url: str, revision: str = "head", *, srid: int | None = None) -> None:
    """Upgrade the database to `revision` (default: the newest). `srid` is the EPSG code the
    geometry columns are typed with when revision 0007 runs (default: `CITYTHERM_DATABASE_SRID`,
    else 25832); a database past 0007 keeps its SRID (see `database_srid`)."""
    cfg = alembic_config(database_url)
    if srid is not None:
        cfg.attributes["database_srid"] = int(srid)
    command.upgrade(cfg, revision)


def downgrade(database_url: str, revision: str = "base") -> None:
    """Downgrade the database to `revision` (default: `base`, i.e. drop the whole schema)."""
    command.downgrade(alembic_config(database_url), revision)


def current_revision(database_url: str) -> str | None:
    """The revision the database is at (None for an empty database)."""
    engine = make_engine(database_url)
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    finally:
        engine.dispose()


def head_revision() -> str:
    """The newest revision of the migration scripts."""
    head = ScriptDirectory.from_config(alembic_config("postgresql://localhost/x")).get_current_head()
    assert head is not None
    return head
