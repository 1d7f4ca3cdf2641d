"""benches/report.py on the quick speed benchmark that `make test` runs before these tests
(target/bench/quick.json, with `--int8-models`): the results page shows the int8 section
with both ceilings and the ratios to FP32 measured in that run."""

import json
import re
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT

QUICK = ROOT / "target" / "bench" / "quick.json"


def report(results, out) -> subprocess.CompletedProcess:
    """benches/report.py on the measurements in `results`, writing the page `out`."""
    return subprocess.run([sys.executable, str(ROOT / "benches" / "report.py"), "--results", str(results),
                           "--out", str(out)], capture_output=True, text=True, timeout=60)


def test_the_results_page_shows_int8_against_fp32_from_the_same_run(tmp_path):
    if not QUICK.exists():
        pytest.fail(f"{QUICK} is missing: `make test` writes it (cargo bench --bench speed -- --quick "
                    "--int8-models target/bench/int8) before these tests")
    speed = json.loads(QUICK.read_text())
    assert speed["int8"], "the quick benchmark ran without --int8-models"
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(QUICK, results / "speed.json")
    out = tmp_path / "results.md"
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    assert "### Int8 against FP32" in page
    # The ceilings row: FP32 and int8 as measured, and their ratio.
    g, gi = speed["gemm_ceiling"]["gflops"], speed["int8"]["gemm_ceiling"]["gops"]
    row = re.search(r"\| GEMM ceiling \(\d+³\), \d+ threads \(G\(FL\)OP/s\) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \|", page)
    assert row, page
    assert (float(row[1]), float(row[2])) == (round(g, 1), round(gi, 1))
    assert float(row[3]) == pytest.approx(gi / g, abs=0.006)
    ratio = speed["int8"]["time_vs_fp32"]["engine"]
    assert f"| {ratio:.2f} |" in page and ratio > 0
    assert "bf16:" in page


def test_the_results_page_compares_with_oidn_in_like_terms(tmp_path):
    if not QUICK.exists():
        pytest.fail(f"{QUICK} is missing: `make test` writes it before these tests")
    speed = json.loads(QUICK.read_text())
    e = speed["engine"]
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(QUICK, results / "speed.json")
    oidn = {"width": e["width"], "height": e["height"], "pyoidn": "2.5.1.0",
            "quality": {"high": {"seconds": 0.5, "file_seconds": 0.8, "file_read_seconds": 0.12,
                                 "file_write_seconds": 0.17, "runs": 3},
                        "fast": {"seconds": 0.25, "file_seconds": 0.5, "runs": 3}}}
    (results / "oidn.json").write_text(json.dumps(oidn))
    out = tmp_path / "results.md"
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    # The denoising alone against the filter call; file to file against read, filter, write.
    alone = re.search(r"\| denoising alone \| ([\d.]+) \| 0\.50 \| ([\d.]+) \| 0\.25 \| ([\d.]+) \|", page)
    whole = re.search(r"\| EXR file to EXR file \| ([\d.]+) \| 0\.80 \| ([\d.]+) \| 0\.50 \| ([\d.]+) \|", page)
    assert alone and whole, page
    assert float(alone[1]) == round(e["engine_s"], 2) and float(whole[1]) == round(e["engine_with_io_s"], 2)
    assert float(alone[2]) == pytest.approx(e["engine_s"] / 0.5, abs=0.006)
    assert float(whole[3]) == pytest.approx(e["engine_with_io_s"] / 0.5, abs=0.006)
    assert "here 0.12 s to read and 0.17 s to write" in page
    # An OIDN measurement from before file_seconds: the filter rows only.
    for q in oidn["quality"].values():
        del q["file_seconds"]
    (results / "oidn.json").write_text(json.dumps(oidn))
    r = report(results, out)
    assert r.returncode == 0 and "quality high | 0.50 |" in out.read_text() and "EXR file to EXR" not in out.read_text()


