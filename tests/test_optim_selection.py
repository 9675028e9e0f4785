"""The optimiser's choice of returned poses: the start is a candidate, an epoch replaces the best only when its map
is sharper (map selection) or its loss lower, and the wording says which."""

from __future__ import annotations

import numpy as np

from dm2_backend.optim.epoch import Epoch
from dm2_backend.optim.selection import first_candidate, offer, selection


def test_the_map_selection_keeps_the_start_until_an_epoch_is_sharper():
    start = np.eye(4)[None]
    best = first_candidate(start, 2.0)
    assert best.epoch == -1 and best.map == best.start_map == 2.0
    blurrier = offer(best, Epoch(0, 0.1, 1.0, 10, map_entropy=2.5), start + 1, by_map=True)
    assert blurrier is best and "no epoch made a sharper map" in selection(best, True)
    sharper = offer(best, Epoch(1, 0.9, 1.0, 20, map_entropy=1.5), start + 2, by_map=True)
    assert sharper.epoch == 1 and sharper.map == 1.5 and sharper.start_map == 2.0
    assert (sharper.poses == start + 2).all() and "sharpest map: epoch 1" in selection(sharper, True)


def test_the_loss_selection_takes_the_lowest_loss():
    best = first_candidate(np.eye(4)[None], None)
    assert best.map is None and selection(best, False) == "the start (no epoch ran)"
    best = offer(best, Epoch(0, 0.5, 1.0, 10), np.eye(4)[None], by_map=False)
    best = offer(best, Epoch(1, 0.7, 1.0, 20), np.eye(4)[None], by_map=False)
    assert best.epoch == 0
    assert selection(best, False, rejected=2) == "lowest epoch loss: epoch 0; 2 diverged epochs rejected"
