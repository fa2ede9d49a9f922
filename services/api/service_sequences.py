"""Sequence packages over HTTP: resumable chunked uploads (parts 1..N of one archive), their
commit (assemble, extract safely, validate, register) and packages registered by path.

In: requests, a session, the settings. Out: JSON-ready dicts. The API's sequence id is the
`sequence_upload` id (a uuid); once committed the upload points at its `sequence` row.

Parts are streamed to `uploads/sequences/<id>/.tmp-*` and renamed to `part-<n>` once complete
and checked (size limit, `Content-MD5`), so a part is either the whole old one or the whole new
one. A commit assembles the parts in order into one archive (`.zip`, `.tar`, `.tar.gz`: told by
its first bytes), extracts it with `db.sequence_archive` into `sequences/.tmp-*`, reads it with
the package reader (every frame checked), renames the package folder to `sequences/<id>/` and
registers it (`db.sequences.register_sequence`) in one transaction; on any refusal the temporary
folders are removed and the upload stays open (its `message` says why).
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path
from typing import Any

from sqlalchemy import text
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from db.errors import NotFoundError
from db.sequence_archive import archive_kind, extract_archive
from db.sequence_manifest import PackageError
from db.sequence_package import MANIFEST, SequencePackage, find_root, open_package
from db.sequences import register_sequence
from db.service_records import (
    UploadError,
    UploadStateError,
    UploadTooLargeError,
    create_sequence_upload,
    get_sequence_upload,
    mark_upload_committed,
    note_upload_problem,
    record_part,
    sequence_dir,
    sequence_parts_dir,
    upload_summary,
)
from db.settings import Settings
from services.api.uploads import check_declared_size, check_free_space, md5_header, receive_body, temp_name
from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_epsg

MAX_PARTS = 10_000


def part_path(settings: Settings, upload_id: uuid.UUID, n: int) -> Path:
    """`uploads/sequences/<id>/part-<n>`."""
    return sequence_parts_dir(settings.storage_dir, upload_id) / f"part-{int(n)}"


def new_upload(session: Session) -> dict[str, Any]:
    """Open a sequence upload; returns `{"id": <uuid>, "status": "open"}`."""
    uid = create_sequence_upload(session)
    session.commit()
    return {"id": str(uid), "status": "open"}


def _room_for_part(session: Session, upload_id: uuid.UUID, n: int, max_bytes: int) -> int:
    """Bytes part `n` may have: the limit less the upload's other parts (409 unless open)."""
    row = get_sequence_upload(session, upload_id=upload_id)
    status, parts = row.status, dict(row.parts or {})
    session.rollback()
    if status != "open":
        raise UploadStateError(f"sequence {upload_id} is {status}: its parts cannot change")
    others = sum(int(p["size"]) for k, p in parts.items() if k != str(n))
    if others >= max_bytes:
        raise UploadTooLargeError(f"sequence {upload_id} has reached the limit of {max_bytes} bytes")
    return max_bytes - others


def _keep_part(
    session: Session, settings: Settings, *, upload_id: uuid.UUID, n: int, tmp: Path, size: int, md5: str
) -> dict[str, Any]:
    """Record the part and move it into place, one unit of work (the temporary file removed on
    any error)."""
    try:
        row = record_part(session, upload_id=upload_id, n=n, size=size, md5=md5)
        if row.bytes > settings.max_upload_bytes:
            raise UploadTooLargeError(
                f"sequence {upload_id}: {row.bytes} bytes with this part, more than the limit of "
                f"{settings.max_upload_bytes} bytes"
            )
        tmp.replace(part_path(settings, upload_id, n))
        session.commit()
    except BaseException:
        session.rollback()
        tmp.unlink(missing_ok=True)
        raise
    return {"id": str(upload_id), "n": n, "size": size, "md5": md5, "bytes": int(row.bytes)}


