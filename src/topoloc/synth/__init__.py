"""Seeded synthetic data for tests, the demo and benchmarks: street routes and bag-of-words streams.

Street routes are a small 3-D world -- a straight street between two rows of
building facades, over a road with pavements -- rendered as forward-looking
views for several *tours* (traverses) at different hours of one day.  They
exist so that place-recognition methods, in particular local-feature ones
(SIFT bag of words, FAB-MAP, a feature co-occurrence map), can be run end to
end on data with known ground truth and nothing to download.  Images made
here are **not** a benchmark: never publish results measured on them.  The
renderer is split along its stages:

* :mod:`~topoloc.synth.config` -- the parameters of a route and the random
  streams derived from its seed;
* :mod:`~topoloc.synth.patches` -- drawing primitives and the texture patches
  (windows, signs, posters, the shared pool that causes aliasing);
* :mod:`~topoloc.synth.textures` -- the facade and ground bands of the atlas;
* :mod:`~topoloc.synth.world` -- the textured street, its lamps and its static light;
* :mod:`~topoloc.synth.lighting` -- the sun, the sky and the lights at one hour;
* :mod:`~topoloc.synth.camera` -- the camera pose and the rendering of one view;
* :mod:`~topoloc.synth.route` -- tour plans and writing the tours to disk.

:mod:`~topoloc.synth.words` draws bag-of-words streams directly (Zipf-distributed
words, and noisy revisits of places), for FAB-MAP tests and timings.
"""

from topoloc.synth.camera import Pose, render_view
from topoloc.synth.config import RouteConfig
from topoloc.synth.lighting import Lighting, sun_position, tour_lighting
from topoloc.synth.route import DEFAULT_TOURS, TourPlan, generate_route, plan_tour, speed_profile
from topoloc.synth.words import loop_sequence, revisit_queries, zipf_inclusion, zipf_occurrence
from topoloc.synth.world import World, build_world

__all__ = [
    "DEFAULT_TOURS",
    "Lighting",
    "Pose",
    "RouteConfig",
    "TourPlan",
    "World",
    "build_world",
    "generate_route",
    "loop_sequence",
    "plan_tour",
    "render_view",
    "revisit_queries",
    "speed_profile",
    "sun_position",
    "tour_lighting",
    "zipf_inclusion",
    "zipf_occurrence",
]
