"""Options of the visibility stage (`texture.visibility`, `texture.occlusion`): the frame border,
depth and distance limits, the grazing limit, and the tolerances of the occlusion test."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class VisibilityOptions:
    """Options of the visibility stage.

    Attributes:
        margin_px: texels projecting closer than this to the frame border are not used.
        min_depth_m: texels closer to the camera than this (along the optical axis) are not used.
        max_distance_m: texels farther than this from the projection centre are not used.
        max_view_angle_deg: largest angle between the surface normal and the ray to the camera
            (the grazing limit). Oblique observations lose out to better ones in the fusion
            (ranked by local resolution, which grows as 1/cos of the angle); a surface seen only
            obliquely (a flat roof from the street) still gets a texture, its mean viewing angle
            in the statistics tells the user (real emissivity falls beyond ~60°).
        max_texel_ratio: an observation whose local resolution (metres on the surface per pixel)
            exceeds this many texel sizes is not used: it resolves nothing at the texel scale
            (inf: no limit).
        occlusion_tolerance_m: rays stop this far short of the texel (its own surface); used by
            `unoccluded` (point-wise test).
        depth_tolerance_m, depth_tolerance_rel: a pixel read for a texel belongs to the texel's
            surface when it sees the texel's plane (its polygon or a coplanar polygon of the same
            building) at the texel's distance within `depth_tolerance_m + depth_tolerance_rel ·
            distance`.
        blur_margin_px: the PSF radius, whole pixels: that must also hold for the pixels this
            far around the 2x2 pixels that bilinear sampling reads: the optics blur a silhouette
            (sky, roof edge, occluder) into its neighbours. The sampling footprint of issue 15 is
            thus the area of the 2x2 pixels grown by this many pixels along each image axis: a
            (2 + 2·margin)² block of whole pixels, tested as a closed area (`pixel_area`). The
            diagonal neighbours belong to it: a separable PSF (a sensor's blur, the synthetic
            renderer's Gaussian) reaches them. Growing by a disc instead (rounded corners, the
            block's four corner regions left out, rays through the corner arcs) let mixed values
            in on the NRW test flight (15 frames): p95 error 1.20 -> 1.27 x the reference's,
            surfaces textured that the reference finds only mixed 9 -> 31.
        buffer_step_px: the occlusion test casts every `buffer_step_px`-th pixel in both
            directions (3: a ninth of the rays); a texel's test then reads the 2x2 cast pixels
            around it, and near a silhouette every pixel of its footprint (`visible`). 3 against
            2: the same textures on the NRW bench drive and flight, a close-range drive past
            Berlin facades 41 against 33 frames/s.
        pixel_area: near a silhouette, the footprint's pixels must see the texel's plane over
            their whole area, tested by rays through their corners as well as their centres (a
            pixel half on a neighbour is a mixed pixel even when its centre is not; a pixel's
            value integrates its area): the footprint's boundary, its outermost pixel corners
            included, is part of it.
        boundary_edges: the samples the rays find clean are then tested exactly against the
            scene's polygon outlines (`footprint.FootprintEdges`): a boundary edge of the texel's
            own polygon, or of a polygon in front of its plane (less than `occlusion_tolerance_m`
            behind it), that crosses or touches the footprint makes it mixed. The rays read every
            1/2 px near a silhouette and every 3rd pixel elsewhere: a polygon corner or a strip
            thinner than that between them went unseen. On the 15-frame NRW test flight (its
            first 40 units), a dense cast (every 1/20 px) finds 128 of the 171 footprints the
            edges reject mixed; the other 43 have an outline within about 0.06 px (the rays hit
            the triangulated mesh, whose border departs from a non-planar polygon's ring by a
            few cm). Observed area per surface 1.014 -> 1.011 x the reference's.
        coplanar_deg, coplanar_m: polygons of one building whose normals differ by less than
            `coplanar_deg` and whose planes are less than `coplanar_m` apart form one plane (a
            facade split into several polygons).
        coplanar_clean: pixels that see such a coplanar polygon count as clean for the
            texel's polygon. False (default, issue 15: the footprint must lie on the texel's
            own polygon): only pixels of the texel's own polygon do; two polygons of one plane
            may differ in temperature (two houses of a row, a repaired patch). On the NRW test
            drive, True textured 4 walls, 1-6 texels each, from pixels mixed with a coplanar
            polygon of the same building.
    """

    margin_px: float = 2.0
    min_depth_m: float = 0.5
    max_distance_m: float = 800.0
    max_view_angle_deg: float = 80.0
    max_texel_ratio: float = 3.0
    occlusion_tolerance_m: float = 0.05
    depth_tolerance_m: float = 0.3
    depth_tolerance_rel: float = 0.02
    blur_margin_px: int = 1
    buffer_step_px: int = 3
    pixel_area: bool = True
    boundary_edges: bool = True
    coplanar_deg: float = 1.0
    coplanar_m: float = 0.05
    coplanar_clean: bool = False
