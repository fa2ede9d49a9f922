"""Records of the HTTP API (`docs/service.md`): API keys, model imports (CityGML uploads) and
sequence uploads, the storage paths they use, and the removal of abandoned uploads.

In: a `Session` (the caller's unit of work commits; these helpers never commit, except
`remove_abandoned_uploads`, which is a unit of work of its own: see there) and, for paths, the
storage directory (`Settings.storage_dir`). Out: small frozen dataclasses; rows of `api_key`,
`model_import`, `sequence_upload`.

API keys are random tokens shown once; only their SHA-256 (hex) and first 8 characters are
stored. Scopes: `read` (GET), `submit` (uploads, jobs; implies read), `admin` (implies all).
The errors below carry their HTTP meaning (`status_code`) like `db.errors`.
"""

from __future__ import annotations

import hashlib
import secrets
import shutil
import time
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import delete, func, select, text, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from db.api_scopes import API_SCOPES
from db.errors import CityDBError, ModelExistsError, NotFoundError
from db.service_models import ApiKey, ModelImport, SequenceUpload
from db.settings import Settings

__all__ = [
    "AbandonedUploads",
    "ApiKeyInfo",
    "StorageFullError",
    "UploadError",
    "UploadStateError",
    "UploadTooLargeError",
    "authenticate",
    "check_model_name",
    "create_api_key",
    "create_model_import",
    "create_sequence_upload",
    "fail_model_import",
    "get_model_import",
    "get_sequence_upload",
    "grants",
    "hash_key",
    "list_api_keys",
    "mark_upload_committed",
    "model_upload_path",
    "record_part",
    "remove_abandoned_uploads",
    "revoke_api_key",
    "sequence_dir",
    "sequence_parts_dir",
]

KEY_PREFIX_CHARS = 8


class UploadError(CityDBError):
    """An upload that must be refused as sent (bad checksum, missing part, not CityGML...)."""

    status_code = 400


class UploadTooLargeError(CityDBError):
    """An upload larger than `Settings.max_upload_bytes`."""

    status_code = 413


class StorageFullError(CityDBError):
    """The storage would keep less than `Settings.min_free_bytes` free."""

    status_code = 507


class UploadStateError(CityDBError):
    """An upload or import in a state that does not allow the request (e.g. already committed)."""

    status_code = 409


# -- storage paths -------------------------------------------------------------------------------
def model_upload_path(storage_dir: Path, import_id: int) -> Path:
    """`uploads/models/<import id>.gml`: the CityGML upload a worker imports."""
    return Path(storage_dir) / "uploads" / "models" / f"{int(import_id)}.gml"


def sequence_parts_dir(storage_dir: Path, upload_id: uuid.UUID) -> Path:
    """`uploads/sequences/<upload id>/`: the parts (`part-<n>`) of a sequence upload."""
    return Path(storage_dir) / "uploads" / "sequences" / str(upload_id)


def sequence_dir(storage_dir: Path, upload_id: uuid.UUID) -> Path:
    """`sequences/<sequence id>/`: a committed, extracted package (its `sequence.json` inside)."""
    return Path(storage_dir) / "sequences" / str(upload_id)


# -- API keys ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ApiKeyInfo:
    """An API key as listed (never the key itself)."""

    id: int
    name: str
    prefix: str
    scopes: tuple[str, ...]
    created_at: datetime
    revoked_at: datetime | None


def _key_info(row: ApiKey) -> ApiKeyInfo:
    return ApiKeyInfo(row.id, row.name, row.prefix, tuple(row.scopes), row.created_at, row.revoked_at)


def hash_key(key: str) -> str:
    """SHA-256 hex digest of an API key (what the database keeps).

    >>> hash_key("abc")[:12]
    'ba7816bf8f01'
    """
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def grants(scopes: tuple[str, ...] | list[str], needed: str) -> bool:
    """True when `scopes` allow `needed`: admin implies all, submit implies read.

    >>> grants(("submit",), "read"), grants(("read",), "submit"), grants(("admin",), "submit")
    (True, False, True)
    """
    have = set(scopes)
    if "admin" in have:
        return True
    if needed == "read":
        return bool(have & {"read", "submit"})
    return needed in have


