"""`report.json` `warnings` when refinement was asked for but nothing was oriented (the 300-frame
NRW drive of seed 2 before the calibration's short-stretch start sets: calibration refused, every
sequence block refused, no building textured, and `warnings` empty)."""

from __future__ import annotations

import numpy as np

from workers.job import Calibrated, Oriented, Planned, RunOptions, job_warnings
from workers.pipeline.orientation.calibration import SequenceCalibration

NOWHERE = "the block found the model nowhere (edge support)"


def calibrated(accepted: bool, reason: str = "") -> Calibrated:
    """A calibrate stage's result (no priors needed here)."""
    return Calibrated(SequenceCalibration(theta=np.zeros(10), accepted=accepted, reason=reason), (), None)


def oriented(frames_oriented: int, blocks: int = 4) -> Oriented:
    """An orient stage's report with `blocks` blocks, accepted when frames were oriented."""
    b = [
        {
            "frames": [0, 97],
            "accepted": frames_oriented > 0,
            **({} if frames_oriented else {"reason": NOWHERE}),
        }
        for _ in range(blocks)
    ]
    return Oriented(None, {"run": True, "frames": 300, "frames_oriented": frames_oriented, "blocks": b})


def test_nothing_oriented_with_refinement_on_is_warned_about() -> None:
    """Calibration refused and no block accepted: one warning naming both reasons and what the
    textures come from; none when either stage oriented something or refinement is off."""
    o = RunOptions()
    assert o.refine
    planned = Planned(())
    got = job_warnings(planned, calibrated(False, "no common correction: no frame set"), oriented(0), o)
    assert len(got) == 1, got
    w = got[0]
    assert w.startswith("refinement was asked for but no frame was oriented"), w
    assert "no common correction: no frame set" in w and "none of its 4 blocks" in w and NOWHERE in w, w
    assert "GNSS/INS poses as recorded" in w, w
    # the resolution warning stays first
    assert job_warnings(Planned((), "coarse"), calibrated(False, "x"), oriented(0), o)[0] == "coarse"
    # something oriented: no warning
    assert job_warnings(planned, calibrated(True), oriented(0), o) == []
    assert job_warnings(planned, calibrated(False, "x"), oriented(120), o) == []
    # refinement off, or neither stage run: nothing was expected to be oriented
    assert (
        job_warnings(
            planned,
            Calibrated(None, (), None),
            Oriented(None, {"run": False}),
            RunOptions.build(refine=False),
        )
        == []
    )
    assert job_warnings(planned, Calibrated(None, (), None), Oriented(None, {"run": False}), o) == []
    # the orient stage failed after a refused calibration: warned, with its reason
    failed = Oriented(None, {"run": False, "reason": "failed: ValueError: boom"})
    w = job_warnings(planned, calibrated(False, "too few frames see the model"), failed, o)[0]
    assert "too few frames see the model" in w and "did not run (failed: ValueError: boom)" in w, w
