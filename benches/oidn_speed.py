"""Intel Open Image Denoise on the speed benchmark's frame, same machine and cores
(`make bench` runs it after `cargo bench --bench speed`).

    python benches/oidn_speed.py target/bench/frame-1280x720.exr --out target/bench/oidn.json

Times `pyoidn.denoise` (HDR, with albedo and normal, as in the quality evaluation) at quality
`high` and `fast`: the median of `--runs` calls after one warm-up call, device creation and
EXR decoding excluded. OIDN uses every core of the machine.
"""

import argparse
import json
import statistics
import sys
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import OpenEXR
import pyoidn


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("frame")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    f = OpenEXR.File(a.frame, separate_channels=True)
    ch = {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    rgb = lambda base: np.ascontiguousarray(np.stack([ch[f"{base}.{c}"] for c in "RGB"], -1))
    color = np.ascontiguousarray(rgb("diffuse") + rgb("specular"))
    albedo, normal = rgb("albedo"), rgb("normal")
    h, w = color.shape[:2]
    rows = {}
    for quality in ("high", "fast"):
        pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
        times = []
        for _ in range(a.runs):
            t = time.perf_counter()
            pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
            times.append(time.perf_counter() - t)
        rows[quality] = {"seconds": statistics.median(times), "runs": a.runs}
        print(f"OIDN {quality} {w}x{h}: {rows[quality]['seconds']:.2f} s", file=sys.stderr)
    Path(a.out).write_text(json.dumps({"width": w, "height": h, "pyoidn": metadata.version("pyoidn"), "quality": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
