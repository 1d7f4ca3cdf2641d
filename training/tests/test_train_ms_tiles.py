"""Frames of several sizes train together: the larger ones are cut into tiles of the smallest."""

import numpy as np

from mcdenoise_train.train_ms import tile_to_smallest


def _frame(h, w, seed):
    r = np.random.default_rng(seed)
    return {"raw": r.random((20, h, w), np.float32), "ref": r.random((6, h, w), np.float32),
            "maxima": np.array([seed, seed + 1], np.float32), "meta": (f"f{seed}", seed, f"s{seed}")}


def test_larger_frames_become_tiles_of_the_smallest_size():
    small, large, odd = _frame(8, 8, 1), _frame(16, 24, 2), _frame(17, 9, 3)
    tiles = tile_to_smallest([small, large, odd])
    assert len(tiles) == 1 + 2 * 3 + 2 * 1
    assert all(t["raw"].shape == (20, 8, 8) and t["ref"].shape == (6, 8, 8) for t in tiles)
    # The tiles of the 16x24 frame cover it exactly, row by row, keeping its maxima and name.
    from_large = tiles[1:7]
    rebuilt = np.concatenate([np.concatenate([t["raw"] for t in from_large[r * 3:r * 3 + 3]], axis=-1)
                              for r in range(2)], axis=-2)
    assert np.array_equal(rebuilt, large["raw"])
    assert all(np.array_equal(t["maxima"], large["maxima"]) and t["meta"] == ("f2", 2, "s2") for t in from_large)
    # A remainder smaller than a tile is dropped: 17x9 gives two 8x8 tiles from its top-left.
    assert np.array_equal(tiles[7]["ref"], odd["ref"][:, :8, :8])
    assert np.array_equal(tiles[8]["ref"], odd["ref"][:, 8:16, :8])
