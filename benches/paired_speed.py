"""`mcdenoise run` against OIDN high, round by round: the issue's ratio taken so that the
machine's speed, which drifts by 20-30 % from minute to minute on these shared virtual
machines, weighs on both sides alike.

    python benches/paired_speed.py target/bench/frame-1280x720.exr --models models \\
        --rounds 7 --threads 2 --out docs/results/paired.json

Each round times one `mcdenoise run` of the frame as a whole process (EXR decode, model
loading, denoising, EXR encode; the wall time around the process) and one `pyoidn.denoise`
call at quality `high` (HDR, albedo and normal, its device and filter made before the
rounds, so the call alone), in turns: the first in even rounds, the second in odd ones. One
warm-up of each comes first (the page cache, OIDN's filter). The JSON has every round, the
median of each side and the median, lowest and highest of the rounds' ratios (ours / OIDN).
OIDN's CPU device takes every core of the machine; compare on a machine with --threads cores.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "training"))

from mcdenoise_train.data import engine_binary  # noqa: E402
from mcdenoise_train.evaluate import oidn_inputs  # noqa: E402
from mcdenoise_train.exr import read_exr  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("frame")
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--variant", default="auto", help="of `mcdenoise run` (auto: the frame's default)")
    p.add_argument("--quality", default="high", help="OIDN's")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    if a.rounds < 1:
        raise SystemExit("--rounds: at least 1")
    if not Path(a.frame).exists():
        raise SystemExit(f"{a.frame}: no such frame (`make bench` writes it)")
    import pyoidn

    ch = read_exr(a.frame)
    h, w = next(iter(ch.values())).shape
    color, albedo, normal = oidn_inputs(ch)
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [engine_binary(), "run", a.frame, "-o", str(Path(tmp) / "out.exr"), "--models", a.models,
               "--variant", a.variant, "--threads", str(a.threads)]

        def ours() -> tuple[float, dict]:
            t = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True)
            seconds = time.perf_counter() - t
            if r.returncode != 0:
                raise SystemExit(f"mcdenoise run failed ({r.returncode}): {r.stderr.strip()}")
            return seconds, json.loads(r.stdout)

        def oidn() -> float:
            t = time.perf_counter()
            pyoidn.denoise(color, albedo, normal, hdr=True, quality=a.quality)
            return time.perf_counter() - t

        _, report = ours()
        oidn()
        rounds = []
        for k in range(a.rounds):
            if k % 2 == 0:
                (ours_s, report), oidn_s = ours(), oidn()
            else:
                oidn_s = oidn()
                ours_s, report = ours()
            rounds.append({"mcdenoise_run_s": ours_s, "oidn_s": oidn_s, "ratio": ours_s / oidn_s})
            print(f"round {k + 1}: mcdenoise run {ours_s:.2f} s, OIDN {a.quality} {oidn_s:.2f} s, "
                  f"{ours_s / oidn_s:.2f}x", file=sys.stderr)
    ratios = [r["ratio"] for r in rounds]
    result = {
        "width": w, "height": h, "threads": a.threads, "variant": report.get("variant", a.variant),
        "oidn_quality": a.quality, "pyoidn": metadata.version("pyoidn"),
        "huge_pages": os.environ.get("MCDENOISE_HUGE_PAGES", "default"), "rounds": rounds,
        "mcdenoise_run_median_s": statistics.median(r["mcdenoise_run_s"] for r in rounds),
        "oidn_median_s": statistics.median(r["oidn_s"] for r in rounds),
        "ratio_median": statistics.median(ratios), "ratio_min": min(ratios), "ratio_max": max(ratios),
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"mcdenoise run / OIDN {a.quality}: median {result['ratio_median']:.2f}x "
          f"({result['ratio_min']:.2f}-{result['ratio_max']:.2f}x over {a.rounds} rounds)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