async def accept_part(
    request: Request, session: Session, settings: Settings, *, upload_id: uuid.UUID, n: int
) -> dict[str, Any]:
    """Stream part `n` of an open upload to storage (replacing an earlier part `n`), checking
    its `Content-MD5` (400 on mismatch) and the upload's size limit (413) and free space (507)."""
    expected_md5 = md5_header(request)
    room = await run_in_threadpool(_room_for_part, session, upload_id, n, settings.max_upload_bytes)
    folder = sequence_parts_dir(settings.storage_dir, upload_id)
    check_declared_size(request, limit=room, min_free=settings.min_free_bytes, folder=folder)
    received = await receive_body(request, temp_name(folder), limit=room, min_free=settings.min_free_bytes)
    if expected_md5 is not None and expected_md5 != received.md5_b64:
        received.path.unlink(missing_ok=True)
        raise UploadError(
            f"part {n}: Content-MD5 mismatch: the header says {expected_md5}, the {received.size} bytes "
            f"received have {received.md5_b64}; send the part again"
        )
    return await run_in_threadpool(
        lambda: _keep_part(
            session,
            settings,
            upload_id=upload_id,
            n=n,
            tmp=received.path,
            size=received.size,
            md5=received.md5_b64,
        )
    )


def _ordered_parts(settings: Settings, upload_id: uuid.UUID, parts: dict[str, Any]) -> list[Path]:
    """The part files 1..N in order; 400 naming the first missing part or one whose file is not
    as recorded."""
    if not parts:
        raise UploadError(f"sequence {upload_id}: no parts uploaded (PUT /sequences/{upload_id}/parts/1 ...)")
    numbers = sorted(int(k) for k in parts)
    missing = [k for k in range(1, numbers[-1] + 1) if str(k) not in parts]
    if missing:
        raise UploadError(
            f"sequence {upload_id}: part {missing[0]} is missing (parts uploaded: "
            f"{', '.join(map(str, numbers[:20]))}{' ...' if len(numbers) > 20 else ''}); send it, then commit"
        )
    paths = []
    for k in numbers:
        p = part_path(settings, upload_id, k)
        if not p.is_file() or p.stat().st_size != int(parts[str(k)]["size"]):
            raise UploadError(
                f"sequence {upload_id}: part {k} is not on the storage as recorded; send it again"
            )
        paths.append(p)
    return paths


