"""Safe extraction of sequence package archives (`.zip`, `.tar`, `.tar.gz` / `.tgz`).

In: an archive path, a destination folder, limits on total expanded bytes and member count.
Out: the archive's regular files and folders written below the destination.

Refused (as `PackageError` naming the member): absolute paths, `..` components, backslash or
drive-letter names, symbolic and hard links, devices and FIFOs, more members than allowed, and
more expanded bytes than allowed. Sizes are counted while the data is copied, never trusted
from the archive's headers (a zip bomb lies about them). No `extractall`.
"""

from __future__ import annotations

import lzma
import shutil
import stat
import tarfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import IO

from db.sequence_manifest import PackageError

CHUNK = 1 << 20


def archive_kind(path: Path) -> str | None:
    """`"zip"`, `"tar"` or None, from the content (not only the suffix)."""
    if zipfile.is_zipfile(path):
        return "zip"
    try:
        if tarfile.is_tarfile(path):
            return "tar"
    except OSError:
        return None
    return None


def _member_path(name: str, dest: Path) -> Path | None:
    """Checked destination of archive member `name` (None for the archive root itself)."""
    if not name or "\\" in name or name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise PackageError(name or "<empty member name>", "absolute or non-POSIX path in the archive")
    parts = [p for p in PurePosixPath(name).parts if p != "."]
    if ".." in parts:
        raise PackageError(name, "'..' in an archive member path")
    if not parts:
        return None
    return dest.joinpath(*parts)


class _Budget:
    """Counts members and bytes against the limits."""

    def __init__(self, max_bytes: int, max_members: int) -> None:
        self.max_bytes, self.max_members = max_bytes, max_members
        self.bytes = 0
        self.members = 0

    def member(self, name: str) -> None:
        self.members += 1
        if self.members > self.max_members:
            raise PackageError(name, f"archive has more than {self.max_members} members")

    def copy(self, src: IO[bytes], target: Path, name: str) -> None:
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists():
            raise PackageError(name, "duplicate archive member")
        with open(target, "wb") as out:
            while chunk := src.read(CHUNK):
                self.bytes += len(chunk)
                if self.bytes > self.max_bytes:
                    raise PackageError(name, f"archive expands past the limit of {self.max_bytes} bytes")
                out.write(chunk)


def _extract_zip(path: Path, dest: Path, budget: _Budget) -> None:
    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
        if len(infos) > budget.max_members:
            raise PackageError(path.name, f"archive has {len(infos)} members, more than {budget.max_members}")
        for info in infos:
            budget.member(info.filename)
            target = _member_path(info.filename, dest)
            fmt = stat.S_IFMT(info.external_attr >> 16)  # 0 when the zip tool wrote no file type
            if fmt and fmt not in (stat.S_IFREG, stat.S_IFDIR):
                raise PackageError(info.filename, "links and special files are not allowed in the archive")
            if target is None:
                continue
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            with zf.open(info) as src:
                budget.copy(src, target, info.filename)


def _extract_tar(path: Path, dest: Path, budget: _Budget) -> None:
    with tarfile.open(path, "r:*") as tf:
        for member in tf:  # streaming: works for compressed tars without a random-access index
            budget.member(member.name)
            target = _member_path(member.name, dest)
            if member.issym() or member.islnk():
                raise PackageError(member.name, "links are not allowed in the archive")
            if not (member.isfile() or member.isdir()):
                raise PackageError(member.name, "devices, FIFOs and special files are not allowed")
            if target is None:
                continue
            if member.isdir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            src = tf.extractfile(member)
            if src is None:
                raise PackageError(member.name, "unreadable archive member")
            with src:
                budget.copy(src, target, member.name)


def extract_archive(path: Path, dest: Path, *, max_bytes: int, max_members: int) -> None:
    """Extract archive `path` into the existing folder `dest`, safely (see module doc).

    On refusal the partial extraction in `dest` is removed and `PackageError` raised.
    """
    kind = archive_kind(path)
    if kind is None:
        raise PackageError(path.name, "not a directory, zip or tar archive")
    budget = _Budget(max_bytes, max_members)
    try:
        if kind == "zip":
            _extract_zip(path, dest, budget)
        else:
            _extract_tar(path, dest, budget)
    except PackageError:
        _clear(dest)
        raise
    except (
        zipfile.BadZipFile,
        tarfile.TarError,
        EOFError,
        OSError,
        RuntimeError,
        NotImplementedError,
        zlib.error,
        lzma.LZMAError,
        ValueError,
    ) as exc:  # corrupt data, encrypted or unsupported compression
        _clear(dest)
        raise PackageError(path.name, f"corrupt or unreadable archive: {exc}") from exc


def _clear(dest: Path) -> None:
    for child in dest.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
