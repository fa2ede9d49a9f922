"""Request bodies streamed to the storage: never whole in memory, never past the limits.

In: a Starlette `Request`, a target file, the limits (`Settings.max_upload_bytes`,
`Settings.min_free_bytes`). Out: the file (complete, or removed on any error) with its size and
MD5. Content-Length, when given, is checked before anything is read (413); the size is counted
while the data arrives (after gzip decoding, so a gzip bomb stops at the limit); free space is
checked before and every few MiB while writing (507). Writes run in a worker thread.
"""

from __future__ import annotations

import base64
import binascii
import functools
import hashlib
import os
import shutil
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import anyio
from starlette.requests import ClientDisconnect, Request

from db.service_records import StorageFullError, UploadError, UploadTooLargeError

WRITE_CHUNK = 1 << 20  # write in MiB blocks
FREE_CHECK_EVERY = 16 << 20  # re-check the free space after this many bytes


@dataclass(frozen=True)
class Received:
    """A body written to `path`: its size in bytes (decoded) and MD5 (base64, as Content-MD5)."""

    path: Path
    size: int
    md5_b64: str


def check_free_space(folder: Path, *, incoming: int, min_free: int) -> None:
    """Raise `StorageFullError` unless `incoming` more bytes leave `min_free` bytes free."""
    folder.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(folder).free
    if free - incoming < min_free:
        raise StorageFullError(
            f"not enough storage: {free} bytes free, {incoming} more would leave less than the "
            f"{min_free} bytes to keep free"
        )


def content_length(request: Request) -> int | None:
    """The request's Content-Length, or None (refuses a malformed one with 400)."""
    raw = request.headers.get("content-length")
    if raw is None:
        return None
    try:
        n = int(raw)
    except ValueError:
        raise UploadError(f"Content-Length: not a number: {raw!r}") from None
    if n < 0:
        raise UploadError(f"Content-Length: negative: {n}")
    return n


def check_declared_size(request: Request, *, limit: int, min_free: int, folder: Path) -> None:
    """Refuse up front (413 / 507) what the Content-Length announces, when it is given."""
    n = content_length(request)
    if n is not None and n > limit:
        raise UploadTooLargeError(f"the upload ({n} bytes) is larger than the limit of {limit} bytes")
    check_free_space(folder, incoming=n or 0, min_free=min_free)


def md5_header(request: Request) -> str | None:
    """The `Content-MD5` header (RFC 1864: base64 of the 16-byte digest), checked for form."""
    raw = request.headers.get("content-md5")
    if raw is None:
        return None
    try:
        digest = base64.b64decode(raw.strip(), validate=True)
    except (binascii.Error, ValueError):
        raise UploadError(f"Content-MD5: not base64: {raw!r}") from None
    if len(digest) != 16:
        raise UploadError(f"Content-MD5: expected the base64 of 16 bytes, got {len(digest)} bytes")
    return base64.b64encode(digest).decode("ascii")


def _decoder(encoding: str | None) -> zlib._Decompress | None:
    enc = (encoding or "identity").strip().lower()
    if enc in ("", "identity"):
        return None
    if enc in ("gzip", "x-gzip"):
        return zlib.decompressobj(16 + zlib.MAX_WBITS)
    raise UploadError(f"Content-Encoding {encoding!r} is not supported (gzip or none)")


def _pieces(dec: zlib._Decompress | None, chunk: bytes) -> Iterator[bytes]:
    """The decoded pieces of `chunk`, at most `WRITE_CHUNK` bytes each (a gzip bomb is
    inflated step by step, never at once)."""
    if dec is None:
        yield chunk
        return
    yield dec.decompress(chunk, WRITE_CHUNK)
    while dec.unconsumed_tail:
        yield dec.decompress(dec.unconsumed_tail, WRITE_CHUNK)


async def receive_body(
    request: Request,
    target: Path,
    *,
    limit: int,
    min_free: int,
    content_encoding: str | None = None,
    head: Callable[[bytes], None] | None = None,
    head_bytes: int = 64 << 10,
) -> Received:
    """Stream the request body into `target` (created; removed again on any error).

    `limit` bounds the decoded size (413), `min_free` the free space left (507);
    `content_encoding` "gzip" decodes on the fly. `head`, when given, is called once with the
    first `head_bytes` decoded bytes (or all of them if fewer) and may raise to refuse the body
    before the rest is read.
    """
    decode = _decoder(content_encoding)
    target.parent.mkdir(parents=True, exist_ok=True)
    md5 = hashlib.md5(usedforsecurity=False)
    size = 0
    since_check = 0
    buf = bytearray()
    pending_head: bytearray | None = bytearray() if head is not None else None
    f = await anyio.to_thread.run_sync(open, target, "wb")
    try:
        async for chunk in request.stream():
            for data in _pieces(decode, chunk):
                if not data:
                    continue
                size += len(data)
                if size > limit:
                    raise UploadTooLargeError(f"the upload is larger than the limit of {limit} bytes")
                md5.update(data)
                buf += data
                if pending_head is not None:
                    pending_head += data[: head_bytes - len(pending_head)]
                    if len(pending_head) >= head_bytes:
                        head(bytes(pending_head))  # type: ignore[misc]
                        pending_head = None
                if len(buf) >= WRITE_CHUNK:
                    since_check += len(buf)
                    if since_check >= FREE_CHECK_EVERY:
                        since_check = 0
                        await anyio.to_thread.run_sync(
                            functools.partial(
                                check_free_space, target.parent, incoming=len(buf), min_free=min_free
                            )
                        )
                    await anyio.to_thread.run_sync(f.write, bytes(buf))
                    buf.clear()
        if decode is not None and not decode.eof:
            raise UploadError("Content-Encoding gzip: the gzip stream is truncated")
        if pending_head is not None:
            head(bytes(pending_head))  # type: ignore[misc]
        await anyio.to_thread.run_sync(f.write, bytes(buf))
        await anyio.to_thread.run_sync(f.close)
    except zlib.error as exc:
        await _discard(f, target)
        raise UploadError(f"Content-Encoding gzip: the body is not valid gzip ({exc})") from exc
    except (Exception, ClientDisconnect, anyio.get_cancelled_exc_class()):
        await _discard(f, target)
        raise
    return Received(target, size, base64.b64encode(md5.digest()).decode("ascii"))


async def _discard(f: object, target: Path) -> None:
    def close_and_remove() -> None:
        try:
            f.close()  # type: ignore[attr-defined]
        finally:
            target.unlink(missing_ok=True)

    with anyio.CancelScope(shield=True):
        await anyio.to_thread.run_sync(close_and_remove)


def temp_name(folder: Path, suffix: str = "") -> Path:
    """A fresh `.tmp-<random><suffix>` path in `folder` (the sweeper removes stale ones)."""
    return folder / f".tmp-{os.urandom(8).hex()}{suffix}"
