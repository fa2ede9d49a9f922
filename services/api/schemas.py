"""Request and response documents of the API (pydantic): they are the OpenAPI document's schemas.

OGC API - Processes 1.0 documents (landing page, conformance, process list and description,
execute request, statusInfo, job list, results) and citytherm's own (models, sequences).
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from workers.job import RunOptions

_DEFAULTS = RunOptions()


class Link(BaseModel):
    """A web link (OGC API common)."""

    href: str
    rel: str
    type: str | None = None
    title: str | None = None


class LandingPage(BaseModel):
    """`GET /`."""

    title: str
    description: str
    links: list[Link]


class Conformance(BaseModel):
    """`GET /conformance`."""

    conformsTo: list[str]  # noqa: N815 - OGC's name


class ProcessSummary(BaseModel):
    """A process in `GET /processes`."""

    model_config = ConfigDict(extra="allow")

    id: str
    title: str
    description: str
    version: str
    jobControlOptions: list[str]  # noqa: N815
    outputTransmission: list[str]  # noqa: N815
    links: list[Link]


class ProcessList(BaseModel):
    """`GET /processes`."""

    processes: list[ProcessSummary]
    links: list[Link]


class ProcessDescription(ProcessSummary):
    """`GET /processes/texture`: the summary plus `inputs` and `outputs` (id -> description)."""

    inputs: dict[str, dict[str, Any]]
    outputs: dict[str, dict[str, Any]]


class TextureInputs(BaseModel):
    """Inputs of the `texture` process: the options of `citytherm run`."""

    model_config = ConfigDict(extra="forbid")

    model: int = Field(..., ge=1, le=2**62, description="The city model's id (`POST /models`), status ready.")
    sequence: uuid.UUID = Field(..., description="The sequence's id (`POST /sequences`), committed.")
    theme: str = Field(
        _DEFAULTS.theme,
        min_length=1,
        max_length=100,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$",
        description="Appearance theme of the textures.",
    )
    resolution: float = Field(
        _DEFAULTS.resolution_px_per_m, gt=0, le=1000, description="Texels per metre on every surface."
    )
    buildings: list[str] | None = Field(
        None,
        min_length=1,
        max_length=100_000,
        description="Ids (gml:id) of the top-level buildings to texture; default: all the sequence sees.",
    )
    refine: bool = Field(
        True, description="Refine the camera poses against the model (false: keep GNSS/INS)."
    )
    calibrate: bool = Field(
        _DEFAULTS.calibrate,
        description="With refinement: calibrate the sequence (boresight, offsets, delay).",
    )
    orient: bool = Field(
        _DEFAULTS.orient, description="With refinement: orient drives in blocks before the buildings."
    )
    orientation: Literal["edges", "sfm", "both"] = Field(
        _DEFAULTS.orientation,
        description="With the sequence orientation: edges (model edges and planes), sfm (the sequence's "
        "own reconstruction, coregistered to the facades) or both (edges where confirmed, the "
        "reconstruction elsewhere).",
    )
    rgb: bool = Field(
        _DEFAULTS.rgb,
        description="With the sequence orientation: first register the TIR block onto the dense cloud "
        "of the sequence's RGB camera (rgb_camera; method 3, costly).",
    )
    anomalies: bool = Field(
        True, description="Analyse the textures: windows, heat-leak candidates, facade figures."
    )

    def run_options(self) -> RunOptions:
        """The job's `RunOptions` (as `citytherm run` builds them from its options)."""
        return RunOptions.build(
            resolution_px_per_m=self.resolution,
            theme=self.theme,
            refine=self.refine,
            calibrate=self.calibrate,
            orient=self.orient,
            orientation=self.orientation,
            rgb=self.rgb,
            anomalies=self.anomalies,
            buildings=tuple(self.buildings) if self.buildings else None,
        )


class Execute(BaseModel):
    """`POST /processes/texture/execution` (OGC execute request). `outputs` and `response` are
    accepted; the job always runs asynchronously and its results are references."""

    inputs: TextureInputs
    outputs: dict[str, Any] | None = None
    response: Literal["document", "raw"] | None = None


class StatusInfo(BaseModel):
    """OGC statusInfo of a job, plus its `stage`, unit counts by state and its inputs."""

    jobID: str  # noqa: N815
    processID: str  # noqa: N815
    type: Literal["process"] = "process"
    status: Literal["accepted", "running", "successful", "failed", "dismissed"]
    message: str | None = None
    created: datetime | None = None
    started: datetime | None = None
    finished: datetime | None = None
    updated: datetime | None = None
    progress: int = Field(..., ge=0, le=100)
    stage: str
    units: dict[str, int]
    inputs: dict[str, Any]
    links: list[Link]


class JobList(BaseModel):
    """`GET /jobs`."""

    jobs: list[StatusInfo]
    links: list[Link]


class OutputRef(BaseModel):
    """One output of a job's results, by reference."""

    href: str
    type: str
    title: str | None = None


class ModelAccepted(BaseModel):
    """`POST /models`: the upload was taken; the import runs."""

    id: int
    name: str
    status: Literal["importing"]
    bytes: int


class ModelView(BaseModel):
    """A city model (its import, and once ready its CRS, counts, extent and themes)."""

    id: int
    name: str
    status: Literal["importing", "ready", "failed"]
    message: str | None = None
    bytes: int
    progress: float
    created: datetime
    updated: datetime
    crs: str | None = None
    srid: int | None = None
    citygml_version: str | None = None
    buildings: int | None = None
    parts: int | None = None
    surfaces: int | None = None
    themes: dict[str, int] | None = None
    imported: datetime | None = None
    extent: list[float] | None = Field(None, description="minx, miny, minz, maxx, maxy, maxz (model CRS).")
    links: list[Link]


class ModelList(BaseModel):
    """`GET /models`."""

    models: list[ModelView]
    links: list[Link]


class SequenceCreated(BaseModel):
    """`POST /sequences`: an open upload."""

    id: uuid.UUID
    status: Literal["open"]


class PartReceived(BaseModel):
    """`PUT /sequences/{id}/parts/{n}`."""

    id: uuid.UUID
    n: int
    size: int
    md5: str = Field(..., description="Base64 MD5 of the part (as Content-MD5).")
    bytes: int = Field(..., description="The upload's bytes so far.")


class PartInfo(BaseModel):
    """A received part."""

    n: int
    size: int
    md5: str


class SequenceView(BaseModel):
    """A sequence upload and, once committed, its package's frames, CRS and platform."""

    id: uuid.UUID
    status: Literal["open", "committed", "failed"]
    bytes: int
    parts: list[PartInfo]
    message: str | None = None
    created: datetime
    updated: datetime
    frames: int | None = None
    crs: str | None = None
    srid: int | None = None
    platform: str | None = None
    links: list[Link]


class RegisterRequest(BaseModel):
    """`POST /sequences/register`: a package already on the storage."""

    model_config = ConfigDict(extra="forbid")

    path: str = Field(
        ...,
        min_length=1,
        max_length=4096,
        description="Folder, sequence.json or archive; relative to the storage directory or "
        "absolute inside it.",
    )
