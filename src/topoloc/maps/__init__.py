"""Saved maps: build once, save in one file, localise new images against it, add later tours."""

from topoloc.maps.localizer import Localizer
from topoloc.maps.map import Map
from topoloc.maps.mapfile import MAP_KIND, MAP_VERSION, read_map_file, write_map_file
from topoloc.maps.tours import tour_record

__all__ = ["MAP_KIND", "MAP_VERSION", "Localizer", "Map", "read_map_file", "tour_record",
           "write_map_file"]
