"""Inputs on a web server (``http://``, ``https://``): the cloud-optimized formats read where they are published.

COPC files and EPTs are published on web servers and object stores (S3, Azure, GCS over https) precisely so that
a reader can fetch one region without the rest: a COPC file's header, hierarchy pages and point chunks are byte
ranges of one file (HTTP ``Range`` requests), an EPT's are small files of their own. This module is the transport:
:class:`RemoteFile`, a read-only seekable file over range requests, for laspy's readers; :func:`fetch` for whole
small files and ranges; :func:`validators` for what identifies a version of a file on the server (size, ``ETag``,
``Last-Modified``), which keys the index cache and a job's resume. Every failure is one
:class:`~tiled_gridpull.errors.InputError` line naming the URL without its query (:func:`shown`: a pre-signed
URL's query is a credential, so it is never written to a message, a manifest or a sidecar).

Only the standard library is used (``urllib``), so remote inputs need no extra package. Only GET requests are
sent (a URL pre-signed for GET refuses HEAD); transient failures (a dropped connection, a timeout, HTTP 5xx or
429, a transfer slower than :data:`MIN_TRANSFER_RATE` on average) are retried :data:`ATTEMPTS` times with a growing
pause.
"""

from __future__ import annotations

import http.client
import io
import posixpath
import re
import time
import urllib.error
import urllib.parse
import urllib.request
from collections import OrderedDict

from ..errors import InputError

__all__ = ["is_url", "url_name", "url_join", "shown", "resolved", "recorded", "RemoteFile", "fetch", "validators",
           "TIMEOUT_S", "ATTEMPTS", "MIN_TRANSFER_RATE", "RATE_GRACE_S", "MIN_RATE_ENV", "min_transfer_rate"]

#: seconds a request may wait for the server before it counts as a failed attempt
TIMEOUT_S = 60.0
#: attempts at a request that failed transiently (connection, timeout, HTTP 5xx or 429)
ATTEMPTS = 4
#: bytes per second a transfer must average, counted from the start of its request once it has run
#: :data:`RATE_GRACE_S` seconds: a server that trickles bytes (10 a second) never trips the per-read timeout and
#: would keep a job running indefinitely. ``TILED_GRIDPULL_MIN_TRANSFER_RATE`` in the environment overrides it
#: (the command line's ``--min-transfer-rate`` sets it, so a local cluster's workers inherit it); 0 turns it off.
MIN_TRANSFER_RATE = 1024
#: seconds a transfer runs before its rate counts (connection set-up and a slow start are not a trickle)
RATE_GRACE_S = 10.0
#: the environment variable that sets the minimum transfer rate (bytes per second) in this process and its workers
MIN_RATE_ENV = "TILED_GRIDPULL_MIN_TRANSFER_RATE"
#: bytes a small read fetches at once (a LAS header is read field by field: one request each would be hundreds)
BLOCK = 1 << 16
#: blocks kept per open file
CACHED_BLOCKS = 16


def is_url(source) -> bool:
    """Whether ``source`` is an ``http://`` or ``https://`` URL (anything else is a local path)."""
    return isinstance(source, str) and source[:8].lower().startswith(("http://", "https://"))


def _split(url: str) -> urllib.parse.SplitResult:
    try:
        return urllib.parse.urlsplit(url)
    except ValueError as exc:
        raise InputError(f"{shown(url)}: not a valid URL ({exc})") from None


def url_name(url: str) -> str:
    """The last segment of the URL's path, without query or fragment (``.../a/ept.json?sig=..`` -> ``ept.json``)."""
    return posixpath.basename(urllib.parse.unquote(_split(url).path))


def url_join(url: str, *parts: str) -> str:
    """``parts`` appended to the directory of ``url``'s path, keeping its query (servers that sign a prefix, e.g.
    a container's SAS token, accept the same query for every file under it)."""
    s = _split(url)
    path = posixpath.join(posixpath.dirname(s.path), *parts)
    return urllib.parse.urlunsplit((s.scheme, s.netloc, path, s.query, ""))


