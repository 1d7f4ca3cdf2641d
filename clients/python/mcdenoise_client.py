"""A small client for the mcdenoise daemon's HTTP API (docs/api.md), standard library only.

Install it (`pip install clients/python`, which also installs the `mcdenoise-client`
command), or copy this one file next to your farm scripts (Python 3.8 or later, no
dependencies):

    from mcdenoise_client import Client

    client = Client("http://mcdenoise:8080", token=os.environ.get("MCDENOISE_TOKEN"))
    job = client.denoise("shot010.0001.exr", "shot010.denoised.0001.exr", label="shot010")
    print(job["timings_ms"]["total"], "ms")

    # with a reference frame, the job reports RelMSE, DSSIM, PSNR, SMAPE of input and output
    job = client.submit("shot010.0001.exr", reference="shot010.ref.0001.exr")
    job = client.wait(job["id"])
    print(job["metrics"]["output"]["relmse"])

    for job in client.jobs(state="failed", label="shot010"):   # every page
        print(job["id"], job["error"]["message"])

    for event in client.events(job_id):                        # Server-Sent Events
        print(event.event, event.data)

or from a shell (`python mcdenoise_client.py ...` where it is only copied):

    mcdenoise-client denoise shot010.0001.exr -o out.exr [--reference ref.exr]
    mcdenoise-client jobs --state failed --label shot010
    mcdenoise-client events JOB_ID
    mcdenoise-client job JOB_ID

The server comes from `--server` or MCDENOISE_SERVER, the token from `--token` or
MCDENOISE_TOKEN.

What it does about errors:

- 429 (queue full, client limit) and 503 (models loading, replica draining) are retried
  after the `Retry-After` the daemon sends, as are refused or reset connections, until
  `retry_timeout` seconds have passed. Submissions carry an idempotency key, so a retried
  submission never creates a second job.
- Other errors raise `DaemonError` with the daemon's status, code and message, e.g. 422
  `invalid_frame` "frame: missing channels: depth.Z (the file has: ...)". They are not
  retried: the same request would fail the same way. 401 and 403 (a wrong token) are never
  retried.
- An upload the daemon refuses before reading it (401, 403, 413, 429) is reported as the
  daemon's answer, not as the broken pipe of the unread body: the client stops sending as
  soon as an answer arrives, reads the answer after a failed send, and when even that is
  lost asks the daemon (`GET /v1/jobs?limit=1`) whether the token is refused.
- A job that ends `failed` or `cancelled` raises `JobFailed` with the job (its
  `error.code` and `error.message` say why).
- `wait` follows the job's event stream; when the stream breaks it asks for the job and
  connects again, and after repeated breaks it polls.

Requests honour the `http_proxy` / `https_proxy` / `no_proxy` environment variables, as
urllib does.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import http.client
import json
import os
import select
import socket
import ssl
import sys
import time
import urllib.parse
import urllib.request
import uuid
from typing import Any, Callable, Dict, Iterable, Iterator, List, NamedTuple, Optional, Tuple, Union

__version__ = "0.2.0"
__all__ = ["Client", "DaemonError", "Event", "JobFailed", "TERMINAL_STATES", "file_key", "main"]

TERMINAL_STATES = ("succeeded", "failed", "cancelled")
RETRYABLE_STATUS = (429, 503)
# Refused tokens: never retried, and what a failed upload is checked for.
AUTH_STATUS = (401, 403)
_CHUNK = 1 << 20
# The daemon sends an event-stream keep-alive comment every 15 s.
_EVENTS_READ_TIMEOUT = 45.0
# How long to wait for the answer after a send failed (it has usually arrived already).
_EARLY_ANSWER_TIMEOUT = 5.0
# An event stream open this long before it broke does not count against using streams.
_STREAM_LIVED = 10.0

PathOrBytes = Union[str, "os.PathLike[str]", bytes, bytearray]


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


class Event(NamedTuple):
    """One Server-Sent Event: its name (`queued`, `started`, `progress`, `succeeded`,
    `failed`, `cancelled`) and its data, parsed from JSON (the raw text if it is not)."""

    event: str
    data: Any
    id: Optional[str] = None


def _retry_after(headers) -> Optional[float]:
    value = headers.get("Retry-After") if headers is not None else None
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: the daemon never sends one


def _error_from(resp) -> DaemonError:
    """The DaemonError of an error response (read and closed here)."""
    try:
        raw = resp.read()
    except (OSError, http.client.HTTPException):
        raw = b""
    finally:
        resp.close()
    code, message = "http_error", raw.decode("utf-8", "replace").strip() or (resp.reason or "")
    try:
        err = json.loads(raw)["error"]
        code, message = err["code"], err["message"]
    except (ValueError, KeyError, TypeError):
        pass
    return DaemonError(resp.status, code, message, _retry_after(resp.headers))


def _file_chunks(path: str, size: int) -> Iterator[bytes]:
    """The file's bytes in chunks; fails if it is not `size` bytes long (changed since its
    size was sent as Content-Length)."""
    n = 0
    with open(path, "rb") as f:
        while True:
            chunk = f.read(_CHUNK)
            if not chunk:
                break
            n += len(chunk)
            yield chunk
    if n != size:
        raise OSError(f"{path} changed while it was uploaded ({n} bytes, expected {size})")


def _source(data: PathOrBytes) -> Tuple[int, Callable[[], Iterator[bytes]]]:
    """A frame given as a path (streamed from disk) or bytes: its size, and a factory of
    its chunks (called again for every attempt)."""
    if isinstance(data, (bytes, bytearray)):
        blob = bytes(data)
        return len(blob), lambda: iter((blob,))
    path = os.fspath(data)
    size = os.path.getsize(path)
    return size, lambda: _file_chunks(path, size)


def _multipart(options: dict, parts: List[Tuple[str, PathOrBytes]]) -> Tuple[str, int, Callable[[], Iterator[bytes]]]:
    """A multipart/form-data body: the `options` JSON part first, then each (name, file)
    part, streamed. Returns its content type, exact length and a factory of its chunks."""
    boundary = "mcdenoise-" + uuid.uuid4().hex
    head = (
        f"--{boundary}\r\nContent-Disposition: form-data; name=\"options\"\r\n"
        f"Content-Type: application/json\r\n\r\n{json.dumps(options)}\r\n"
    ).encode()
    pieces: List[Tuple[bytes, int, Callable[[], Iterator[bytes]]]] = []
    for name, data in parts:
        part_head = (
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}.exr\"\r\n"
            f"Content-Type: image/x-exr\r\n\r\n"
        ).encode()
        size, chunks = _source(data)
        pieces.append((part_head, size, chunks))
    tail = f"--{boundary}--\r\n".encode()
    length = len(head) + sum(len(h) + size + 2 for h, size, _ in pieces) + len(tail)

    def body() -> Iterator[bytes]:
        yield head
        for part_head, _, chunks in pieces:
            yield part_head
            yield from chunks()
            yield b"\r\n"
        yield tail

    return f"multipart/form-data; boundary={boundary}", length, body


def _readable(sock) -> bool:
    """Whether the daemon has sent something (its answer) while the body is being sent."""
    return bool(select.select([sock], [], [], 0)[0])


class _SourceFailed(Exception):
    """Reading an upload's source (a frame file) failed; `error` is why."""

    def __init__(self, error: OSError):
        super().__init__(str(error))
        self.error = error


