"""An independent reference texturer and the comparison of the product against it (issue 15).

- `geometry`: scene polygons, planes and the reference's own texel grids.
- `zbuffer`: the OpenCV camera (`RefCamera`) and a polygon z-buffer (`ZBuffer` -> `IdBuffer`).
- `texturer`: `reference_textures(...) -> {polygon id: RefTexture}` with `ReferenceOptions`;
  `reference_half_textures` the same from the even and the odd half of each building's frames.
- `compare`: synthetic scenes over real LoD2 files, the product run through its shipped path,
  and the figures of both against the truth (shared by `bench/texture.py` and the tests).
- `split_half`: the reference's split-half figures and the product's against them.

Shares no code with the product's texture path (`workers/pipeline/texture`, ray casting, camera
projection, units): it reads only plain numbers from the product's data objects. The one
exception is deliberate and outside the texturing: `split_half` compares the reference's halves
with the product's pure `split_half_agreement`, so that both are judged by one rule.
"""