def shown(source) -> str:
    """An input as messages and records show it: a URL without its query (a signature, a token) and user info;
    a path as given."""
    if not is_url(source):
        return str(source)
    head, _, query = source.partition("?")
    head = re.sub(r"^(https?://)[^/@]*@", r"\1", head.partition("#")[0], flags=re.IGNORECASE)
    return head + ("?..." if query else "")


def resolved(source) -> str:
    """An input as handed to workers: a URL as given, a path made absolute (workers of an external cluster do
    not share the driver's working directory)."""
    from pathlib import Path

    return source if is_url(source) else str(Path(source).resolve())


def recorded(source) -> str:
    """An input as a manifest or sidecar records it: :func:`resolved`, then :func:`shown`."""
    return shown(resolved(source))


_TRANSIENT_STATUS = {429, 500, 502, 503, 504}


def min_transfer_rate() -> float:
    """The minimum transfer rate in force, bytes per second (0: none): ``TILED_GRIDPULL_MIN_TRANSFER_RATE`` when
    set, else :data:`MIN_TRANSFER_RATE`."""
    import os

    text = os.environ.get(MIN_RATE_ENV, "").strip()
    if not text:
        return float(MIN_TRANSFER_RATE)
    try:
        rate = float(text)
    except ValueError:
        rate = -1.0
    if not (rate >= 0 and rate != float("inf")):
        from ..errors import ConfigError

        raise ConfigError(f"{MIN_RATE_ENV}={text!r}: expected bytes per second, 0 or more")
    return rate


class _Trickle(Exception):
    """A transfer below the minimum rate (raised inside a request: counted as a failed attempt)."""


class _Watch:
    """The minimum transfer rate, enforced on a whole request: connection, headers and body.

    A server that trickles its status line, its headers or a chunk-size line holds a single blocking read (in
    ``http.client``) for as long as bytes keep coming: the socket's timeout never fires and a check between body
    reads is never reached. A watchdog thread therefore holds the request to the rule of :func:`_read_body` (after
    :data:`RATE_GRACE_S` seconds from the request's start, the body bytes received must average ``rate`` bytes per
    second): it sleeps until the moment the bytes counted so far stop being enough, and then shuts the request's
    socket down, which ends any read blocked on it. The request then counts as a failed attempt (:class:`_Trickle`).

    Parameters
    ----------
    rate : float
        Bytes per second (0: no watchdog; the socket's timeout alone bounds each read).
    """

    def __init__(self, rate: float):
        import threading

        self.rate = rate
        self.start = time.monotonic()
        self.got = 0
        self.tripped: str | None = None
        self._sock = None
        self._lock = threading.Lock()
        self._done = threading.Event()
        if rate > 0:
            threading.Thread(target=self._run, name="tiled-gridpull-transfer-watch", daemon=True).start()

    def attach(self, sock):
        """Keep a duplicate of the request's socket, fresh from its connection (TLS then takes the socket over and
        detaches the object this one was), to shut the connection down through; a tripped request's at once."""
        with self._lock:
            self._close()
            self._sock = sock.dup()
            if self.tripped:
                self._shut(self._sock)
        return sock

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    @staticmethod
    def _shut(sock) -> None:
        import socket

        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def _run(self) -> None:
        while True:
            elapsed = time.monotonic() - self.start
            due = max(RATE_GRACE_S, self.got / self.rate)  # when the bytes counted so far stop being enough
            if self._done.wait(max(due - elapsed, 0.0) + 0.05):
                return
            elapsed = time.monotonic() - self.start
            if elapsed > RATE_GRACE_S and self.got < self.rate * elapsed:
                with self._lock:
                    if self._done.is_set():
                        return
                    self.tripped = (f"the server sends {self.got / elapsed:.0f} bytes/s, below the minimum "
                                    f"transfer rate of {self.rate:g} bytes/s (--min-transfer-rate)")
                    if self._sock is not None:
                        self._shut(self._sock)
                return

    def finish(self) -> None:
        """End the watch; :class:`_Trickle` when it had tripped (what was read may have been cut short)."""
        with self._lock:
            self._done.set()
            self._close()
        if self.tripped:
            raise _Trickle(self.tripped)