def create_api_key(
    session: Session, *, name: str, scopes: list[str] | tuple[str, ...]
) -> tuple[ApiKeyInfo, str]:
    """Insert a new key with `scopes`; returns its record and the key (shown once, never stored)."""
    wanted = tuple(dict.fromkeys(scopes))
    bad = [s for s in wanted if s not in API_SCOPES]
    if bad or not wanted:
        raise ValueError(f"scopes: expected some of {', '.join(API_SCOPES)}, got {', '.join(bad) or 'none'}")
    key = "ct_" + secrets.token_urlsafe(32)
    row = ApiKey(name=name, prefix=key[:KEY_PREFIX_CHARS], key_hash=hash_key(key), scopes=list(wanted))
    session.add(row)
    session.flush()
    session.refresh(row)
    return _key_info(row), key


def list_api_keys(session: Session, *, include_revoked: bool = True) -> list[ApiKeyInfo]:
    """Every key (optionally without the revoked ones), by id."""
    q = select(ApiKey).order_by(ApiKey.id)
    if not include_revoked:
        q = q.where(ApiKey.revoked_at.is_(None))
    return [_key_info(r) for r in session.scalars(q)]


def revoke_api_key(session: Session, *, key_id: int) -> ApiKeyInfo:
    """Revoke a key (kept for the record; revoking twice keeps the first time). Raises
    `NotFoundError`."""
    row = session.get(ApiKey, key_id, with_for_update=True)
    if row is None:
        raise NotFoundError(f"API key {key_id} not found")
    if row.revoked_at is None:
        row.revoked_at = session.execute(text("SELECT now()")).scalar_one()
        session.flush()
    return _key_info(row)


def authenticate(session: Session, *, key: str) -> ApiKeyInfo | None:
    """The unrevoked key whose hash matches `key`, or None."""
    row = session.scalars(
        select(ApiKey).where(ApiKey.key_hash == hash_key(key), ApiKey.revoked_at.is_(None))
    ).first()
    return None if row is None else _key_info(row)


# -- model imports -------------------------------------------------------------------------------
def check_model_name(session: Session, *, name: str) -> None:
    """Raise `ModelExistsError` when an import that did not fail, or a city model, has `name`."""
    taken = session.execute(
        text(
            "SELECT 1 FROM model_import WHERE name = :n AND status <> 'failed' "
            "UNION ALL SELECT 1 FROM city_model WHERE name = :n"
        ),
        {"n": name},
    ).first()
    if taken is not None:
        raise ModelExistsError(f"a city model named {name!r} exists or is being imported")


def create_model_import(session: Session, *, name: str, nbytes: int = 0) -> int:
    """Insert a `model_import` (status `importing`) and return its id (the API's model id).
    Raises `ModelExistsError` when an import that did not fail, or a city model, has the name."""
    check_model_name(session, name=name)
    row = ModelImport(name=name, status="importing", bytes=nbytes, progress=0.0)
    try:
        with session.begin_nested():
            session.add(row)
            session.flush()
    except IntegrityError:
        raise ModelExistsError(f"a city model named {name!r} is being imported") from None
    return int(row.id)


def adopt_models(session: Session) -> int:
    """Give every complete city model that has no `model_import` row (imported with `citytherm
    import` or `run --database`) a `ready` one, so the API lists it and jobs can name it.
    Returns how many were adopted."""
    res = session.execute(
        text(
            "INSERT INTO model_import (name, status, city_model_id, bytes, progress) "
            "SELECT m.name, 'ready', m.id, 0, 1 FROM city_model m WHERE m.state = 'complete' "
            "AND NOT EXISTS (SELECT 1 FROM model_import i WHERE i.city_model_id = m.id "
            "OR (i.name = m.name AND i.status <> 'failed')) ON CONFLICT DO NOTHING"
        )
    )
    return int(res.rowcount or 0)  # type: ignore[attr-defined]


