"""Intel Open Image Denoise on the speed benchmark's frame, same machine and cores
(`make bench` runs it after `cargo bench --bench speed`).

    python benches/oidn_speed.py target/bench/frame-1280x720.exr --out target/bench/oidn.json

Times `pyoidn.denoise` (HDR, with albedo and normal, as in the quality evaluation) at quality
`high` and `fast`: the median of `--runs` calls after one warm-up call, device creation and
EXR decoding excluded (`seconds`). OIDN uses every core of the machine.

`file_seconds` is the counterpart of `mcdenoise run`, EXR file to EXR file: the frame read
and decoded with OpenEXR (the C++ library), the color summed from the diffuse and specular
layers, the filter call, and the result written as float RGB with PIZ compression, as
`mcdenoise run` writes it; the median of `--runs`, after the warm-up above. OpenEXR's Python
binding reads and writes on one thread, where `mcdenoise` decodes and encodes on every core:
this row is the time a farm would see from such a tool, not the denoisers' ratio.
"""

import argparse
import json
import statistics
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import OpenEXR
import pyoidn


def read_frame(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(color, albedo, normal) of a frame, [H, W, 3] float32 each."""
    f = OpenEXR.File(path, separate_channels=True)
    ch = {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    rgb = lambda base: np.ascontiguousarray(np.stack([ch[f"{base}.{c}"] for c in "RGB"], -1))  # noqa: E731
    return np.ascontiguousarray(rgb("diffuse") + rgb("specular")), rgb("albedo"), rgb("normal")


def file_to_file(src: str, dst: str, quality: str) -> tuple[float, float, float]:
    """Seconds to denoise `src` into `dst` with OIDN (read, filter, write), and to read
    and to write alone."""
    t = time.perf_counter()
    color, albedo, normal = read_frame(src)
    read = time.perf_counter() - t
    out = pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
    header = {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {c: np.ascontiguousarray(out[..., i], dtype=np.float32) for i, c in enumerate("RGB")}
    w = time.perf_counter()
    with OpenEXR.File(header, channels) as f:
        f.write(dst)
    end = time.perf_counter()
    return end - t, read, end - w


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("frame")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    color, albedo, normal = read_frame(a.frame)
    h, w = color.shape[:2]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for quality in ("high", "fast"):
            pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
            times = []
            for _ in range(a.runs):
                t = time.perf_counter()
                pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
                times.append(time.perf_counter() - t)
            files = [file_to_file(a.frame, str(Path(tmp) / "out.exr"), quality) for _ in range(a.runs)]
            whole, read, write = (statistics.median(f[i] for f in files) for i in range(3))
            rows[quality] = {"seconds": statistics.median(times), "file_seconds": whole,
                             "file_read_seconds": read, "file_write_seconds": write, "runs": a.runs}
            print(f"OIDN {quality} {w}x{h}: {rows[quality]['seconds']:.2f} s, EXR to EXR "
                  f"{rows[quality]['file_seconds']:.2f} s", file=sys.stderr)
    Path(a.out).write_text(json.dumps({"width": w, "height": h, "pyoidn": metadata.version("pyoidn"), "quality": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