def _opener(watch: _Watch):
    """A urllib opener whose connections hand their sockets to ``watch`` (redirects open new ones: each is
    handed over in turn)."""

    def watched(cls):
        def connection(*args, **kwargs):
            conn = cls(*args, **kwargs)
            create = conn._create_connection
            conn._create_connection = lambda *a, **k: watch.attach(create(*a, **k))
            return conn

        return connection

    class Http(urllib.request.HTTPHandler):
        def do_open(self, http_class, req, **kwargs):
            return super().do_open(watched(http_class), req, **kwargs)

    class Https(urllib.request.HTTPSHandler):
        def do_open(self, http_class, req, **kwargs):
            return super().do_open(watched(http_class), req, **kwargs)

    handlers = [Http(), Https()] if hasattr(http.client, "HTTPSConnection") else [Http()]
    return urllib.request.build_opener(*handlers)


def _read_body(r, rate: float, watch: _Watch | None = None) -> bytes:
    """The body of the response ``r``, read as it comes, refused (:class:`_Trickle`) once it has run
    :data:`RATE_GRACE_S` seconds at less than ``rate`` bytes per second on average (0: never). The bytes read
    are counted on ``watch``, whose watchdog ends a read that blocks (a trickled chunk-size line) in the same
    event; its clock, started with the request, is the one used."""
    start = watch.start if watch is not None else time.monotonic()
    parts, got = [], 0
    while True:
        chunk = r.read1(1 << 16)
        if not chunk:
            break
        parts.append(chunk)
        got += len(chunk)
        if watch is not None:
            watch.got = got
        elapsed = time.monotonic() - start
        if rate > 0 and elapsed > RATE_GRACE_S and got < rate * elapsed:
            raise _Trickle(f"the server sends {got / elapsed:.0f} bytes/s, below the minimum transfer rate of "
                           f"{rate:g} bytes/s (--min-transfer-rate)")
    if r.length:  # the connection closed before the promised length
        raise http.client.IncompleteRead(b"".join(parts), r.length)
    return b"".join(parts)


def _request(url: str, start: int | None = None, stop: int | None = None):
    """(status, headers, body) of a GET of ``url`` or of its range ``[start, stop)``; retried when transient.
    InputError (one line, no chained exception: it may cross a process boundary, and an HTTP error holds its
    open response, which does not pickle) for anything else."""
    headers = {"User-Agent": "tiled-gridpull", "Accept-Encoding": "identity"}
    if start is not None:
        headers["Range"] = f"bytes={start}-{stop - 1}"
    problem = None
    rate = min_transfer_rate()  # a bad setting is the user's, not the server's: asked before the first attempt
    for attempt in range(ATTEMPTS):
        if attempt:
            time.sleep(0.5 * 2 ** (attempt - 1))
        watch = _Watch(rate)
        try:
            try:
                with _opener(watch).open(urllib.request.Request(url, headers=headers), timeout=TIMEOUT_S) as r:
                    body = _read_body(r, rate, watch)
            finally:
                watch.finish()  # a read cut by the watchdog fails as whatever it hit: the rate is the cause
            if start is None and (r.headers.get("Content-Encoding") or "").lower() == "gzip":
                import gzip  # a server may compress a whole file though asked for it as it is

                body = gzip.decompress(body)
            return r.status, r.headers, body
        except urllib.error.HTTPError as exc:
            exc.close()
            # urllib's reason for a redirect loop spans three lines: a message is one line
            reason = (str(exc.reason or "").strip().splitlines() or [""])[0]
            if exc.code == 404:
                problem = "file not found (HTTP 404)"
            elif 300 <= exc.code < 400:
                problem = f"too many redirects, or a redirect loop (HTTP {exc.code})"
            else:
                problem = f"the server refused the request (HTTP {exc.code} {reason})"
            if exc.code not in _TRANSIENT_STATUS:
                break
        except urllib.error.URLError as exc:
            problem = f"cannot reach the server ({exc.reason})"
            if isinstance(exc.reason, (ValueError, LookupError)):
                break
        except (TimeoutError, ConnectionError, http.client.IncompleteRead) as exc:
            problem = f"the connection failed ({exc.__class__.__name__})"
        except _Trickle as exc:  # retried: a congested link may recover
            problem = str(exc)
        except (http.client.HTTPException, ValueError, OSError) as exc:
            first = (str(exc).strip().splitlines() or [""])[0]
            problem = f"cannot read from the server ({exc.__class__.__name__}: {first})"
            break
    raise InputError(f"{shown(url)}: {problem}" + (f" after {attempt + 1} attempts" if attempt else ""))


