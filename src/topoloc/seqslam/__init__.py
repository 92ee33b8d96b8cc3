"""SeqSLAM's image comparison (Milford & Wyeth, ICRA 2012): preprocessing and difference matrix.

The sequence search itself is :mod:`topoloc.sequence` (shared with every
method's ``--sequence``); the recogniser is :class:`topoloc.methods.seq_slam.SeqSLAM`.
"""

from topoloc.seqslam.difference import difference_matrix
from topoloc.seqslam.preprocess import patch_normalize, preprocess_image

__all__ = ["difference_matrix", "patch_normalize", "preprocess_image"]
