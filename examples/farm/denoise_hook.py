"""Post-render hook: denoise rendered frames with mcdenoise and write each result next to its frame.

    shots/sh010/beauty.0001.exr  ->  shots/sh010/beauty.denoised.0001.exr

The frame must be in the layout of docs/frame-layout.md (diffuse, specular, albedo,
normal, depth, or the Blender Cycles passes they derive from; variances and covariance
optional). A frame that is not is refused by the daemon with the missing channels named;
the hook reports that and fails the frame.

As a farm command (exit status 0 when every frame was denoised, 1 otherwise, naming each
frame that failed, so the farm marks the task failed and can retry it):

    python denoise_hook.py --server http://mcdenoise.farm:8080 beauty.0001.exr [...]
    python denoise_hook.py --pattern 'shots/sh010/beauty.####.exr' --frames 1-240

A range is submitted as a whole: up to `--concurrency` frames (default 16) are in flight at
once (submitted and not yet downloaded), the next one is submitted as soon as one is done,
so the daemon's queue always holds the range's next frames. Each job is followed through
its event stream and its result downloaded as soon as it has succeeded. A refused token
(401, 403) stops the run: the frames not yet submitted are reported as not submitted.

Output names: `--output-pattern`, a path relative to the frame's directory (or absolute;
missing directories are created), with the fields

    {stem}   the file name before the frame number and its separator   beauty
    {sep}    that separator (`.`, `_` or `-`; `.` when there is none)   .
    {frame}  the frame number as written, with its padding               0001
    {ext}    the extension, without the dot                              exr
    {name}   the whole file name without the extension                   beauty.0001

(the values for `beauty.0001.exr`). The default, `{stem}{sep}denoised{sep}{frame}.{ext}`,
puts the suffix before the frame number, so the results are a sequence of their own:
`beauty.0001.exr` -> `beauty.denoised.0001.exr`, `shot_0001.exr` -> `shot_denoised_0001.exr`.
A name without a frame number (`beauty.exr`) has an empty `{frame}`, and the separator
before it is dropped (`beauty.denoised.exr`); one that is only a frame number (`0001.exr`,
Blender's default) has an empty `{stem}`, and the separator after it is dropped
(`denoised.0001.exr`). Other examples: `{name}.denoised.{ext}` (`beauty.0001.denoised.exr`,
the name before version 0.2), `denoised/{stem}.{frame}.{ext}`,
`/mnt/comp/sh010/{stem}_dn.{frame}.{ext}`. A pattern that names the frame itself is refused.

(OpenCue: a layer running this with `--frames #IFRAME#-#IFRAME#` that depends frame by
frame on the render layer, or once over the whole range after it; Deadline: the job's
post-task script calling `denoise_frames`; Blender: examples/blender/denoise_handler.py.)
The token comes from `--token` or MCDENOISE_TOKEN, the server from `--server` or
MCDENOISE_SERVER, as for `mcdenoise submit`.

From Python: `denoise_frame(path, client)` for one frame (submit, wait, download),
`denoise_frames(paths, client, concurrency=16)` for many. Running the hook twice on the same
file finds the same job (the idempotency key is derived from the file's path, size and
mtime) unless the daemon has forgotten it; a job lost while waiting (a 404: the replica
that held it was removed, or its result expired) is submitted again, up to `resubmits`
times.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Iterable, List, Optional

try:
    import mcdenoise_client as mc
except ImportError:  # run from the repository: the client lives in clients/python
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "clients" / "python"))
    import mcdenoise_client as mc

DEFAULT_OUTPUT_PATTERN = "{stem}{sep}denoised{sep}{frame}.{ext}"
DEFAULT_CONCURRENCY = 16
# What a frame can fail with (the client converts other transport errors to OSError).
FRAME_ERRORS = (mc.DaemonError, mc.JobFailed, OSError, TimeoutError, ValueError)

_NUMBERED = re.compile(r"(?:(?P<stem>.*)(?P<sep>[._-]))?(?P<frame>\d+)")
_EMPTY_STEM, _EMPTY_FRAME = "\0stem\0", "\0frame\0"


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def output_path(frame: os.PathLike | str, pattern: str = DEFAULT_OUTPUT_PATTERN) -> Path:
    """Where the denoised frame goes: `pattern` (see the module's docstring) filled from
    the frame's name, relative to the frame's directory."""
    p = Path(frame)
    if p.suffix.lower() != ".exr":
        raise ValueError(f"{p}: not an .exr file")
    name = p.name[: -len(p.suffix)]
    m = _NUMBERED.fullmatch(name)
    stem, sep, number = (m.group("stem") or "", m.group("sep") or ".", m.group("frame")) if m else (name, ".", "")
    try:
        text = pattern.format(stem=stem or _EMPTY_STEM, sep=sep, frame=number or _EMPTY_FRAME,
                              ext=p.suffix[1:], name=name)
    except (KeyError, IndexError, ValueError) as e:
        raise ValueError(f"output pattern {pattern!r}: {e!r} (fields: stem, sep, frame, ext, name)") from None
    # An empty field takes its separator with it: `beauty.denoised..exr` would be no one's intent.
    text = re.sub(rf"[._-]?{_EMPTY_FRAME}|{_EMPTY_FRAME}[._-]?", "", text)
    text = re.sub(rf"{_EMPTY_STEM}[._-]?|[._-]?{_EMPTY_STEM}", "", text)
    out = p.parent / text
    if not text or text.endswith(("/", os.sep)):
        raise ValueError(f"output pattern {pattern!r} gives no file name for {p}")
    if os.path.abspath(out) == os.path.abspath(p):
        raise ValueError(f"output pattern {pattern!r} would overwrite the rendered frame {p}")
    return out


def submit_frame(frame: os.PathLike | str, client: mc.Client, *, label: Optional[str] = None,
                 priority: Optional[str] = None, log: Callable[[str], None] = _stderr) -> dict:
    """Submits one frame (idempotently: the key is derived from the file); returns its job."""
    frame = Path(frame)
    job = client.submit(frame, label=label, priority=priority, idempotency_key=mc.file_key(frame))
    log(f"{frame.name}: job {job['id']} {job['state']}")
    return job


def finish_frame(frame: os.PathLike | str, job: dict, client: mc.Client, *, out: os.PathLike | str,
                 label: Optional[str] = None, priority: Optional[str] = None,
                 wait_timeout: Optional[float] = None, resubmits: int = 2,
                 log: Callable[[str], None] = _stderr) -> dict:
    """Waits for a submitted frame's job (its events) and downloads the result to `out`;
    submits the frame again when the job is gone (404), up to `resubmits` times. Returns the
    finished job; raises `mc.DaemonError`, `mc.JobFailed`, `OSError` or `TimeoutError`."""
    frame, out = Path(frame), Path(out)
    for attempt in range(resubmits + 1):
        if attempt:
            job = submit_frame(frame, client, label=label, priority=priority, log=log)
        try:
            job = client.wait(job["id"], timeout=wait_timeout)
            out.parent.mkdir(parents=True, exist_ok=True)
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


def denoise_frame(
    frame: os.PathLike | str,
    client: mc.Client,
    *,
    out: os.PathLike | str | None = None,
    output_pattern: str = DEFAULT_OUTPUT_PATTERN,
    label: Optional[str] = None,
    priority: Optional[str] = None,
    wait_timeout: Optional[float] = None,
    resubmits: int = 2,
    log: Callable[[str], None] = _stderr,
) -> dict:
    """Submits `frame`, waits for its job and writes the denoised EXR to `out` (default:
    `output_path(frame, output_pattern)`). Returns the finished job; raises
    `mc.DaemonError` (refused, e.g. 422 with the missing channels), `mc.JobFailed` or
    `OSError`."""
    out = Path(out) if out is not None else output_path(frame, output_pattern)
    job = submit_frame(frame, client, label=label, priority=priority, log=log)
    return finish_frame(frame, job, client, out=out, label=label, priority=priority,
                        wait_timeout=wait_timeout, resubmits=resubmits, log=log)


def denoise_frames(
    frames: Iterable[os.PathLike | str],
    client: mc.Client,
    *,
    concurrency: int = DEFAULT_CONCURRENCY,
    output_pattern: str = DEFAULT_OUTPUT_PATTERN,
    label: Optional[str] | Callable[[Path], Optional[str]] = None,
    priority: Optional[str] = None,
    wait_timeout: Optional[float] = None,
    resubmits: int = 2,
    log: Callable[[str], None] = _stderr,
) -> List[str]:
    """Denoises many frames: submits them in order with at most `concurrency` in flight
    (submitted, not yet written), waits for each through its events on a thread of its own
    and writes each result as soon as its job has succeeded. Returns one message per frame
    that failed, naming it (empty when all succeeded); one bad frame does not stop the
    others, a refused token (401, 403) stops the submissions. `label` is a label or a
    function of the frame's path."""
    if concurrency < 1:
        raise ValueError("concurrency must be at least 1")
    frames = list(dict.fromkeys(Path(f) for f in frames))  # each once, in order
    errors: dict = {}  # frame -> message
    lock = threading.Lock()
    slots = threading.Semaphore(concurrency)

    def fail(frame: Path, e: object) -> None:
        msg = f"{frame}: {e}"
        log(msg)
        with lock:
            errors[frame] = msg

    # Each frame's output, and no two frames writing the same file (a pattern without {frame}).
    outputs: dict = {}
    writers: dict = {}
    for frame in frames:
        try:
            outputs[frame] = output_path(frame, output_pattern)
        except ValueError as e:
            outputs[frame] = e
            continue
        writers.setdefault(os.path.abspath(outputs[frame]), []).append(frame)
    for frame in frames:
        out = outputs[frame]
        if isinstance(out, Path) and len(writers[os.path.abspath(out)]) > 1:
            others = ", ".join(str(f) for f in writers[os.path.abspath(out)] if f != frame)
            outputs[frame] = ValueError(f"its output {out} is also the output of {others}")

    def finish(frame: Path, job: dict, out: Path, lbl: Optional[str]) -> None:
        try:
            finish_frame(frame, job, client, out=out, label=lbl, priority=priority,
                         wait_timeout=wait_timeout, resubmits=resubmits, log=log)
        except FRAME_ERRORS as e:
            fail(frame, e)
        except BaseException as e:  # a bug: still name the frame, and release its slot
            fail(frame, e)
            raise
        finally:
            slots.release()

    with ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="denoise") as pool:
        for i, frame in enumerate(frames):
            slots.acquire()
            lbl = label(frame) if callable(label) else label
            try:
                out = outputs[frame]
                if isinstance(out, Exception):
                    raise out
                job = submit_frame(frame, client, label=lbl, priority=priority, log=log)
            except FRAME_ERRORS as e:
                slots.release()
                fail(frame, e)
                if isinstance(e, mc.DaemonError) and e.status in mc.AUTH_STATUS:
                    for rest in frames[i + 1:]:
                        fail(rest, f"not submitted: {e}")
                    break
                continue
            pool.submit(finish, frame, job, out, lbl)
    return [errors[f] for f in frames if f in errors]


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
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="Output pattern fields: {stem} {sep} {frame} {ext} {name}; "
                                       "see the module's docstring.")
    p.add_argument("frames", nargs="*", help="rendered EXR frames")
    p.add_argument("--pattern", help="frame path with #### for the number (with --frames)")
    p.add_argument("--frames", dest="range", help="frame numbers for --pattern, e.g. 1-240 or 1-10,20")
    p.add_argument("--output-pattern", default=DEFAULT_OUTPUT_PATTERN,
                   help="name of the denoised frame, relative to the frame's directory "
                        f"(default {DEFAULT_OUTPUT_PATTERN.replace('%', '%%')})")
    p.add_argument("--concurrency", type=int, default=DEFAULT_CONCURRENCY,
                   help=f"frames in flight at once (default {DEFAULT_CONCURRENCY})")
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
        try:
            frames += expand_pattern(args.pattern, args.range)
        except ValueError as e:
            p.error(str(e))
    frames = list(dict.fromkeys(frames))
    if not frames:
        p.error("no frames given")
    if args.concurrency < 1:
        p.error("--concurrency must be at least 1")
    try:
        output_path("x/beauty.0001.exr", args.output_pattern)
    except ValueError as e:
        p.error(str(e))

    def on_retry(reason, wait):
        _stderr(f"mcdenoise: {reason}; retrying in {wait:g} s")

    client = mc.Client(args.server, token=args.token, on_retry=on_retry)
    start = time.monotonic()
    errors = denoise_frames(frames, client, concurrency=args.concurrency, output_pattern=args.output_pattern,
                            label=args.label or (lambda f: Path(f).resolve().parent.name),
                            priority=args.priority, wait_timeout=args.timeout)
    _stderr(f"denoised {len(frames) - len(errors)} of {len(frames)} frames in {time.monotonic() - start:.1f} s")
    if errors:
        _stderr(f"{len(errors)} failed:")
        for msg in errors:
            _stderr(f"  {msg}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
