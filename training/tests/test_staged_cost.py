"""benches/staged_cost.py on a small frame: the cut graphs give the whole graph's outputs, and
the two layouts are the engine's regions and the cores with their margin."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_staged_cost_cuts_the_shipped_graph_exactly(capsys):
    sys.path.insert(0, str(ROOT / "benches"))
    import staged_cost

    assert staged_cost.main(["--sizes", "160x64", "--tile", "48", "--rounds", "1", "--threads", "1"]) == 0
    (row,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert row["max_abs_diff"] == 0.0
    # Cores of 48 × 32 (the last column 16 wide): the 128-px halo reaches the whole frame but
    # for the last column's first 16 px; the 16-px margin stays near each core.
    assert row["now_regions"] == ["160x64", "160x64", "160x64", "144x64"] * 2
    assert row["now_pixels"] == 2 * (3 * 160 + 144) * 64
    assert row["staged_regions"] == ["64x48", "80x48", "80x48", "32x48"] * 2
    assert row["middle"] == "80x32"
    assert row["now_s"] > 0 and row["ratio_median"] > 0


def test_cores_are_the_engines():
    sys.path.insert(0, str(ROOT / "benches"))
    import staged_cost

    # Tiling::cores with the default tile and halo: two cores at 720p, six at 1080p.
    assert staged_cost.cores(1280, 720, 768, 128, 16) == [(0, 0, 640, 720), (640, 0, 640, 720)]
    six = staged_cost.cores(1920, 1080, 768, 128, 16)
    assert [(x, y) for x, y, _, _ in six] == [(0, 0), (640, 0), (1280, 0), (0, 544), (640, 544), (1280, 544)]
    assert [staged_cost.grow(c, 128, 1920, 1080, 16) for c in six[:3]] == [(768, 672), (896, 672), (768, 672)]


def test_frames_the_engine_cuts_further_are_refused():
    sys.path.insert(0, str(ROOT / "benches"))
    import staged_cost

    with pytest.raises(SystemExit, match="region bound"):
        staged_cost.main(["--sizes", "3840x2160", "--rounds", "1", "--threads", "1"])