def test_the_results_page_shows_the_rounds_in_turns_against_oidn(tmp_path):
    # benches/paired_speed.py's rounds: each with its ratio, and the median with its range.
    if not QUICK.exists():
        pytest.fail(f"{QUICK} is missing: `make test` writes it before these tests")
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(QUICK, results / "speed.json")
    rounds = [{"mcdenoise_run_s": a, "oidn_s": b, "ratio": a / b} for a, b in ((2.2, 1.6), (2.5, 1.5), (2.0, 1.6))]
    paired = {"width": 1280, "height": 720, "threads": 2, "variant": "full", "oidn_quality": "high",
              "pyoidn": "2.5.1.0", "rounds": rounds, "mcdenoise_run_median_s": 2.2, "oidn_median_s": 1.6,
              "ratio_median": 2.2 / 1.6, "ratio_min": 2.0 / 1.6, "ratio_max": 2.5 / 1.5}
    (results / "paired.json").write_text(json.dumps(paired))
    out = tmp_path / "results.md"
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    assert "### `mcdenoise run` against OIDN high, in turns" in page
    assert "| 2 | 2.50 | 1.50 | 1.67 |" in page
    assert "| **median** | 2.20 | 1.60 | **1.38** (1.25–1.67) |" in page


def test_the_results_page_shows_the_gpu_run_against_oidn(tmp_path):
    # The committed GPU measurements (docs/results/gpu.json, gpu-split.json): each daemon row
    # with its ratio to OIDN's CUDA time at that size, the parts that failed, the parity.
    results = tmp_path / "results"
    results.mkdir()
    for name in ("gpu.json", "gpu-split.json"):
        shutil.copy(ROOT / "docs" / "results" / name, results / name)
    out = tmp_path / "results.md"
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    gpu = json.loads((results / "gpu.json").read_text())
    oidn = {o["frame"]: o["ms_per_frame"] for o in gpu["oidn"]}
    assert "### GPU: the daemon against OIDN's CUDA device" in page
    for row in gpu["daemon"]:
        ratio = row["job_stages_ms_median"]["inference"] / oidn[row["frame"]]
        assert f"{row['job_stages_ms_median']['inference']:.1f} / " in page and f"| {ratio:.0f}× |" in page
    for e in gpu["errors"]:
        assert f"Failed: **{e['part']}**" in page
    for p in gpu["parity"]:
        assert f"| {p['precision']} | {p['reconstruction']} | {p['max_abs_diff']:.3g} |" in page
    assert "#### Where the frame time goes" in page
    # A run without OIDN (`--oidn-benchmark` not given): the same rows, their OIDN cells empty.
    (results / "gpu.json").write_text(json.dumps({**gpu, "oidn": None}))
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    rows = [ln for ln in out.read_text().splitlines() if ln.endswith("|  |  |")]
    assert len(rows) == len(gpu["daemon"]) + len(gpu["variants"]), rows
    assert all(ln.startswith(f"| {r['frame']} | ") for ln, r in zip(rows, gpu["daemon"] + gpu["variants"])), rows


def test_the_results_page_shows_each_evaluated_set_with_what_it_holds(tmp_path):
    # make eval writes one directory per set; the page shows those present, in order, each
    # under its title with the line evaluate opens results.md with (what frames were judged).
    results = tmp_path / "results"
    for name, held in (("test-both", "48 frames of 16 scenes from `data-test`"),
                       ("heldout-384", "18 frames of 6 scenes from `runs/cpu/heldout384`"),
                       ("heldout-384-cycles", "9 frames of 3 scenes from `runs/cpu/heldout384c`")):
        (results / name).mkdir(parents=True)
        (results / name / "results.md").write_text(f"{held} (split `test`).\n\n## Mean over all frames\n\n| m |\n")
    out = tmp_path / "results.md"
    r = report(results, out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    held = page.index("### Held-out scenes at 384² (never seen in training or selection)\n\n18 frames of 6 scenes")
    test = page.index("### Test scenes, both renderers (never seen in training or selection)\n\n48 frames of 16 scenes")
    cycles = page.index("### Held-out Cycles scenes at 384² (never seen in training or selection)\n\n9 frames of 3")
    assert held < cycles < test and "#### Mean over all frames" in page
    assert "### Validation scenes" not in page
