"""Orientation: the GNSS/INS poses of a thermal-infrared sequence refined against the city model.

In: the `Camera`, the frames in recording order with their times (seconds) and float32 images in
physical units (`FrameSource`), the GNSS/INS prior camera pose per frame (world = model CRS) with
the manifest's `Accuracy` and `Mounting`, the buildings (`Building`, model CRS) and a `RayCaster`
over them. Out: the sequence calibration (boresight, GNSS offset, lever arm, time delay; the
calibrated priors and the estimated mounting), the sequence orientation (a pose and its
covariance per frame, tie tracks) and per building `{frame: RefinedPose}` with status
`"refined"` or `"prior"`. A run calls them in that order: calibrate once per sequence, orient the
sequence (drives, terrestrial; from the calibrated priors or the manifest's), then refine each
building unit.

Entry points, by stage:
- `calibration`: the systematic pose error of a sequence (`calibrate_sequence`,
  `SequenceCalibration`, `CalibrationOptions`), the calibrated priors (`apply_calibration`) and
  their a-priori σ (`calibrated_accuracy`); `calibration_model`: how θ corrects a frame
  (`design`, `frame_motion`); `mounting`: θ in the manifest's mounting terms
  (`mounting_document`, `calibration_report`, `calibrated_mounting`).
- `sequence`: every frame in overlapping blocks of tracks and bundle adjustment, before the
  building units, calibration accepted or not (`orient_sequence`, `SequenceOrientation`,
  `SequenceOrientationOptions`, `uncalibrated_options`, `SEQUENCE_PLATFORMS`);
  `sequence_acceptance`: which frames of a block are confirmed (`confirm_block`,
  `ConfirmOptions`: edges, planes and tracks, consistency with the priors); `smoothing`: start
  poses from noisy priors (`smooth_poses`).
- `building`: the per-building refinement of a unit's frames (`refine_building`; its options
  `CoregisterOptions` and `calibrated_options` live in `building_options`).
- `block`: a block of frames oriented with tracks and the model (`refine_block`,
  `adjust_block`, `BlockOptions`), and the building's check of the sequence poses
  (`refine_from_sequence`, `UnitSequence`); `block_recheck`: weakly tied frames whose model edges
  contradict the adjusted block, their ties dropped and the block adjusted again
  (`recheck_block`, `RecheckOptions`); `bundle`: the bundle adjustment with tie points,
  model planes, model edges and priors (`bundle_adjust`, `BundleOptions`); `tracks`: feature
  tracks on the model's surfaces (`track_sequence`, `Tracks`, `TrackOptions`).
- `common_correction`: one common correction of a building's or sequence's priors
  (`joint_fit`, `JointOptions`); `oriented_gradient`: its correspondence-free edge score
  (`oriented_gradient_score`).
- `frame_fit`: one frame fitted to a wireframe (`fit_frame`, `FrameFit`; its options
  `FrameFitOptions` in `fit_options`); `coarse`: the edge-distance search of one frame or of all
  frames of a building at once (`coarse_search`, `joint_coarse`, `apply_coarse`); `neighbours`:
  a frame's correction predicted from its neighbours in time (`predict`).
- `edge_observations`: the edge observations every stage shares (`visible_samples`,
  `normal_equations`, `edge_support`, `frame_edges`); `wireframe`: the model side
  (`building_wireframe`, `mesh_wireframe`, `visible_wireframe`); `features`: the image side
  (`extract_features`, `ImageFeatures`).
- `priors`: what every stage assumes a priori (`PriorOptions`: per-frame deviation, null shift;
  `prior_information`, `frame_noise_covariance`).
- `quality`: measures against a synthetic ground truth (`reprojection_rms`, `efficiency`,
  `point_quality`, `match_quality`, `tie_errors`).

Pose corrections are `δ = (ω_cam, dC_world)` (`geometry.pose_increments`). The modules import
each other without a circle (`tests/unit/test_layers.py`).
"""