def _close(body) -> None:
    if body is not None and hasattr(body, "close"):
        body.close()


class Client:
    """HTTP client of one daemon (or of a Kubernetes Service in front of several).

    `on_retry(reason, wait_s)` is called before each retry wait (for logging);
    `reason` is e.g. "429 queue_full" or "connection refused". `ssl_context` is used for
    an https:// server (default: the system's CAs).
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8080",
        token: Optional[str] = None,
        timeout: float = 60.0,
        retry_timeout: float = 600.0,
        max_retry_wait: float = 60.0,
        on_retry: Optional[Callable[[str, float], None]] = None,
        ssl_context: Optional[ssl.SSLContext] = None,
    ):
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.retry_timeout = retry_timeout
        self.max_retry_wait = max_retry_wait
        self.on_retry = on_retry
        self.ssl_context = ssl_context
        url = urllib.parse.urlsplit(self.base_url)
        if url.scheme not in ("http", "https") or not url.hostname:
            raise ValueError(f"{base_url}: not an http:// or https:// URL")
        self._url = url

    # --- plumbing ------------------------------------------------------------------

    def _connect(self, timeout: float) -> Tuple[http.client.HTTPConnection, str, Dict[str, str]]:
        """A connection to the daemon (through the environment's proxy, if any), the
        prefix of request targets on it and the headers the proxy needs."""
        url = self._url
        host, port, https = url.hostname, url.port, url.scheme == "https"
        prefix = url.path.rstrip("/")
        proxy, auth = None, {}
        if not urllib.request.proxy_bypass(url.netloc.rpartition("@")[2]):
            proxy = urllib.request.getproxies().get(url.scheme)
        if proxy:
            p = urllib.parse.urlsplit(proxy if "://" in proxy else "http://" + proxy)
            if p.username is not None:
                user_pass = f"{urllib.parse.unquote(p.username)}:{urllib.parse.unquote(p.password or '')}"
                auth["Proxy-Authorization"] = "Basic " + base64.b64encode(user_pass.encode()).decode()
            if https:
                conn = http.client.HTTPSConnection(p.hostname, p.port or 80, timeout=timeout,
                                                   context=self.ssl_context or ssl.create_default_context())
                conn.set_tunnel(host, port or 443, headers=auth)
                auth = {}
            else:
                conn = http.client.HTTPConnection(p.hostname, p.port or 80, timeout=timeout)
                prefix = f"http://{url.netloc.rpartition('@')[2]}{prefix}"
        elif https:
            conn = http.client.HTTPSConnection(host, port, timeout=timeout,
                                               context=self.ssl_context or ssl.create_default_context())
        else:
            conn = http.client.HTTPConnection(host, port, timeout=timeout)
        return conn, prefix, auth

    def _open(self, method: str, path: str, body: Optional[Iterable[bytes]] = None,
              headers: Optional[Dict[str, str]] = None, timeout: Optional[float] = None):
        """One request; returns the response (an http.client.HTTPResponse, 2xx) or raises
        DaemonError (the daemon's answer) or OSError (no answer).

        A body is sent in chunks; when the daemon answers before it is all sent (a refusal:
        401, 413, 429, or the job that already has this idempotency key), sending stops and
        the answer is returned or raised."""
        h = {"Accept": "application/json", "Connection": "close", "User-Agent": f"mcdenoise-client/{__version__}"}
        if self.token:
            h["Authorization"] = f"Bearer {self.token}"
        h.update(headers or {})
        if body is None and method in ("POST", "PUT", "PATCH"):
            h.setdefault("Content-Length", "0")
        conn, prefix, proxy_headers = self._connect(self.timeout if timeout is None else timeout)
        h.update(proxy_headers)
        try:
            conn.putrequest(method, prefix + path, skip_accept_encoding=True)
            for k, v in h.items():
                conn.putheader(k, v)
            conn.endheaders()
            if body is None:
                resp = conn.getresponse()
            else:
                failed = self._send_body(conn, body)
                if failed is None:
                    try:
                        resp = conn.getresponse()
                    except (ConnectionError, socket.timeout) as e:
                        failed, resp = e, None
                else:
                    resp = self._answer_after_failed_send(conn, failed)
                if resp is None:
                    # The upload ended without an answer (lost with the connection, or
                    # never sent): was it the token? If not, the connection error stands.
                    self._check_auth(failed)
                    raise failed
        except http.client.HTTPException as e:  # RemoteDisconnected is also a ConnectionError
            conn.close()
            if isinstance(e, OSError):
                raise
            raise ConnectionError(f"bad answer from {self.base_url}: {e!r}") from e
        except BaseException:
            conn.close()
            raise
        if resp.status >= 400:
            conn.close()
            raise _error_from(resp)
        return resp

    @staticmethod
    def _send_body(conn: http.client.HTTPConnection, body: Iterable[bytes]) -> Optional[OSError]:
        """Sends the body; stops early when the daemon has already answered. Returns the
        error that stopped the send, None when sent (or answered). A failure to read the
        body's source (the frame file) raises _SourceFailed."""
        sock = conn.sock
        chunks = iter(body)
        try:
            while True:
                try:
                    chunk = next(chunks)
                except StopIteration:
                    return None
                except OSError as e:
                    raise _SourceFailed(e) from e
                if sock is not None and _readable(sock):
                    return None  # an early answer (the daemon reads no more of the body)
                try:
                    conn.send(chunk)
                except OSError as e:
                    return e
        finally:
            _close(chunks)

    @staticmethod
    def _answer_after_failed_send(conn: http.client.HTTPConnection, err: OSError):
        """The daemon's answer after sending the body failed (it answered and closed
        before reading it all), if it can still be read; else None."""
        try:
            if conn.sock is not None:
                conn.sock.settimeout(_EARLY_ANSWER_TIMEOUT)
            return conn.getresponse()
        except (OSError, http.client.HTTPException):
            return None

    def _check_auth(self, cause: OSError) -> None:
        """After an upload failed without an answer: raises the daemon's 401/403 when it
        refuses the token (a cheap authenticated request), else returns."""
        try:
            resp = self._open("GET", "/v1/jobs?limit=1")
        except DaemonError as e:
            if e.status in AUTH_STATUS:
                raise e from cause
            return
        except OSError:
            return
        resp.close()

    def _request(self, method: str, path: str, body_factory=None, headers=None, timeout=None):
        """`_open` with retries of 429/503 and of connection failures until retry_timeout.

        `body_factory` makes a fresh body for every attempt (a file must be re-read)."""
        deadline = time.monotonic() + self.retry_timeout
        attempt = 0
        while True:
            attempt += 1
            body = body_factory() if body_factory else None
            try:
                return self._open(method, path, body, headers, timeout)
            except DaemonError as e:
                if e.status not in RETRYABLE_STATUS:
                    raise
                reason, wait = f"{e.status} {e.code}", e.retry_after if e.retry_after is not None else 1.0
                last: Exception = e
            except _SourceFailed as e:
                raise e.error from None  # reading the frame failed: not the daemon's doing
            except OSError as e:
                if isinstance(e, ssl.SSLCertVerificationError):
                    raise  # the same certificate fails the same way
                reason = str(e) or type(e).__name__
                wait, last = min(2.0 ** attempt / 4, 10.0), e
            finally:
                _close(body)
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
        frame: PathOrBytes,
        *,
        reference: Optional[PathOrBytes] = None,
        priority: Optional[str] = None,
        label: Optional[str] = None,
        layers: Iterable[str] = (),
        variant: Optional[str] = None,
        deadline_seconds: Optional[int] = None,
        idempotency_key: Optional[str] = None,
        **options: Any,
    ) -> dict:
        """Submits a frame (a path, streamed from disk, or the EXR's bytes); returns the
        job (state `queued`). With a `reference` (path or bytes) the upload is
        multipart/form-data (`options`, `frame`, `reference` parts) and the finished job
        reports `metrics` of the input and output against it. Other keyword options
        (`fireflies`, `firefly_strength`, ...) are passed as the API names them. Without an
        idempotency key a random one is used, so retries of this call cannot create a
        second job."""
        key = idempotency_key or f"mcdenoise-client-{uuid.uuid4()}"
        opts: Dict[str, Any] = {"priority": priority, "label": label, "variant": variant,
                                "deadline_seconds": deadline_seconds, **options}
        opts = {k: v for k, v in opts.items() if v is not None}
        layers = list(layers)
        headers = {"Idempotency-Key": key}
        if reference is not None:
            if layers:
                opts["layers"] = layers
            opts["idempotency_key"] = key
            ctype, length, factory = _multipart(opts, [("frame", frame), ("reference", reference)])
            headers.update({"Content-Type": ctype, "Content-Length": str(length)})
            return self._json("POST", "/v1/jobs", body_factory=factory, headers=headers)
        if layers:
            opts["layers"] = ",".join(layers)
        q = urllib.parse.urlencode(opts)
        length, factory = _source(frame)
        headers.update({"Content-Type": "image/x-exr", "Content-Length": str(length)})
        return self._json("POST", "/v1/jobs" + (f"?{q}" if q else ""), body_factory=factory, headers=headers)

    def job(self, job_id: str) -> dict:
        return self._json("GET", f"/v1/jobs/{urllib.parse.quote(job_id, safe='')}")

    def jobs(self, *, state: Optional[str] = None, priority: Optional[str] = None,
             label: Optional[str] = None, page_size: int = 100) -> Iterator[dict]:
        """Every job this token may see (all of them for an operator token), in submission
        order, optionally filtered; fetched `page_size` (1 to 1000) at a time, following
        `next_page_token` across all pages."""
        query: Dict[str, Any] = {"state": state, "priority": priority, "label": label, "limit": page_size}
        query = {k: v for k, v in query.items() if v is not None}
        while True:
            page = self._json("GET", "/v1/jobs?" + urllib.parse.urlencode(query))
            yield from page.get("jobs", [])
            token = page.get("next_page_token")
            if not token:
                return
            query["page_token"] = token

    def events(self, job_id: str, *, read_timeout: Optional[float] = None) -> Iterator[Event]:
        """The job's Server-Sent Events, parsed: its current state first, then every
        change, ending after the terminal event (`succeeded`, `failed`, `cancelled`).
        Opening the stream is retried like other requests; a stream that breaks raises
        OSError (`wait` connects again). `read_timeout` (default 45 s; the daemon sends a
        keep-alive every 15 s) bounds the silence before the stream counts as broken."""
        path = f"/v1/jobs/{urllib.parse.quote(job_id, safe='')}/events"
        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        rt = read_timeout if read_timeout is not None else max(self.timeout, _EVENTS_READ_TIMEOUT)
        resp = self._request("GET", path, headers=headers, timeout=rt)
        try:
            yield from _parse_sse(resp)
        except http.client.HTTPException as e:
            if isinstance(e, OSError):
                raise
            raise ConnectionError(f"the event stream of job {job_id} broke: {e!r}") from e
        finally:
            resp.close()

    def wait(self, job_id: str, timeout: Optional[float] = None, poll: float = 0.5,
             on_progress: Optional[Callable[[dict], None]] = None, use_events: bool = True) -> dict:
        """Waits until the job is terminal; returns it when it succeeded, raises JobFailed
        otherwise (TimeoutError after `timeout` seconds; DaemonError 404 when the job is
        gone). Follows the job's event stream; when the stream breaks, asks for the job
        and connects again; after three streams in a row that broke within seconds it polls
        every `poll` seconds instead (as it does with `use_events=False`). `on_progress(job)` gets the
        job (as far as the events tell: `state`, `progress`) whenever its state or
        progress changes."""
        deadline = None if timeout is None else time.monotonic() + timeout
        job: dict = {"id": job_id}
        seen: List[Any] = [None]

        def report(j: dict) -> None:
            key = (j.get("state"), json.dumps(j.get("progress"), sort_keys=True))
            if on_progress and key != seen[0]:
                seen[0] = key
                on_progress(j)

        def finished(j: dict) -> Optional[dict]:
            if j.get("state") == "succeeded":
                return j
            if j.get("state") in TERMINAL_STATES:
                raise JobFailed(j)
            return None

        def late() -> bool:
            return deadline is not None and time.monotonic() >= deadline

        def timed_out() -> TimeoutError:
            return TimeoutError(f"job {job_id} still {job.get('state', 'unknown')} after {timeout} s")

        breaks = 0  # event streams in a row that broke or ended early without the end
        while True:
            if use_events and breaks < 3:
                rt = max(self.timeout, _EVENTS_READ_TIMEOUT)
                if deadline is not None:
                    rt = max(0.05, min(rt, deadline - time.monotonic()))
                opened, over_time = time.monotonic(), False
                try:
                    for ev in self.events(job_id, read_timeout=rt):
                        job = _merge_event(job, ev)
                        report(job)
                        if ev.event in TERMINAL_STATES:
                            break
                        if late():
                            over_time = True
                            break
                except OSError:
                    if late():
                        raise timed_out() from None
                if over_time:
                    raise timed_out()
                done = finished(job)
                if done is not None:
                    return done
                # The stream broke, or ended without the terminal event (the job was
                # deleted, or the daemon is stopping). One that lasted a while is no sign
                # that streams do not work here (a proxy cutting long responses).
                breaks = 0 if time.monotonic() - opened > _STREAM_LIVED else breaks + 1
            # Ask for the job (retried; 404 when it is gone), then connect again or poll.
            job = self.job(job_id)
            report(job)
            done = finished(job)
            if done is not None:
                return done
            if late():
                raise timed_out()
            time.sleep(poll if not use_events or breaks >= 3 else min(poll * (1 + breaks), 5.0))

    def download(self, job_id: str, dest: Union[str, os.PathLike]) -> int:
        """Writes the job's denoised EXR to `dest` atomically (a `.part` file renamed when
        complete); returns its size in bytes."""
        dest = os.fspath(dest)
        part = f"{dest}.part-{os.getpid()}"
        n = 0
        try:
            with self._request("GET", f"/v1/jobs/{urllib.parse.quote(job_id, safe='')}/result") as resp, \
                    open(part, "wb") as out:
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
        return self._json("POST", f"/v1/jobs/{urllib.parse.quote(job_id, safe='')}/cancel")

    def delete(self, job_id: str) -> None:
        with self._request("DELETE", f"/v1/jobs/{urllib.parse.quote(job_id, safe='')}"):
            pass

    def denoise(self, frame: Union[str, os.PathLike], dest: Union[str, os.PathLike], *,
                reference: Optional[Union[str, os.PathLike]] = None,
                wait_timeout: Optional[float] = None, on_progress=None, **options) -> dict:
        """Submit, wait and download: the denoised frame goes to `dest`; returns the job.
        The idempotency key defaults to one derived from the frame's (and the reference's)
        path, size and modification time, so running this again for the same file finds
        the same job."""
        if "idempotency_key" not in options:
            options["idempotency_key"] = file_key(frame, *([reference] if reference is not None else []))
        job = self.submit(frame, reference=reference, **options)
        job = self.wait(job["id"], timeout=wait_timeout, on_progress=on_progress)
        self.download(job["id"], dest)
        return job


def _parse_sse(resp) -> Iterator[Event]:
    """Server-Sent Events from a response (text/event-stream), until it ends."""
    name, data, last_id = "", [], None
    while True:
        raw = resp.readline()
        if not raw:
            return
        line = raw.decode("utf-8", "replace").rstrip("\r\n")
        if not line:
            if data:
                text = "\n".join(data)
                try:
                    value = json.loads(text)
                except ValueError:
                    value = text
                yield Event(name or "message", value, last_id)
            name, data = "", []
            continue
        if line.startswith(":"):
            continue  # a comment: the keep-alive
        field, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if field == "event":
            name = value
        elif field == "data":
            data.append(value)
        elif field == "id":
            last_id = value


def _merge_event(job: dict, ev: Event) -> dict:
    """The job as far as an event tells: the whole job for `queued` and the terminal
    events, the state and progress for `started` and `progress`."""
    data = ev.data if isinstance(ev.data, dict) else {}
    if ev.event in ("queued",) + TERMINAL_STATES and "state" in data:
        return dict(data)
    if ev.event == "started":
        return {**job, "state": "running", "attempts": data.get("attempt", job.get("attempts"))}
    if ev.event == "progress":
        return {**job, "state": "running",
                "progress": {"tiles_done": data.get("tiles_done"), "tiles_total": data.get("tiles_total")}}
    return job


def file_key(path: Union[str, os.PathLike], *more: Union[str, os.PathLike]) -> str:
    """An idempotency key for a frame file (and, e.g., its reference): their absolute
    paths, sizes and mtimes."""
    ident = []
    for p in (path, *more):
        st = os.stat(p)
        ident.append(f"{os.path.abspath(p)}\0{st.st_size}\0{st.st_mtime_ns}")
    return "frame-" + hashlib.sha256("\0\0".join(ident).encode()).hexdigest()[:32]


def _print_job_line(job: dict) -> None:
    prog = job.get("progress") or {}
    err = (job.get("error") or {}).get("message") or ""
    print("\t".join([job.get("id", ""), job.get("state", ""), job.get("priority") or "",
                     job.get("label") or "-", f"{prog.get('tiles_done', 0)}/{prog.get('tiles_total', 0)}", err]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--server", default=os.environ.get("MCDENOISE_SERVER", "http://127.0.0.1:8080"))
    p.add_argument("--token", default=os.environ.get("MCDENOISE_TOKEN"))
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="cmd")
    sub.required = True
    d = sub.add_parser("denoise", help="submit a frame, wait, write the denoised EXR")
    d.add_argument("frame")
    d.add_argument("-o", "--output", required=True)
    d.add_argument("--reference", help="a reference frame: the job reports metrics against it")
    d.add_argument("--priority", choices=["high", "normal", "low"])
    d.add_argument("--label")
    d.add_argument("--layers", help="comma-separated, combinable: diffuse, specular (denoised components), all (every other input channel, unchanged)")
    d.add_argument("--variant", help="auto, or the name of a loaded variant (full, nocov, ...)")
    d.add_argument("--timeout", type=float, help="seconds to wait for the job")
    g = sub.add_parser("job", help="print a job as JSON")
    g.add_argument("id")
    ls = sub.add_parser("jobs", help="list jobs (every page): id, state, priority, label, tiles, error")
    ls.add_argument("--state", choices=["queued", "running"] + list(TERMINAL_STATES))
    ls.add_argument("--priority", choices=["high", "normal", "low"])
    ls.add_argument("--label")
    ls.add_argument("--page-size", type=int, default=100)
    ls.add_argument("--json", action="store_true", help="one job as JSON per line")
    e = sub.add_parser("events", help="print a job's events until it ends (exit 1 unless it succeeded)")
    e.add_argument("id")
    c = sub.add_parser("cancel", help="cancel a job")
    c.add_argument("id")
    x = sub.add_parser("delete", help="delete a job and its result")
    x.add_argument("id")
    args = p.parse_args(argv)

    def log(reason, wait):
        print(f"mcdenoise: {reason}; retrying in {wait:g} s", file=sys.stderr)

    client = Client(args.server, token=args.token, on_retry=log)
    try:
        if args.cmd == "job":
            print(json.dumps(client.job(args.id), indent=2))
        elif args.cmd == "jobs":
            for job in client.jobs(state=args.state, priority=args.priority, label=args.label,
                                   page_size=args.page_size):
                if args.json:
                    print(json.dumps(job))
                else:
                    _print_job_line(job)
        elif args.cmd == "events":
            last = None
            for ev in client.events(args.id):
                print(f"{ev.event} {json.dumps(ev.data)}", flush=True)
                last = ev.event
            return 0 if last == "succeeded" else 1
        elif args.cmd == "cancel":
            print(json.dumps(client.cancel(args.id), indent=2))
        elif args.cmd == "delete":
            client.delete(args.id)
        else:
            job = client.denoise(args.frame, args.output, reference=args.reference, priority=args.priority,
                                 label=args.label, layers=args.layers.split(",") if args.layers else (),
                                 variant=args.variant, wait_timeout=args.timeout)
            print(json.dumps(job, indent=2))
    except (DaemonError, JobFailed, OSError, TimeoutError) as e:
        print(f"mcdenoise: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
