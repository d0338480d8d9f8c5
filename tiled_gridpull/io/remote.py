"""Inputs on a web server (``http://``, ``https://``): the cloud-optimized formats read where they are published.

COPC files and EPTs are published on web servers and object stores (S3, Azure, GCS over https) precisely so that
a reader can fetch one region without the rest: a COPC file's header, hierarchy pages and point chunks are byte
ranges of one file (HTTP ``Range`` requests), an EPT's are small files of their own. This module is the transport:
:class:`RemoteFile`, a read-only seekable file over range requests, for laspy's readers; :func:`fetch` for whole
small files; :func:`validators` for what identifies a version of a file on the server (size, ``ETag``,
``Last-Modified``), which keys the per-process index cache and a job's resume. Every failure is one
:class:`~tiled_gridpull.errors.InputError` line naming the URL.

Only the standard library is used (``urllib``), so remote inputs need no extra package. Credentials are whatever
the URL carries (a pre-signed object-store URL works; a bucket needing signed requests does not).
"""

from __future__ import annotations

import contextlib
import io
import posixpath
import urllib.error
import urllib.parse
import urllib.request
from collections import OrderedDict
from collections.abc import Iterator

from ..errors import InputError

__all__ = ["is_url", "url_name", "url_join", "resolved", "RemoteFile", "fetch", "validators", "TIMEOUT_S"]

#: seconds a request may wait for the server before the input is reported unreachable
TIMEOUT_S = 60.0
#: bytes a small read fetches at once (a LAS header is read field by field: one request each would be hundreds)
BLOCK = 1 << 16
#: blocks kept per open file
CACHED_BLOCKS = 16


def is_url(source) -> bool:
    """Whether ``source`` is an ``http://`` or ``https://`` URL (anything else is a local path)."""
    return isinstance(source, str) and source[:8].lower().startswith(("http://", "https://"))


def url_name(url: str) -> str:
    """The last segment of the URL's path, without query or fragment (``.../a/ept.json?sig=..`` -> ``ept.json``)."""
    return posixpath.basename(urllib.parse.urlsplit(url).path)


def url_join(url: str, *parts: str) -> str:
    """``parts`` appended to the directory of ``url``'s path, keeping its query (a pre-signed URL's signature
    belongs to one object, so a sibling needs its own: this keeps the query for servers that sign a prefix)."""
    s = urllib.parse.urlsplit(url)
    path = posixpath.join(posixpath.dirname(s.path), *parts)
    return urllib.parse.urlunsplit((s.scheme, s.netloc, path, s.query, ""))


@contextlib.contextmanager
def _errors(url: str) -> Iterator[None]:
    try:
        yield
    except urllib.error.HTTPError as exc:
        if exc.code == 404:
            raise InputError(f"{url}: file not found (HTTP 404)") from None
        raise InputError(f"{url}: the server refused the request (HTTP {exc.code} {exc.reason})") from None
    except urllib.error.URLError as exc:
        raise InputError(f"{url}: cannot reach the server ({exc.reason})") from None
    except (TimeoutError, ConnectionError, OSError) as exc:
        raise InputError(f"{url}: cannot read from the server ({exc.__class__.__name__}: {exc})") from None


def _open(url: str, start: int | None = None, stop: int | None = None, method: str = "GET"):
    headers = {"User-Agent": "tiled-gridpull"}
    if start is not None:
        headers["Range"] = f"bytes={start}-{stop - 1}"
    return urllib.request.urlopen(urllib.request.Request(url, headers=headers, method=method), timeout=TIMEOUT_S)


def fetch(url: str, start: int | None = None, stop: int | None = None) -> bytes:
    """The bytes of ``url``, or of its range ``[start, stop)``. A server that ignores the range (answers 200 with
    the whole file) is refused: reading every node of a survey that way would fetch the survey once per node."""
    with _errors(url):
        with _open(url, start, stop) as r:
            if start is not None and r.status != 206:
                raise InputError(f"{url}: the server does not answer range requests (HTTP {r.status} to "
                                 f"'Range: bytes={start}-{stop - 1}'), which reading by region needs")
            data = r.read()
    if start is not None and len(data) != stop - start:
        raise InputError(f"{url}: truncated answer ({len(data)} bytes for a range of {stop - start})")
    return data


def validators(url: str) -> dict:
    """What identifies this version of the file on the server: ``size``, ``etag``, ``last_modified`` (a HEAD
    request; absent headers are None)."""
    with _errors(url):
        with _open(url, method="HEAD") as r:
            size = r.headers.get("Content-Length")
            return {"url": url, "size": int(size) if size is not None else None, "etag": r.headers.get("ETag"),
                    "last_modified": r.headers.get("Last-Modified")}


class RemoteFile(io.RawIOBase):
    """A read-only, seekable file over HTTP range requests (what laspy's LAS and COPC readers read from).

    Reads smaller than :data:`BLOCK` are served from whole blocks fetched once (the LAS header and VLRs are read
    a few bytes at a time); larger reads (a COPC node group's compressed chunks) fetch exactly their range.

    Parameters
    ----------
    url : str
    size : int, optional
        The file's length; asked of the server (HEAD) when not given.
    """

    def __init__(self, url: str, size: int | None = None):
        super().__init__()
        self.url = url
        self.size = size if size is not None else validators(url)["size"]
        if self.size is None:
            raise InputError(f"{url}: the server does not say the file's length (no Content-Length), which "
                             "reading by region needs")
        self._pos = 0
        self._blocks: OrderedDict[int, bytes] = OrderedDict()

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
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
                view[done:done + take] = block[at:at + take]
                done += take
        self._pos += n
        return n

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0:
            size = max(self.size - self._pos, 0)
        buf = bytearray(size)
        n = self.readinto(buf)
        return bytes(buf[:n])


def resolved(source) -> str:
    """An input as recorded and handed to workers: a URL as given, a path made absolute (workers of an external
    cluster do not share the driver's working directory)."""
    from pathlib import Path

    return source if is_url(source) else str(Path(source).resolve())