def imports_to_requeue(session: Session, *, older_than_s: float, limit: int = 100) -> list[int]:
    """Model imports still `importing` whose upload is stored and that nobody touched for
    `older_than_s` seconds (their message was lost, or their worker died): locked (`SKIP
    LOCKED`), `updated_at` set to now. The import task skips one that another worker imports."""
    ids = [
        int(r[0])
        for r in session.execute(
            text(
                "SELECT id FROM model_import WHERE status = 'importing' AND upload_path IS NOT NULL "
                "AND updated_at < now() - make_interval(secs => :old) ORDER BY id LIMIT :n "
                "FOR UPDATE SKIP LOCKED"
            ),
            {"old": float(older_than_s), "n": int(limit)},
        ).all()
    ]
    if ids:
        session.execute(text("UPDATE model_import SET updated_at = now() WHERE id = ANY(:i)"), {"i": ids})
    return ids


def get_model_import(session: Session, *, import_id: int, lock: bool = False) -> ModelImport:
    """The `model_import` row (optionally locked `FOR UPDATE`). Raises `NotFoundError`."""
    row = session.get(ModelImport, import_id, with_for_update=lock, populate_existing=lock)
    if row is None:
        raise NotFoundError(f"city model {import_id} not found")
    return row


def set_model_upload(session: Session, *, import_id: int, upload_path: str, nbytes: int) -> None:
    """Record where the import's upload lies and its size."""
    session.execute(
        update(ModelImport)
        .where(ModelImport.id == import_id)
        .values(upload_path=upload_path, bytes=nbytes, updated_at=text("now()"))
    )


def fail_model_import(session: Session, *, import_id: int, message: str) -> None:
    """Mark an import `failed` with `message` (its name becomes free again)."""
    session.execute(
        update(ModelImport)
        .where(ModelImport.id == import_id)
        .values(status="failed", message=message, updated_at=text("now()"))
    )


def delete_model_import(session: Session, *, import_id: int) -> None:
    """Remove an import's row (its city model, if any, is deleted by `db.city_models`)."""
    session.execute(delete(ModelImport).where(ModelImport.id == import_id))


# -- sequence uploads ----------------------------------------------------------------------------
def create_sequence_upload(
    session: Session,
    *,
    status: str = "open",
    sequence_id: int | None = None,
    upload_id: uuid.UUID | None = None,
) -> uuid.UUID:
    """Insert a `sequence_upload` (status `open`, or `committed` with `sequence_id` for a
    package registered in place); returns its id (the API's sequence id)."""
    uid = upload_id or uuid.uuid4()
    session.add(SequenceUpload(id=uid, status=status, parts={}, bytes=0, sequence_id=sequence_id))
    session.flush()
    return uid


def get_sequence_upload(session: Session, *, upload_id: uuid.UUID, lock: bool = False) -> SequenceUpload:
    """The `sequence_upload` row (optionally locked `FOR UPDATE`). Raises `NotFoundError`."""
    row = session.get(SequenceUpload, upload_id, with_for_update=lock, populate_existing=lock)
    if row is None:
        raise NotFoundError(f"sequence {upload_id} not found")
    return row


def record_part(session: Session, *, upload_id: uuid.UUID, n: int, size: int, md5: str) -> SequenceUpload:
    """Record part `n` (replacing an earlier one of that number) on the locked, open upload;
    `bytes` becomes the sum of the parts. Raises `UploadStateError` once committed."""
    row = get_sequence_upload(session, upload_id=upload_id, lock=True)
    if row.status != "open":
        raise UploadStateError(f"sequence {upload_id} is {row.status}: its parts cannot change")
    parts = dict(row.parts or {})
    parts[str(int(n))] = {"size": int(size), "md5": md5}
    row.parts = parts
    row.bytes = sum(int(p["size"]) for p in parts.values())
    row.updated_at = session.execute(text("SELECT now()")).scalar_one()
    session.flush()
    return row


def mark_upload_committed(session: Session, *, upload_id: uuid.UUID, sequence_id: int) -> None:
    """The upload is committed as sequence `sequence_id` (its message cleared)."""
    session.execute(
        update(SequenceUpload)
        .where(SequenceUpload.id == upload_id)
        .values(status="committed", sequence_id=sequence_id, message=None, updated_at=text("now()"))
    )


