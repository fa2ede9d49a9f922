"""Geometry: the domain types and coordinate frames every other stage builds on.

What goes in and out: numpy arrays in the model CRS (metres, projected, z up) and small frozen
dataclasses; no file or database I/O. Frame conventions are those of `docs/sequence-format.md`
(camera x right, y down, z forward; `Pose.R_world_from_cam`, projection centre `C`).

Modules and their entry points:
- `camera`: `Camera` (OpenCV model), `project((N,3)) -> (N,2)`, `bearing((N,2)) -> (N,3)`.
- `pose`: `Pose` (exterior orientation, world from camera).
- `pose_increments`: rotation vectors (`so3_exp`, `so3_log`), pose corrections
  (`pose_delta`, `apply_delta`), step bounds and the projection Jacobian (`project_jacobian`).
- `georef`: direct georeferencing, GNSS/INS solution + mounting -> camera poses (`prior_poses`).
- `crs`: CRS names as written in CityGML and manifests -> pyproj (`resolve_crs`, `horizontal_epsg`);
  `transform`: model coordinates into another CRS, heights kept (`CrsTransform`, `transform_building`).
- `polygons`: plane fit, local surface frames, triangulation (`fit_plane`, `triangulate`).
- `raycast`: the triangulated city model and ray casting through it (`build_scene_mesh`, `RayCaster`).
- `citymodel`: the city model's domain types (`Building`, `Polygon`, `Appearance`, ...).
- `manifest`: the sequence package's domain types (`SequenceManifest`, `Mounting`, `Accuracy`,
  `Radiometry`, the `FrameSource` protocol).
"""