def install_archive(settings: Settings, archive: Path, upload_id: uuid.UUID) -> tuple[SequencePackage, Path]:
    """Extract and read `archive` into `sequences/<upload_id>/` (replacing what an interrupted
    commit left there). Returns the opened package (manifest read, every frame checked) and the
    folder. On refusal nothing is left and `PackageError` names the field or file."""
    if archive_kind(archive) is None:
        raise PackageError("archive", "not a .zip, .tar or .tar.gz archive (by its content)")
    seq_root = Path(settings.storage_dir) / "sequences"
    tmp = temp_name(seq_root)
    tmp.mkdir(parents=True)
    final = sequence_dir(settings.storage_dir, upload_id)
    try:
        extract_archive(
            archive, tmp, max_bytes=settings.max_package_bytes, max_members=settings.max_package_members
        )
        root = find_root(tmp)
        if final.exists():
            shutil.rmtree(final)
        root.replace(final)
        package = open_package(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(final, ignore_errors=True)
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    return package, final


def _register(session: Session, package: SequencePackage, folder: Path, name: str) -> int:
    manifest_json = json.loads((package.root / MANIFEST).read_text(encoding="utf-8"))
    crs = package.manifest.crs
    try:
        srid = 0 if crs.strip().lower() == "model" else int(horizontal_epsg(crs) or 0)
    except UnknownCRSError as exc:
        raise PackageError("crs", str(exc)) from exc
    return register_sequence(
        session,
        name=name,
        manifest=package.manifest,
        manifest_json=manifest_json,
        storage_location=str(folder.resolve()),
        srid=srid,
    )


def commit_upload(session: Session, settings: Settings, *, upload_id: uuid.UUID, base: str) -> dict[str, Any]:
    """Assemble, extract, validate and register an upload (see the module doc); committing a
    committed upload again returns it. Returns the sequence view."""
    row = get_sequence_upload(session, upload_id=upload_id, lock=True)
    if row.status == "committed":
        session.rollback()
        return sequence_view(session, upload_id=upload_id, base=base)
    if row.status != "open":
        raise UploadStateError(
            f"sequence {upload_id} is {row.status}: {row.message or 'it cannot be committed'}"
        )
    paths = _ordered_parts(settings, upload_id, dict(row.parts or {}))
    total = int(row.bytes or 0)
    seq_root = Path(settings.storage_dir) / "sequences"
    check_free_space(seq_root, incoming=2 * total, min_free=settings.min_free_bytes)
    archive = temp_name(seq_root, ".archive")
    final: Path | None = None
    try:
        with open(archive, "wb") as out:
            for p in paths:
                with open(p, "rb") as src:
                    shutil.copyfileobj(src, out, 1 << 20)
        package, final = install_archive(settings, archive, upload_id)
        with package:
            sid = _register(session, package, final, str(upload_id))
        mark_upload_committed(session, upload_id=upload_id, sequence_id=sid)
        session.commit()
    except (PackageError, UploadError) as exc:
        session.rollback()
        if final is not None:
            shutil.rmtree(final, ignore_errors=True)
        note_upload_problem(session, upload_id=upload_id, message=str(exc))
        session.commit()
        raise
    except BaseException:
        session.rollback()
        if final is not None:
            shutil.rmtree(final, ignore_errors=True)
        raise
    finally:
        archive.unlink(missing_ok=True)
    shutil.rmtree(sequence_parts_dir(settings.storage_dir, upload_id), ignore_errors=True)
    return sequence_view(session, upload_id=upload_id, base=base)


def register_path(session: Session, settings: Settings, *, path: str, base: str) -> dict[str, Any]:
    """Register a package already on the storage (a folder, its `sequence.json`, or an archive,
    given relative to the storage directory or absolute inside it). A folder is registered where
    it lies; an archive is extracted into `sequences/<id>/`. Returns the sequence view."""
    storage = Path(settings.storage_dir).resolve()
    p = Path(path)
    p = (p if p.is_absolute() else storage / p).resolve()
    if not p.is_relative_to(storage):
        raise PackageError("path", "must name a package inside the storage directory")
    if p.is_relative_to(storage / "uploads") or any(part.startswith(".tmp") for part in p.parts):
        # uploads and temporary folders are removed by the sweeper: a package there would vanish
        raise PackageError("path", "must not lie in uploads/ or a temporary folder of the storage")
    if not p.exists():
        raise PackageError("path", f"no package at {path!r} in the storage directory")
    uid = uuid.uuid4()
    if p.is_file() and p.name != MANIFEST:
        package, folder = install_archive(settings, p, uid)
    else:
        package = open_package(p)
        folder = package.root
    try:
        with package:
            sid = _register(session, package, folder, str(uid))
        create_sequence_upload(session, status="committed", sequence_id=sid, upload_id=uid)
        session.commit()
    except BaseException:
        session.rollback()
        if folder == sequence_dir(settings.storage_dir, uid):
            shutil.rmtree(folder, ignore_errors=True)
        raise
    return sequence_view(session, upload_id=uid, base=base)


def sequence_view(session: Session, *, upload_id: uuid.UUID, base: str) -> dict[str, Any]:
    """The upload (status, parts, bytes, message) and, once committed, its sequence: frames, CRS
    (the manifest's `crs` and its EPSG code `srid`, 0 for `model`), platform."""
    row = get_sequence_upload(session, upload_id=upload_id)
    out = upload_summary(row)
    out["links"] = [{"href": f"{base}/sequences/{upload_id}", "rel": "self", "type": "application/json"}]
    if row.sequence_id is not None:
        s = (
            session.execute(
                text(
                    "SELECT frame_count, srs_name, srid, manifest->>'platform' AS platform, created_at "
                    "FROM sequence WHERE id = :s"
                ),
                {"s": row.sequence_id},
            )
            .mappings()
            .first()
        )
        if s is None:
            raise NotFoundError(f"sequence {upload_id}: its package was deleted")
        out.update(
            frames=int(s["frame_count"]), crs=s["srs_name"], srid=int(s["srid"]), platform=s["platform"]
        )
    session.rollback()
    return out
