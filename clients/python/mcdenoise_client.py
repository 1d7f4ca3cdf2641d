"""A small client for the mcdenoise daemon's HTTP API (docs/api.md), standard library only.

Copy this one file next to your farm scripts (Python 3.8 or later, no dependencies):

    from mcdenoise_client import Client

    client = Client("http://mcdenoise:8080", token=os.environ.get("MCDENOISE_TOKEN"))
    job = client.denoise("shot010.0001.exr", "shot010.0001.denoised.exr", label="shot010")
    print(job["timings_ms"]["total"], "ms")

or from a shell:

    python mcdenoise_client.py denoise shot010.0001.exr -o shot010.0001.denoised.exr

What it does about errors:

- 429 (queue full) and 503 (models loading, replica draining) are retried after the
  `Retry-After` the daemon sends, as are refused or reset connections, until
  `retry_timeout` seconds have passed. Submissions carry an idempotency key, so a retried
  submission never creates a second job.
- Other errors raise `DaemonError` with the daemon's status, code and message, e.g. 422
  `invalid_frame` "frame: missing channels: depth.Z (the file has: ...)". They are not
  retried: the same request would fail the same way.
- A job that ends `failed` or `cancelled` raises `JobFailed` with the job (its
  `error.code` and `error.message` say why).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import socket
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from typing import Callable, Dict, Iterable, Optional, Union

__all__ = ["Client", "DaemonError", "JobFailed", "TERMINAL_STATES"]

TERMINAL_STATES = ("succeeded", "failed", "cancelled")
RETRYABLE_STATUS = (429, 503)
_CHUNK = 1 << 20


class DaemonError(Exception):
    """The daemon refused a request: HTTP status, error code and message (docs/api.md)."""

    def __init__(self, status: int, code: str, message: str, retry_after: Optional[float] = None):
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.retry_after = retry_after


class JobFailed(Exception):
    """A job ended `failed` or `cancelled`; `job` is its last state."""

    def __init__(self, job: dict):
        err = job.get("error") or {}
        detail = f"{err.get('code')}: {err.get('message')}" if err else job.get("state")
        super().__init__(f"job {job.get('id')} {job.get('state')}: {detail}")
        self.job = job


def _retry_after(headers) -> Optional[float]:
    value = headers.get("Retry-After") if headers is not None else None
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: the daemon never sends one


class Client:
    """HTTP client of one daemon (or of a Kubernetes Service in front of several).

    `on_retry(reason, wait_s)` is called before each retry wait (for logging);
    `reason` is e.g. "429 queue_full" or "connection refused".
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8080",
        token: Optional[str] = None,
        timeout: float = 60.0,
        retry_timeout: float = 600.0,
        max_retry_wait: float = 60.0,
        on_retry: Optional[Callable[[str, float], None]] = None,
    ):
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.retry_timeout = retry_timeout
        self.max_retry_wait = max_retry_wait
        self.on_retry = on_retry

    # --- plumbing ------------------------------------------------------------------

    def _open(self, method: str, path: str, body=None, headers: Optional[Dict[str, str]] = None):
        """One request; returns the response or raises DaemonError / OSError."""
        h = {"Accept": "application/json"}
        if self.token:
            h["Authorization"] = f"Bearer {self.token}"
        h.update(headers or {})
        req = urllib.request.Request(self.base_url + path, data=body, method=method, headers=h)
        try:
            return urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as e:
            raw = e.read()
            code, message = "http_error", raw.decode("utf-8", "replace").strip() or e.reason
            try:
                err = json.loads(raw)["error"]
                code, message = err["code"], err["message"]
            except (ValueError, KeyError, TypeError):
                pass
            raise DaemonError(e.code, code, message, _retry_after(e.headers)) from None

    def _request(self, method: str, path: str, body_factory=None, headers=None):
        """`_open` with retries of 429/503 and of connection failures until retry_timeout.

        `body_factory` makes a fresh body for every attempt (a file must be re-read)."""
        deadline = time.monotonic() + self.retry_timeout
        attempt = 0
        while True:
            attempt += 1
            body = body_factory() if body_factory else None
            try:
                return self._open(method, path, body, headers)
            except DaemonError as e:
                if e.status not in RETRYABLE_STATUS:
                    raise
                reason, wait = f"{e.status} {e.code}", e.retry_after if e.retry_after is not None else 1.0
                last: Exception = e
            except (ConnectionError, socket.timeout, urllib.error.URLError) as e:
                reason = str(getattr(e, "reason", e))
                wait, last = min(2.0 ** attempt / 4, 10.0), e
            finally:
                if body is not None and hasattr(body, "close"):
                    body.close()
            wait = min(wait, self.max_retry_wait)
            if time.monotonic() + wait > deadline:
                raise last
            if self.on_retry:
                self.on_retry(reason, wait)
            time.sleep(wait)

    def _json(self, method: str, path: str, **kw) -> dict:
        with self._request(method, path, **kw) as resp:
            return json.loads(resp.read())

    # --- the API ---------------------------------------------------------------------

    def ready(self) -> bool:
        """True when /readyz says the daemon accepts jobs."""
        try:
            with self._open("GET", "/readyz"):
                return True
        except (DaemonError, OSError):
            return False

    def submit(
        self,
        frame: Union[str, os.PathLike, bytes],
        *,
        priority: Optional[str] = None,
        label: Optional[str] = None,
        layers: Iterable[str] = (),
        variant: Optional[str] = None,
        deadline_seconds: Optional[int] = None,
        idempotency_key: Optional[str] = None,
    ) -> dict:
        """Submits a frame (a path, streamed from disk, or the EXR's bytes); returns the
        job (state `queued`). Without an idempotency key a random one is used, so retries
        of this call cannot create a second job."""
        query = {"priority": priority, "label": label, "variant": variant, "deadline_seconds": deadline_seconds}
        if layers:
            query["layers"] = ",".join(layers)
        q = urllib.parse.urlencode({k: v for k, v in query.items() if v is not None})
        headers = {
            "Content-Type": "image/x-exr",
            "Idempotency-Key": idempotency_key or f"mcdenoise-client-{uuid.uuid4()}",
        }
        if isinstance(frame, (bytes, bytearray)):
            data = bytes(frame)
            headers["Content-Length"] = str(len(data))
            factory = lambda: data  # noqa: E731
        else:
            path = os.fspath(frame)
            headers["Content-Length"] = str(os.path.getsize(path))
            factory = lambda: open(path, "rb")  # noqa: E731
        return self._json("POST", "/v1/jobs" + (f"?{q}" if q else ""), body_factory=factory, headers=headers)

    def job(self, job_id: str) -> dict:
        return self._json("GET", f"/v1/jobs/{urllib.parse.quote(job_id)}")

    def wait(self, job_id: str, timeout: Optional[float] = None, poll: float = 0.5,
             on_progress: Optional[Callable[[dict], None]] = None) -> dict:
        """Polls until the job is terminal; returns it when it succeeded, raises JobFailed
        otherwise (TimeoutError after `timeout` seconds)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        seen = None
        while True:
            job = self.job(job_id)
            if on_progress and (job["state"], job.get("progress")) != seen:
                seen = (job["state"], job.get("progress"))
                on_progress(job)
            if job["state"] == "succeeded":
                return job
            if job["state"] in TERMINAL_STATES:
                raise JobFailed(job)
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout} s")
            time.sleep(poll)

    def download(self, job_id: str, dest: Union[str, os.PathLike]) -> int:
        """Writes the job's denoised EXR to `dest` atomically (a `.part` file renamed when
        complete); returns its size in bytes."""
        dest = os.fspath(dest)
        part = f"{dest}.part-{os.getpid()}"
        n = 0
        try:
            with self._request("GET", f"/v1/jobs/{urllib.parse.quote(job_id)}/result") as resp, open(part, "wb") as out:
                expected = resp.headers.get("Content-Length")
                while True:
                    chunk = resp.read(_CHUNK)
                    if not chunk:
                        break
                    out.write(chunk)
                    n += len(chunk)
                out.flush()
                os.fsync(out.fileno())
            if expected is not None and int(expected) != n:
                raise OSError(f"result of job {job_id} truncated: {n} of {expected} bytes")
            os.replace(part, dest)
        finally:
            if os.path.exists(part):
                os.remove(part)
        return n

    def cancel(self, job_id: str) -> dict:
        return self._json("POST", f"/v1/jobs/{urllib.parse.quote(job_id)}/cancel")

    def delete(self, job_id: str) -> None:
        with self._request("DELETE", f"/v1/jobs/{urllib.parse.quote(job_id)}"):
            pass

    def denoise(self, frame: Union[str, os.PathLike], dest: Union[str, os.PathLike], *,
                wait_timeout: Optional[float] = None, on_progress=None, **options) -> dict:
        """Submit, wait and download: the denoised frame goes to `dest`; returns the job.
        The idempotency key defaults to one derived from the frame's path, size and
        modification time, so running this again for the same file finds the same job."""
        if "idempotency_key" not in options:
            options["idempotency_key"] = file_key(frame)
        job = self.submit(frame, **options)
        job = self.wait(job["id"], timeout=wait_timeout, on_progress=on_progress)
        self.download(job["id"], dest)
        return job


def file_key(path: Union[str, os.PathLike]) -> str:
    """An idempotency key for a frame file: its absolute path, size and mtime."""
    st = os.stat(path)
    ident = f"{os.path.abspath(path)}\0{st.st_size}\0{st.st_mtime_ns}"
    return "frame-" + hashlib.sha256(ident.encode()).hexdigest()[:32]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="mcdenoise_client.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--server", default=os.environ.get("MCDENOISE_SERVER", "http://127.0.0.1:8080"))
    p.add_argument("--token", default=os.environ.get("MCDENOISE_TOKEN"))
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("denoise", help="submit a frame, wait, write the denoised EXR")
    d.add_argument("frame")
    d.add_argument("-o", "--output", required=True)
    d.add_argument("--priority", choices=["high", "normal", "low"])
    d.add_argument("--label")
    d.add_argument("--layers", help="comma-separated, combinable: diffuse, specular (denoised components), all (every other input channel, unchanged)")
    d.add_argument("--variant", help="auto, or the name of a loaded variant (full, nocov, ...)")
    g = sub.add_parser("job", help="print a job as JSON")
    g.add_argument("id")
    args = p.parse_args(argv)

    def log(reason, wait):
        print(f"mcdenoise: {reason}; retrying in {wait:g} s", file=sys.stderr)

    client = Client(args.server, token=args.token, on_retry=log)
    try:
        if args.cmd == "job":
            print(json.dumps(client.job(args.id), indent=2))
            return 0
        job = client.denoise(args.frame, args.output, priority=args.priority, label=args.label,
                             layers=args.layers.split(",") if args.layers else (), variant=args.variant)
    except (DaemonError, JobFailed, OSError, TimeoutError) as e:
        print(f"mcdenoise: {e}", file=sys.stderr)
        return 1
    print(json.dumps(job, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
