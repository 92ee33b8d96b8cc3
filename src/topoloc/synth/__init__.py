"""Synthetic routes: a seeded street rendered at several times of day, for tests and the demo."""

from topoloc.synth.route import RouteConfig, generate_route

__all__ = ["RouteConfig", "generate_route"]
