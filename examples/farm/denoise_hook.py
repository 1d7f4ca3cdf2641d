"""Post-render hook: denoise each rendered frame with mcdenoise and write the result next to it.

    shots/sh010/beauty.0001.exr  ->  shots/sh010/beauty.0001.denoised.exr

The frame must be in the layout of docs/frame-layout.md (diffuse, specular, albedo,
normal, depth, or the Blender Cycles passes they derive from; variances and covariance
optional). A frame that is not is refused
by the daemon with the missing channels named; the hook reports that and fails the frame.

As a per-frame farm command (exit status 0 when every frame was denoised, 1 otherwise, so
the farm marks the task failed and can retry it):

    python denoise_hook.py --server http://mcdenoise.farm:8080 beauty.0001.exr [...]
    python denoise_hook.py --pattern 'shots/sh010/beauty.####.exr' --frames 1-24

(OpenCue: a layer running this with `--frames #IFRAME#-#IFRAME#` that depends frame by
frame on the render layer; Deadline: the job's post-task script calling `denoise_frames`;
Blender: examples/blender/denoise_handler.py.) The token comes from `--token` or
MCDENOISE_TOKEN, the server from `--server` or MCDENOISE_SERVER, as for `mcdenoise
submit`.

From Python: `denoise_frame(path, client)`. Running the hook twice on the same file finds
the same job (the idempotency key is derived from the file's path, size and mtime) unless
the daemon has forgotten it; a job lost while waiting (a 404: the replica that held it was
removed, or its result expired) is submitted again, up to `resubmits` times.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from pathlib import Path
from typing import Callable, Iterable, List, Optional

try:
    import mcdenoise_client as mc
except ImportError:  # run from the repository: the client lives in clients/python
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "clients" / "python"))
    import mcdenoise_client as mc

SUFFIX = ".denoised"


def output_path(frame: os.PathLike | str, suffix: str = SUFFIX) -> Path:
    """Where the denoised frame goes: the same name with `suffix` before `.exr`."""
    p = Path(frame)
    if p.suffix.lower() != ".exr":
        raise ValueError(f"{p}: not an .exr file")
    return p.with_name(p.stem + suffix + p.suffix)


def denoise_frame(
    frame: os.PathLike | str,
    client: mc.Client,
    *,
    out: os.PathLike | str | None = None,
    label: Optional[str] = None,
    priority: Optional[str] = None,
    wait_timeout: Optional[float] = None,
    resubmits: int = 2,
    log: Callable[[str], None] = lambda msg: print(msg, file=sys.stderr),
) -> dict:
    """Submits `frame`, waits for its job and writes the denoised EXR to `out` (default:
    next to the frame, see `output_path`). Returns the finished job; raises
    `mc.DaemonError` (refused, e.g. 422 with the missing channels), `mc.JobFailed` or
    `OSError`."""
    frame = Path(frame)
    out = Path(out) if out is not None else output_path(frame)
    key = mc.file_key(frame)
    for attempt in range(resubmits + 1):
        job = client.submit(frame, label=label, priority=priority, idempotency_key=key)
        log(f"{frame.name}: job {job['id']} {job['state']}")
        try:
            job = client.wait(job["id"], timeout=wait_timeout)
            size = client.download(job["id"], out)
        except mc.DaemonError as e:
            if e.status == 404 and attempt < resubmits:
                log(f"{frame.name}: job {job['id']} is gone ({e.message}); submitting again")
                continue
            raise
        t = job.get("timings_ms") or {}
        log(f"{frame.name}: wrote {out} ({size} bytes, {t.get('total', 0) / 1e3:.1f} s in the daemon)")
        return job
    raise AssertionError("unreachable")


def denoise_frames(frames: Iterable[os.PathLike | str], client: mc.Client, **kw) -> List[str]:
    """Denoises each frame in turn; returns the error message of each frame that failed
    (empty when all succeeded). One bad frame does not stop the others."""
    errors = []
    for f in frames:
        try:
            denoise_frame(f, client, **kw)
        except (mc.DaemonError, mc.JobFailed, OSError, TimeoutError) as e:
            msg = f"{f}: {e}"
            kw.get("log", lambda m: print(m, file=sys.stderr))(f"{msg}")
            errors.append(msg)
    return errors


def expand_pattern(pattern: str, frames: str) -> List[str]:
    """`beauty.####.exr` with `1-3,7` -> beauty.0001.exr, beauty.0002.exr, beauty.0003.exr,
    beauty.0007.exr (the number of `#` is the padding)."""
    m = re.search(r"#+", pattern)
    if not m:
        raise ValueError(f"{pattern}: no #### frame-number placeholder")
    numbers: List[int] = []
    for part in frames.split(","):
        a, _, b = part.strip().partition("-")
        numbers.extend(range(int(a), int(b or a) + 1))
    width = len(m.group(0))
    return [pattern[: m.start()] + str(n).zfill(width) + pattern[m.end():] for n in numbers]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("frames", nargs="*", help="rendered EXR frames")
    p.add_argument("--pattern", help="frame path with #### for the number (with --frames)")
    p.add_argument("--frames", dest="range", help="frame numbers for --pattern, e.g. 1-24 or 5")
    p.add_argument("--server", default=os.environ.get("MCDENOISE_SERVER", "http://127.0.0.1:8080"))
    p.add_argument("--token", default=os.environ.get("MCDENOISE_TOKEN"))
    p.add_argument("--label", help="job label (default: the frame's directory name)")
    p.add_argument("--priority", choices=["high", "normal", "low"])
    p.add_argument("--timeout", type=float, default=3600, help="seconds to wait for each job")
    args = p.parse_args(argv)
    frames = list(args.frames)
    if args.pattern:
        if not args.range:
            p.error("--pattern needs --frames")
        frames += expand_pattern(args.pattern, args.range)
    if not frames:
        p.error("no frames given")

    def on_retry(reason, wait):
        print(f"mcdenoise: {reason}; retrying in {wait:g} s", file=sys.stderr)

    client = mc.Client(args.server, token=args.token, on_retry=on_retry)
    start = time.monotonic()
    errors = []
    for f in frames:
        label = args.label or Path(f).resolve().parent.name
        errors += denoise_frames([f], client, label=label, priority=args.priority, wait_timeout=args.timeout)
    print(f"denoised {len(frames) - len(errors)} of {len(frames)} frames in {time.monotonic() - start:.1f} s",
          file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
