"""Which places look alike: the look-alikes each place keeps, strongest first."""

from __future__ import annotations

import numpy as np

from topoloc.maps.confusion import note_look_alike


def test_a_place_keeps_its_strongest_look_alikes_once_each() -> None:
    rows, sup = np.full((4, 2), -1, np.int64), np.zeros((4, 2), np.float32)
    for b, n in ((1, 10), (2, 30), (1, 25), (3, 5), (2, 20), (0, 12)):
        note_look_alike(rows, sup, 0, b, n)
    # Place 1 raised to 25, place 2 kept at its best (30); 3 (5) never made it, 0 is the place itself.
    assert rows[0].tolist() == [2, 1] and sup[0].tolist() == [30, 25]
    note_look_alike(rows, sup, 1, 3, 0)  # no support: no look-alike
    assert rows[1].tolist() == [-1, -1]
    note_look_alike(rows, sup, 0, 3, 26)  # a third, stronger than the weaker of the two kept, takes its slot
    assert rows[0].tolist() == [2, 3] and sup[0].tolist() == [30, 26]
