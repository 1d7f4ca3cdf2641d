"""Frames of several sizes train together: the larger ones are cut into tiles of the smallest."""

import json

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


def _write(root, name, h, w, seed, split="train"):
    from mcdenoise_train.exr import write_exr
    from mcdenoise_train.frames import synthetic_frame

    ch = synthetic_frame(h, w, seed=seed)
    write_exr(root / f"{name}.exr", ch)
    write_exr(root / f"{name}-ref.exr", ch)
    with open(root / "manifest.jsonl", "a") as m:
        m.write(json.dumps({"scene": name, "spp": 4, "split": split, "noisy": f"{name}.exr",
                            "reference": f"{name}-ref.exr"}) + "\n")


def test_a_frame_set_takes_the_scenes_completed_since(tmp_path):
    """A data set rendered beside the training: refresh() adds the frames that appeared, cut
    to the set's size; frames smaller than it are left out; nothing is loaded twice."""
    import torch

    from mcdenoise_train.train_ms import FrameSet

    _write(tmp_path, "a", 16, 16, 1)
    _write(tmp_path, "v", 16, 16, 2, split="val")
    fs = FrameSet([str(tmp_path)], "train", torch.device("cpu"))
    assert len(fs) == 1 and fs.raw.shape[-2:] == (16, 16) and fs.refresh() == 0
    _write(tmp_path, "b", 32, 48, 3)  # 2 x 3 tiles of 16²
    _write(tmp_path, "c", 8, 8, 4)  # smaller than the set's frames: left out
    assert fs.refresh() == 6
    assert len(fs) == 7 and fs.raw.shape == (7, 20, 16, 16) and fs.ref.shape[0] == fs.maxima.shape[0] == 7
    assert fs.names.count("b") == 6 and "c" not in fs.names
    assert fs.refresh() == 0 and len(fs) == 7


def test_training_frames_have_the_albedo_the_engine_gives_the_networks(tmp_path):
    """load_raw prefilters the albedo as the engine does by default, or not with
    --albedo-prefilter off; the two are cached apart."""
    from mcdenoise_train.preprocess import ALBEDO, VAR, prefilter_albedo
    from mcdenoise_train.train_ms import load_raw, parse

    _write(tmp_path, "a", 16, 16, 1)
    rec = {"noisy": str(tmp_path / "a.exr"), "reference": str(tmp_path / "a-ref.exr")}
    cache = tmp_path / "raw-cache"
    on, off = load_raw(rec, cache), load_raw(rec, cache, albedo_prefilter=False)
    filtered = prefilter_albedo(off["raw"][ALBEDO], off["raw"][VAR["albedo"]])
    # Kept in half float, as the engine keeps it.
    np.testing.assert_array_equal(on["raw"][ALBEDO], filtered.astype(np.float16).astype(np.float32))
    assert not np.array_equal(on["raw"][ALBEDO], filtered)
    assert np.abs(on["raw"][ALBEDO] - off["raw"][ALBEDO]).max() > 1e-3
    assert sorted(p.name for p in cache.iterdir()) == ["a-albedo-0.7-1.npz", "a-albedo-off.npz"]
    assert np.array_equal(load_raw(rec, cache)["raw"], on["raw"]), "read back from its own cache file"
    # With the albedo of the frame without variances kept after the raw channels
    # (--var-dropout): prefiltered by its estimated variance; cached apart.
    from mcdenoise_train.exr import read_exr
    from mcdenoise_train.preprocess import raw_from_channels
    kept = load_raw(rec, cache, keep_albedo=True)
    bare = {k: v for k, v in read_exr(rec["noisy"]).items() if "Variance" not in k}
    assert kept["raw"].shape[0] == 23 and np.array_equal(kept["raw"][:20], on["raw"])
    np.testing.assert_array_equal(kept["raw"][20:], raw_from_channels(bare)[0][ALBEDO])
    assert not np.array_equal(kept["raw"][20:], on["raw"][ALBEDO])
    assert "a-albedo-0.7-1-kept.npz" in {p.name for p in cache.iterdir()}
    assert np.array_equal(load_raw(rec, cache, keep_albedo=True)["raw"], kept["raw"])
    assert parse(["--data", "x", "--out", "y"]).albedo_prefilter == "on"
    assert parse(["--data", "x", "--out", "y", "--albedo-prefilter", "off"]).albedo_prefilter == "off"
