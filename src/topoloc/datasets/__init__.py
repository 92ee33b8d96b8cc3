"""Traverses (image folders, or frames held in memory) and ground truth."""

from topoloc.datasets.groundtruth import (
    GroundTruth,
    ground_truth_from_file,
    ground_truth_from_places,
    ground_truth_from_xy,
    parse_tolerance,
)
from topoloc.datasets.traverse import Traverse, find_images, load_traverse, read_image

__all__ = [
    "GroundTruth",
    "Traverse",
    "find_images",
    "ground_truth_from_file",
    "ground_truth_from_places",
    "ground_truth_from_xy",
    "load_traverse",
    "parse_tolerance",
    "read_image",
]
