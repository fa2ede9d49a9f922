"""Reconstruction-based orientation of TIR sequences (Hoegner & Stilla, method 1) with pycolmap:
`orient_reconstruction` (tracks → triangulation + bundle adjustment → similarity onto the
GNSS/INS → facade coregistration) and `combine` (model edges where confirmed, reconstruction
elsewhere). Modules `dense*`, `icp*`, `rgb*` hold method 3.
"""

from workers.pipeline.reconstruction.combine import combine, to_sequence, with_reconstruction
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.orient import ReconstructionOrientation, orient_reconstruction

__all__ = [
    "ReconstructionOptions",
    "ReconstructionOrientation",
    "combine",
    "orient_reconstruction",
    "to_sequence",
    "with_reconstruction",
]