def note_upload_problem(session: Session, *, upload_id: uuid.UUID, message: str) -> None:
    """Keep the last commit refusal on an open upload (it stays open: parts can be sent again)."""
    session.execute(
        update(SequenceUpload)
        .where(SequenceUpload.id == upload_id)
        .values(message=message[:2000], updated_at=text("now()"))
    )


# -- abandoned uploads ---------------------------------------------------------------------------
@dataclass(frozen=True)
class AbandonedUploads:
    """What `remove_abandoned_uploads` removed."""

    sequence_uploads: tuple[str, ...]
    stray_paths: tuple[str, ...]


def _older(path: Path, cutoff: float) -> bool:
    try:
        return path.stat().st_mtime < cutoff
    except OSError:
        return False


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def remove_abandoned_uploads(
    session: Session, settings: Settings, older_than_s: float | None = None
) -> AbandonedUploads:
    """Remove uploads nobody finished: called by the workers' sweeper.

    - open sequence uploads idle (no part, no commit) longer than `older_than_s` (default
      `settings.upload_ttl_s`): marked `failed` ("abandoned") and their parts removed;
    - files under `uploads/` and `sequences/` older than that which no record owns: parts of
      uploads that are no longer open, CityGML uploads of imports that are not `importing`,
      temporary files of interrupted requests (`.tmp-*`).

    A unit of work of its own: the rows are committed before any file is removed, so a failure
    leaves files without rows (removed next time), never rows without their files.
    """
    ttl = settings.upload_ttl_s if older_than_s is None else float(older_than_s)
    storage = Path(settings.storage_dir)
    ids = [
        str(u)
        for u in session.scalars(
            update(SequenceUpload)
            .where(
                SequenceUpload.status == "open",
                SequenceUpload.updated_at < func.now() - timedelta(seconds=ttl),
            )
            .values(status="failed", message="abandoned: no part or commit in time", updated_at=func.now())
            .returning(SequenceUpload.id)
            .execution_options(synchronize_session=False)
        )
    ]
    session.commit()
    for uid in ids:
        shutil.rmtree(sequence_parts_dir(storage, uuid.UUID(uid)), ignore_errors=True)
    cutoff = time.time() - ttl
    open_uploads = {
        str(u) for u in session.scalars(select(SequenceUpload.id).where(SequenceUpload.status == "open"))
    }
    importing = {
        str(i) for i in session.scalars(select(ModelImport.id).where(ModelImport.status == "importing"))
    }
    committed = {
        str(u) for u in session.scalars(select(SequenceUpload.id).where(SequenceUpload.status == "committed"))
    }
    session.commit()
    stray: list[str] = []
    candidates: list[tuple[Path, bool]] = []
    parts_root = storage / "uploads" / "sequences"
    if parts_root.is_dir():
        candidates += [(p, p.name not in open_uploads) for p in parts_root.iterdir()]
    models_root = storage / "uploads" / "models"
    if models_root.is_dir():
        candidates += [
            (p, p.name.startswith(".tmp-") or p.stem not in importing) for p in models_root.iterdir()
        ]
    seq_root = storage / "sequences"
    if seq_root.is_dir():
        candidates += [(p, p.name.startswith(".tmp-")) for p in seq_root.iterdir() if p.name not in committed]
    for path, unowned in candidates:
        if unowned and _older(path, cutoff):
            _remove(path)
            stray.append(str(path))
    return AbandonedUploads(tuple(ids), tuple(stray))


def upload_summary(row: SequenceUpload) -> dict[str, Any]:
    """The upload's own fields as the API shows them (parts sorted by number)."""
    parts = sorted(((int(k), v) for k, v in (row.parts or {}).items()), key=lambda kv: kv[0])
    return {
        "id": str(row.id),
        "status": row.status,
        "bytes": int(row.bytes or 0),
        "parts": [{"n": n, "size": int(v["size"]), "md5": v["md5"]} for n, v in parts],
        "message": row.message,
        "created": row.created_at,
        "updated": row.updated_at,
    }
