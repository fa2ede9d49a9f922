"""The sequence calibration's cost is bounded whatever the sequence length (issue 18, item 2),
counted without timing: the frames it looks at and loads, the edge searches along projected
wireframe samples and the oriented-gradient scores it computes are the same for a sequence and
one four times as long, and the correction is within its error bound on both."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation import calibration, calibration_delay, common_correction, edge_observations
from workers.pipeline.orientation.calibration import CalibrationOptions, apply_calibration, calibrate_sequence
from workers.pipeline.synth import ErrorOptions, SynthOptions, SynthResult, procedural_block, synthesize

N_DRIVE = 40
#: the functions counted (wrapped anew for every calibration)
SEARCH, SCORE, SAMPLE = edge_observations.edge_search, common_correction.oriented_gradient_score, \
    calibration.sample_frames
OFFSET_M = np.array([2.0, -1.5, 1.0])  # the GNSS offset every prior carries (world, metres)


@pytest.fixture(scope="module")
def drive() -> tuple[SynthResult, list[np.ndarray], RayCaster]:
    """An error-free synthetic drive past a procedural block (seed 1): result, frames, caster."""
    res = synthesize(
        procedural_block(6, seed=1),
        SynthOptions(platform="drive", n_frames=N_DRIVE, seed=1, buildings=3,
                     errors=ErrorOptions(enabled=False)),
    )
    return res, [res.frames.load(i) for i in range(N_DRIVE)], RayCaster(res.mesh)


def there_and_back(k: int) -> int:
    """The drive's frame shown as frame `k` of a sequence driving it there and back again."""
    lap, i = divmod(k, N_DRIVE)
    return i if lap % 2 == 0 else N_DRIVE - 1 - i


@dataclass
class CountingFrames:
    """A `FrameSource` over the drive driven there and back that counts its loads."""

    imgs: list[np.ndarray]
    loads: list[int] = field(default_factory=list)

    def load(self, index: int) -> np.ndarray:
        """Frame `index` `(H, W)` float32."""
        self.loads.append(index)
        return self.imgs[there_and_back(index)]


def calibrate_counted(drive: tuple[SynthResult, list[np.ndarray], RayCaster], n: int,
                      monkeypatch: pytest.MonkeyPatch) -> tuple[dict[str, int], float, float, bool]:
    """Calibrate an `n`-frame sequence (the drive there and back, every prior off by `OFFSET_M`)
    -> (counts of the work done, largest position (m) and rotation (deg) error of the calibrated
    priors against the truth, accepted)."""
    res, imgs, caster = drive
    counts = {"looked": 0, "edge_searches": 0, "edge_samples": 0, "gradient_scores": 0}
    real_search, real_score, real_sample = SEARCH, SCORE, SAMPLE

    def search(feats, uv, *args, **kwargs):  # type: ignore[no-untyped-def]
        counts["edge_searches"] += 1
        counts["edge_samples"] += len(uv)
        return real_search(feats, uv, *args, **kwargs)

    def score(grad, ds, uv, *args, **kwargs):  # type: ignore[no-untyped-def]
        counts["gradient_scores"] += int(np.prod(uv.shape[:-1]))
        return real_score(grad, ds, uv, *args, **kwargs)

    def sample(*args, **kwargs):  # type: ignore[no-untyped-def]
        got = real_sample(*args, **kwargs)
        counts["looked"] += len(got.looked)
        return got

    monkeypatch.setattr(edge_observations, "edge_search", search)
    monkeypatch.setattr(common_correction, "oriented_gradient_score", score)
    monkeypatch.setattr(calibration_delay, "oriented_gradient_score", score)
    monkeypatch.setattr(calibration, "sample_frames", sample)
    truth = [res.truth.poses[there_and_back(k)] for k in range(n)]
    priors = [Pose(p.R_world_from_cam, p.center + OFFSET_M) for p in truth]
    times = [0.1 * k for k in range(n)]
    frames = CountingFrames(imgs)
    cal = calibrate_sequence(res.manifest.camera, caster, list(range(n)), frames, dict(enumerate(priors)),
                             dict(enumerate(times)), res.manifest.accuracy)
    counts["loaded"] = len(set(frames.loads))
    counts["loads"] = len(frames.loads)
    out = apply_calibration(priors, times, cal)
    d = np.array([pose_delta(t, p) for t, p in zip(truth, out, strict=True)])
    pos = float(np.linalg.norm(d[:, 3:], axis=1).max())
    rot = float(np.degrees(np.linalg.norm(d[:, :3], axis=1)).max())
    return counts, pos, rot, cal.accepted


def test_a_four_times_longer_sequence_costs_the_same(drive: tuple[SynthResult, list[np.ndarray], RayCaster],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """120 and 480 frames: as many frames looked at and loaded (each once), oriented-gradient
    scores within 10 % of each other, edge searches within a bound the options set, not the
    length (the Gauss-Newton stages stop when they converge); the GNSS offset is calibrated away
    on both (before: 2.7 m on every frame)."""
    o = CalibrationOptions()
    short, pos_s, rot_s, ok_s = calibrate_counted(drive, 3 * N_DRIVE, monkeypatch)
    long, pos_l, rot_l, ok_l = calibrate_counted(drive, 12 * N_DRIVE, monkeypatch)
    assert ok_s and ok_l
    # the error bound: the per-frame σ of the model (0.3 m, 0.3°) at 2σ, every frame
    for pos, rot in ((pos_s, rot_s), (pos_l, rot_l)):
        assert pos < 0.6 and rot < 0.6, (pos, rot)
    assert short["looked"] == long["looked"] == o.look_frames, (short, long)
    most = o.max_frames + o.start_segments * o.start_frames
    assert short["loaded"] == long["loaded"] <= most, (short, long)
    assert short["loads"] == short["loaded"] and long["loads"] == long["loaded"], (short, long)
    # measured: 8.56 and 8.59 million oriented-gradient scores (the coarse search, the delay's)
    g_short, g_long = short["gradient_scores"], long["gradient_scores"]
    assert abs(g_long - g_short) <= 0.1 * g_short, (short, long)
    # edge searches: per frame and Gauss-Newton iteration of the start (candidates verified, then
    # the fine stage) and of the adjustment (twice, with the delay search between), plus the
    # support tests; none of it counts the sequence's frames
    jo = o.joint
    per_start = (1 + jo.candidates + jo.translation_candidates) * jo.verify_frames * jo.verify_iterations \
        + o.start_frames * (jo.iterations + 3)
    bound = o.start_segments * per_start + 2 * o.max_frames * (o.iterations + 3)
    # (measured: 1,081 and 812, the adjustment ran twice on the shorter one)
    assert short["edge_searches"] <= bound and long["edge_searches"] <= bound, (short, long, bound)
