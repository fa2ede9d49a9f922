"""The options of one texturing job (`RunOptions`): what `citytherm run` and a service job take,
stored with the job as JSON (`to_dict` / `from_dict`). The job's stages are in `workers.job`,
which re-exports `RunOptions`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from workers.pipeline.options import options_from_dict, options_to_dict
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.plan import PlanOptions
from workers.pipeline.units import UnitOptions


@dataclass(frozen=True)
class RunOptions:
    """Options of one texturing job (`citytherm run`, a service job).

    Attributes:
        unit: the building units' options: texel resolution (`unit.texel.resolution_px_per_m`),
            theme, refinement (`unit.refine`, None: keep the GNSS/INS poses) and the texture
            stages. The one home of those values: read them through the properties below.
        plan: planning options.
        calibrate: with refinement, calibrate the sequence (mounting, GNSS offset, time delay)
            before the units, which then refine from the calibrated priors.
        orient: with refinement, orient close-range sequences (drives, terrestrial) in blocks
            (feature tracks, bundle adjustment with the model) before the units, from the
            calibrated priors or the manifest's; the units then refine from those poses.
        orientation: how the orient stage orients: `"edges"` the blocks with model edges and
            planes (`orientation.sequence`), `"sfm"` the sequence's own reconstruction placed on
            the GNSS/INS and coregistered to the facades (`reconstruction`, Hoegner & Stilla's
            method 1), `"both"` the edge path's poses where its blocks confirmed them and the
            reconstruction's for the frames it left unoriented.
        rgb: in the orient stage, first register the TIR block onto the dense cloud of the
            package's RGB camera (`rgb_camera`; Hoegner & Stilla's method 3, `workers.orient_rgb`):
            the sequence orientation then starts from the registered poses (when the ICP is
            accepted); `report.json` `sequence_orientation.rgb`. Off by default (costly).
        buildings: ids of the top-level buildings to texture (None: all the sequence sees).
        workers: processes for the building units in one process (`citytherm run`; 1: in this
            process).
        display: also write the 8-bit colour-mapped `<theme>-display` appearance.
        split_half: after the units, texture every building's even and odd frames separately
            and report how the two halves agree (`workers.split_half`; `report.json`
            `split_half`); the job's outputs stay the same. `citytherm run` only.
    """

    unit: UnitOptions = field(default_factory=UnitOptions)
    plan: PlanOptions = field(default_factory=PlanOptions)
    calibrate: bool = True
    orient: bool = True
    orientation: Literal["edges", "sfm", "both"] = "edges"
    rgb: bool = False
    buildings: tuple[str, ...] | None = None
    workers: int = 1
    display: bool = True
    split_half: bool = False

    def __post_init__(self) -> None:
        if self.orientation not in ("edges", "sfm", "both"):
            raise ValueError(f"orientation {self.orientation!r}: one of edges, sfm, both")

    @classmethod
    def build(
        cls,
        *,
        resolution_px_per_m: float | None = None,
        theme: str | None = None,
        refine: bool | None = None,
        anomalies: bool | None = None,
        **fields: Any,
    ) -> RunOptions:
        """Options from the job's few headline values (as the command line gives them); the
        others keep their defaults or come in `fields`. `refine=True` uses the default
        refinement options, False none; `anomalies=False` skips the thermal analysis."""
        unit: UnitOptions = fields.pop("unit", UnitOptions())
        if anomalies is not None:
            unit = replace(unit, anomalies=replace(unit.anomalies, enabled=bool(anomalies)))
        if resolution_px_per_m is not None:
            unit = replace(unit, texel=replace(unit.texel, resolution_px_per_m=float(resolution_px_per_m)))
        if theme is not None:
            unit = replace(unit, theme=theme)
        if refine is not None:
            unit = replace(unit, refine=(unit.refine or CoregisterOptions()) if refine else None)
        return cls(unit=unit, **fields)

    @property
    def refine(self) -> bool:
        """True when the units refine their poses (and the sequence stages may run)."""
        return self.unit.refine is not None

    @property
    def theme(self) -> str:
        """Appearance theme of the textures."""
        return self.unit.theme

    @property
    def resolution_px_per_m(self) -> float:
        """Texels per metre on every surface."""
        return self.unit.texel.resolution_px_per_m

    def to_dict(self) -> dict[str, Any]:
        """JSON form (`workers.pipeline.options.options_to_dict`)."""
        return options_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> RunOptions:
        """Rebuild from `to_dict`'s form; unknown keys or wrong types raise `OptionsError`."""
        return options_from_dict(cls, data)
