"""ORM classes of the HTTP service's own records (`db.service_records`): API keys, model imports
started over HTTP, chunked sequence uploads. On the one `db.models.Base` metadata: importing this
module registers their tables (the Alembic environment and the schema test do).
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from sqlalchemy import (
    BigInteger,
    CheckConstraint,
    DateTime,
    Double,
    ForeignKey,
    Index,
    Integer,
    Text,
    Uuid,
    func,
    text,
)
from sqlalchemy.dialects.postgresql import ARRAY, JSONB
from sqlalchemy.orm import Mapped, mapped_column

from db.models import Base


class ApiKey(Base):
    """A bearer API key of the HTTP API: only its SHA-256 is stored (and its first characters,
    to tell keys apart in lists)."""

    __tablename__ = "api_key"
    __table_args__ = (
        CheckConstraint("scopes <@ ARRAY['read', 'submit', 'admin']::text[]", name="ck_api_key_scopes"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(Text)
    prefix: Mapped[str] = mapped_column(Text)
    key_hash: Mapped[str] = mapped_column(Text, unique=True)
    scopes: Mapped[list[str]] = mapped_column(ARRAY(Text))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


class ModelImport(Base):
    """A CityGML upload of the HTTP API and its import by a worker; its id is the API's model id.
    `city_model_id` is set once the import is complete (status `ready`)."""

    __tablename__ = "model_import"
    __table_args__ = (
        CheckConstraint("status IN ('importing', 'ready', 'failed')", name="ck_model_import_status"),
        Index(
            "uq_model_import_name_active", "name", unique=True, postgresql_where=text("status <> 'failed'")
        ),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    name: Mapped[str] = mapped_column(Text)
    status: Mapped[str] = mapped_column(Text)
    message: Mapped[str | None] = mapped_column(Text)
    upload_path: Mapped[str | None] = mapped_column(Text)
    city_model_id: Mapped[int | None] = mapped_column(ForeignKey("city_model.id", ondelete="SET NULL"))
    bytes: Mapped[int] = mapped_column(BigInteger, server_default="0")
    progress: Mapped[float] = mapped_column(Double, server_default="0")
    #: deliveries of its import task (bounded).
    attempts: Mapped[int] = mapped_column(Integer, server_default="0")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class SequenceUpload(Base):
    """A resumable, chunked sequence upload of the HTTP API; its id is the API's sequence id.
    `parts` maps part number -> {size, md5}; `sequence_id` is set once committed."""

    __tablename__ = "sequence_upload"
    __table_args__ = (
        CheckConstraint("status IN ('open', 'committed', 'failed')", name="ck_sequence_upload_status"),
    )

    id: Mapped[uuid.UUID] = mapped_column(Uuid, primary_key=True, default=uuid.uuid4)
    status: Mapped[str] = mapped_column(Text)
    parts: Mapped[dict[str, Any]] = mapped_column(JSONB, server_default=text("'{}'::jsonb"))
    bytes: Mapped[int] = mapped_column(BigInteger, server_default="0")
    message: Mapped[str | None] = mapped_column(Text)
    sequence_id: Mapped[int | None] = mapped_column(ForeignKey("sequence.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