def fetch(url: str, start: int | None = None, stop: int | None = None) -> bytes:
    """The bytes of ``url``, or of its range ``[start, stop)``.

    A server that ignores the range (answers 200 with the whole file) is refused unless the range was the whole
    file: reading every node of a survey that way would fetch the survey once per node."""
    status, _, data = _request(url, start, stop)
    if start is not None and status != 206 and not (status == 200 and start == 0 and len(data) <= stop):
        raise InputError(f"{shown(url)}: the server does not answer range requests (HTTP {status} to "
                         f"'Range: bytes={start}-{stop - 1}'), which reading by region needs")
    if start is not None and len(data) != stop - start and not (status == 200 and start == 0):
        raise InputError(f"{shown(url)}: truncated answer ({len(data)} bytes for a range of {stop - start})")
    return data


def validators(url: str) -> dict:
    """What identifies this version of the file on the server: ``size``, ``etag``, ``last_modified`` (from a
    one-byte range GET: ``Content-Range`` carries the size; absent headers are None). The URL is recorded
    without its query, so a re-signed URL of the same file keys the same version."""
    status, h, data = _request(url, 0, 1)
    size = None
    m = re.search(r"/(\d+)\s*$", h.get("Content-Range") or "")
    if status == 206 and m:
        size = int(m.group(1))
    elif status == 200:  # no range support: the whole file came back
        size = len(data)
    return {"url": shown(url), "size": size, "etag": h.get("ETag"), "last_modified": h.get("Last-Modified")}


class RemoteFile(io.RawIOBase):
    """A read-only, seekable file over HTTP range requests (what laspy's LAS and COPC readers read from).

    Reads smaller than :data:`BLOCK` are served from whole blocks fetched once (the LAS header and VLRs are read
    a few bytes at a time); larger reads (a COPC node group's compressed chunks) fetch exactly their range.

    Parameters
    ----------
    url : str
    size : int, optional
        The file's length; asked of the server (:func:`validators`) when not given.
    """

    def __init__(self, url: str, size: int | None = None):
        super().__init__()
        self.url = url
        self.size = size if size is not None else validators(url)["size"]
        if self.size is None:
            raise InputError(f"{shown(url)}: the server does not say the file's length, which reading by region "
                             "needs")
        self._pos = 0
        self._blocks: OrderedDict[int, bytes] = OrderedDict()

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        self._checkClosed()
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self._checkClosed()
        if whence not in (io.SEEK_SET, io.SEEK_CUR, io.SEEK_END):
            raise ValueError(f"invalid whence ({whence})")
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self.size}[whence]
        if base + offset < 0:
            raise ValueError("negative seek position")
        self._pos = base + offset
        return self._pos

    def _block(self, k: int) -> bytes:
        if k in self._blocks:
            self._blocks.move_to_end(k)
            return self._blocks[k]
        data = fetch(self.url, k * BLOCK, min(self.size, (k + 1) * BLOCK))
        self._blocks[k] = data
        if len(self._blocks) > CACHED_BLOCKS:
            self._blocks.popitem(last=False)
        return data

    def readinto(self, buffer) -> int:
        self._checkClosed()
        view = memoryview(buffer).cast("B")
        n = min(len(view), max(self.size - self._pos, 0))
        if n == 0:
            return 0
        if n >= BLOCK:
            view[:n] = fetch(self.url, self._pos, self._pos + n)
        else:
            done = 0
            while done < n:
                k, at = divmod(self._pos + done, BLOCK)
                block = self._block(k)
                take = min(n - done, len(block) - at)
                if take <= 0:  # the server's file is shorter than it said
                    raise InputError(f"{shown(self.url)}: the file ended early (changed on the server?)")
                view[done:done + take] = block[at:at + take]
                done += take
        self._pos += n
        return n

    def read(self, size: int = -1) -> bytes:
        self._checkClosed()
        left = max(self.size - self._pos, 0)
        size = left if size is None or size < 0 else min(size, left)
        buf = bytearray(size)
        n = self.readinto(buf)
        return bytes(buf[:n])
