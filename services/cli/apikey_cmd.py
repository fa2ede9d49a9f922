"""`citytherm apikey create|list|revoke`: the HTTP API's bearer keys.

- `citytherm apikey create --scope read --scope submit [--name N]` makes a key and prints it
  alone on its last line (shown once: only its SHA-256 is stored).
- `citytherm apikey list [--json]` lists the keys: id, name, first characters, scopes, created,
  revoked.
- `citytherm apikey revoke ID` revokes a key (kept for the record).

Scopes: `read` (GET), `submit` (uploads and jobs; implies read), `admin` (implies all: deleting
models, registering packages by path). The database is `CITYTHERM_DATABASE_URL` unless
`--database-url` is given.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.table import Table

from db.api_scopes import API_SCOPES
from db.settings import get_settings
from services.cli.db_cmd import DbUrl
from services.cli.results_cmd import database_error

if TYPE_CHECKING:  # the ORM is loaded when a command runs, not for every `citytherm` start
    from sqlalchemy.orm import Session

apikey_app = typer.Typer(help="API keys of the HTTP API (bearer tokens with scopes).", no_args_is_help=True)


def _session(database_url: str | None) -> Session:
    from sqlalchemy.orm import Session

    from db.session import make_engine

    return Session(make_engine(database_url or get_settings().database_url))


@apikey_app.command("create")
def create_cmd(
    scope: list[str] = typer.Option(..., "--scope", help=f"Scope: {', '.join(API_SCOPES)} (repeatable)."),
    name: str = typer.Option("", "--name", help="A name to tell the key apart in lists."),
    database_url: str | None = DbUrl,
) -> None:
    """Create an API key; the key is printed alone on the last line (and never again)."""
    console = Console()
    bad = [s for s in scope if s not in API_SCOPES]
    if bad:
        console.print(f"[red]error:[/] --scope {bad[0]!r}: expected one of {', '.join(API_SCOPES)}")
        raise typer.Exit(code=2)
    from sqlalchemy.exc import SQLAlchemyError

    from db.service_records import create_api_key

    try:
        with _session(database_url) as session:
            info, key = create_api_key(session, name=name or "key", scopes=scope)
            session.commit()
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/] {database_error(exc)}")
        raise typer.Exit(code=1) from exc
    console.print(f"API key {info.id} ({info.name}, scopes {', '.join(info.scopes)}); it is shown only now:")
    print(key)


@apikey_app.command("list")
def list_cmd(
    as_json: bool = typer.Option(False, "--json", help="JSON for scripts."), database_url: str | None = DbUrl
) -> None:
    """List the API keys (never the keys themselves: their first characters)."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.service_records import list_api_keys

    console = Console()
    try:
        with _session(database_url) as session:
            keys = list_api_keys(session)
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/] {database_error(exc)}")
        raise typer.Exit(code=1) from exc
    if as_json:
        rows = [
            {
                "id": k.id,
                "name": k.name,
                "prefix": k.prefix,
                "scopes": list(k.scopes),
                "created": k.created_at.isoformat(),
                "revoked": k.revoked_at.isoformat() if k.revoked_at else None,
            }
            for k in keys
        ]
        print(json.dumps(rows, indent=1))
        return
    table = Table("id", "name", "key", "scopes", "created", "revoked")
    for k in keys:
        table.add_row(
            str(k.id),
            k.name,
            f"{k.prefix}…",
            ", ".join(k.scopes),
            f"{k.created_at:%Y-%m-%d %H:%M}",
            f"{k.revoked_at:%Y-%m-%d %H:%M}" if k.revoked_at else "",
        )
    console.print(table)


@apikey_app.command("revoke")
def revoke_cmd(key_id: int = typer.Argument(..., help="The key's id (`citytherm apikey list`)."),
               database_url: str | None = DbUrl) -> None:  # fmt: skip
    """Revoke an API key: requests with it get 401 from then on."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.errors import NotFoundError
    from db.service_records import revoke_api_key

    console = Console()
    try:
        with _session(database_url) as session:
            info = revoke_api_key(session, key_id=key_id)
            session.commit()
    except NotFoundError as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(code=1) from exc
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/] {database_error(exc)}")
        raise typer.Exit(code=1) from exc
    console.print(f"API key {info.id} ({info.name}, {info.prefix}…) revoked")


def register(root: typer.Typer) -> None:
    """Add the `apikey` command group to the root app."""
    root.add_typer(apikey_app, name="apikey")
