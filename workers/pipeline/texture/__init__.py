"""Texture: thermal textures of every visible surface, fused over the frames, packed in atlases.

In: the building's polygons (model CRS), the camera, a pose per frame, float32 frames in physical
units (`FrameSource`), a ray caster over the building and its occluders. Out: per polygon a
`SurfaceTexture` on its `TexelGrid` (value, best resolution, view angle, frame per texel) and
16-bit atlas tiles with CityGML texture coordinates.

Modules and their entry points:
- `texel`: the texel grid laid on a planar polygon (`texel_grid`, `TexelOptions`).
- `visibility`: which buildings and texels a frame sees (`boxes_in_frustum`, `project_texels`,
  `buried_texels`; re-exports `OcclusionScene`).
- `occlusion`: the clean-pixel test of a frame's texel samples by ray casting (`OcclusionScene`).
- `frame_pass`: a frame over all surfaces of a unit at once (`UnitTexels`, `observe`).
- `fusion`: sampling one frame onto the grids and fusing it in (`texture_frame`,
  `SurfaceTexture`, `FusionOptions`).
- `alignment`: sub-texel alignment of a partial texture by correlation (`align_partial`).
- `atlas`: packing a building's textures into tiles with texture coordinates (`build_atlas`).
- `quality`: texture error against a known temperature field (synthetic truth: `surface_errors`,
  `summarize`).
"""
