"""topoloc: appearance-based localisation and loop closure.

Conventions used everywhere in the package
------------------------------------------
Every recogniser produces a similarity matrix ``S`` of shape
``(n_map_places, n_queries)``: row ``i`` is the map's ``i``-th place id in
ascending order, column ``j`` is the ``j``-th query image in traverse order, and
higher values mean "more similar".  Ground truth comes as two boolean matrices
``GThard`` and ``GTsoft`` of the same shape (see :mod:`topoloc.datasets.groundtruth`).
"""

from topoloc.errors import TopolocError

__version__ = "0.1.0"
__all__ = ["TopolocError", "__version__"]
