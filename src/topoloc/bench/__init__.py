"""Speed and scale experiments on synthetic or real data (``topoloc bench``, ``benchmarks/``).

Every helper the benchmark scripts and the ``topoloc bench`` commands share lives
here, above the methods (it may import any layer below the CLI):

* :mod:`~topoloc.bench.coocmap_speed` -- a synthetic Cooc-Map of the paper's size;
* :mod:`~topoloc.bench.fabmap_speed` -- FAB-MAP 2.0 index, bail-out and Chow-Liu timings;
* :mod:`~topoloc.bench.landmark_density` -- map density against frame rate (landmarks, voting), and
  the densest map of each within a frame-rate budget on real data;
* :mod:`~topoloc.bench.quantisation` -- vocabulary quantisation speed and agreement, k-means convergence.
"""
