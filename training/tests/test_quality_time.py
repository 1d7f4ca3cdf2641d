"""The benchmarks that time `mcdenoise run` against OIDN, on tiny inputs: benches/quality_time.py
(the error of each method over the frames every method ran on, against the seconds of a
whole `mcdenoise run` and of an OIDN call) and benches/paired_speed.py (the two timed in
turns, every round's ratio kept)."""

import json
import os
import sys
from pathlib import Path

import pytest

from mcdenoise_train.exr import write_exr
from mcdenoise_train.frames import synthetic_frame

ROOT = Path(__file__).resolve().parents[2]
BIN = os.environ.get("MCDENOISE_BIN", str(ROOT / "target/release/mcdenoise"))
needs_engine = pytest.mark.skipif(not os.path.isfile(BIN) and not os.environ.get("CI"), reason="MCDENOISE_BIN not built")


@needs_engine
def test_quality_against_time_on_tiny_inputs(tmp_path):
    sys.path.insert(0, str(ROOT / "benches"))
    import quality_time

    frame = tmp_path / "frame.exr"
    write_exr(frame, synthetic_frame(32, 48, seed=1))  # height 32, width 48
    rows = [
        # frame a: every method; frame b: no OIDN row, so it is left out of every mean.
        {"frame": "a", "method": "default", "relmse": 0.01, "dssim": 0.10},
        {"frame": "a", "method": "oidn-fast", "relmse": 0.03, "dssim": 0.20},
        {"frame": "b", "method": "default", "relmse": 9.0, "dssim": 0.90},
        {"frame": "c", "method": "default", "relmse": 0.03, "dssim": 0.30},
        {"frame": "c", "method": "oidn-fast", "relmse": 0.05, "dssim": 0.40},
    ]
    results = tmp_path / "results.jsonl"
    results.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "qt.json"
    assert quality_time.main(["--frame", str(frame), "--models", str(ROOT / "tests/fixtures/models/tiny"),
                              "--results", str(results), "--variants", "default", "--qualities", "fast",
                              "--runs", "1", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert (report["width"], report["height"], report["frames"]) == (48, 32, 2)
    points = {p["method"]: p for p in report["points"]}
    assert points["default"]["relmse"] == pytest.approx(0.02) and points["default"]["dssim"] == pytest.approx(0.2)
    assert points["oidn-fast"]["relmse"] == pytest.approx(0.04)
    assert all(p["seconds"] > 0 for p in report["points"])
    assert out.with_suffix(".png").stat().st_size > 1000

    with pytest.raises(SystemExit, match="no frame has rows of every method"):
        quality_time.main(["--frame", str(frame), "--results", str(results), "--variants", "lin2020",
                           "--qualities", "fast", "--out", str(out)])


@needs_engine
def test_rounds_in_turns_on_tiny_inputs(tmp_path):
    sys.path.insert(0, str(ROOT / "benches"))
    import paired_speed

    frame = tmp_path / "frame.exr"
    write_exr(frame, synthetic_frame(32, 48, seed=2))
    out = tmp_path / "paired.json"
    assert paired_speed.main([str(frame), "--models", str(ROOT / "tests/fixtures/models/tiny"), "--rounds", "3",
                              "--threads", "1", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert (report["width"], report["height"], report["oidn_quality"]) == (48, 32, "high")
    assert len(report["rounds"]) == 3
    ratios = [r["mcdenoise_run_s"] / r["oidn_s"] for r in report["rounds"]]
    assert [r["ratio"] for r in report["rounds"]] == pytest.approx(ratios)
    assert report["ratio_min"] <= report["ratio_median"] <= report["ratio_max"]
    assert report["ratio_median"] == pytest.approx(sorted(ratios)[1])

    with pytest.raises(SystemExit, match="mcdenoise run failed"):
        paired_speed.main([str(frame), "--models", str(tmp_path / "nosuch"), "--rounds", "1", "--out", str(out)])
    with pytest.raises(SystemExit, match="no such frame"):
        paired_speed.main([str(tmp_path / "none.exr"), "--out", str(out)])
