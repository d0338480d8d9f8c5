"""COPC files and EPTs read from a web server (a local one here, answering range requests as object stores do):
the same index, the same tiles byte for byte as the files on disk, only the bytes a tile needs, and one-line
errors for what a server can do wrong."""

import email.utils
import hashlib
import http.server
import os
import threading
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.errors import InputError
from tiled_gridpull.io.indexed import read_index
from tiled_gridpull.io.indexed_write import write_copc, write_ept
from tiled_gridpull.io import remote
from tiled_gridpull.io.remote import RemoteFile, shown, url_join, url_name
from tiled_gridpull.jobdir import JobPaths
from tiled_gridpull.prepare import prepare_job
from tiled_gridpull.tiling import TilingConfig

pytest.importorskip("copclib", reason="writing COPC test files needs copclib (pip install 'tiled-gridpull[copc]')")

TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
ORIGIN = np.array([500000.0, 4000000.0, 20.0])
WKT = 'PROJCS["WGS 84 / UTM zone 31N",GEOGCS["WGS 84"],UNIT["metre",1]]'


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Files of the served directory with HEAD, ETag, Last-Modified and single ``Range: bytes=a-b`` requests
    (206), counting the body bytes sent; ``ranges = False`` on the server answers 200 with the whole file."""

    def log_message(self, *args):
        pass

    def _file(self):
        f = Path(self.translate_path(self.path))
        return f if f.is_file() else None

    def _headers(self, f: Path, status: int, length: int, extra: dict | None = None):
        st = f.stat()
        self.send_response(status)
        self.send_header("Content-Length", str(length))
        self.send_header("ETag", f'"{st.st_size:x}-{st.st_mtime_ns:x}"')
        self.send_header("Last-Modified", email.utils.formatdate(st.st_mtime, usegmt=True))
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()

    def do_HEAD(self):  # refused, as an object store refuses HEAD on a URL pre-signed for GET
        self.send_error(403, "SignatureDoesNotMatch")

    def do_GET(self):
        f = self._file()
        if f is None:
            self.send_error(404)
            return
        self.server.gets[f.name] = self.server.gets.get(f.name, 0) + 1
        self.server.asked.append((f.name, self.headers.get("Range")))
        if f.name in self.server.flaky and self.server.gets[f.name] == 1:
            self.send_error(503, "Slow Down")  # a transient failure: the first request of the file
            return
        data = f.read_bytes()
        rng = self.headers.get("Range")
        if rng and self.server.ranges:
            a, b = rng.split("=")[1].split("-")
            a, b = int(a), min(int(b), len(data) - 1)
            body = data[a:b + 1]
            self._headers(f, 206, len(body), {"Content-Range": f"bytes {a}-{b}/{len(data)}"})
        else:
            body = data
            self._headers(f, 200, len(body))
        self.server.sent[f.name] = self.server.sent.get(f.name, 0) + len(body)
        self.wfile.write(body)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("served")
    rng = np.random.default_rng(8)
    n = 40000
    x = np.concatenate([rng.uniform(0, 10, n // 2), rng.uniform(30, 40, n // 2)])
    y = rng.uniform(0, 12, n)
    xyz = np.column_stack([x, y, 0.3 * np.sin(x) * np.cos(y / 2)]) + ORIGIN
    write_copc(root / "s.copc.laz", xyz, max_node_points=3000, wkt=WKT)
    write_copc(root / "far.copc.laz", xyz + [0, 60, 0], max_node_points=3000, wkt=WKT)
    write_ept(root / "ept", xyz, max_node_points=3000, wkt=WKT)

    def handler(*args, **kwargs):
        return _Handler(*args, directory=str(root), **kwargs)

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.sent, server.ranges, server.gets, server.flaky, server.asked = {}, True, {}, set(), []
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    yield {"root": root, "server": server, "base": base,
           "COPC": (f"{base}/s.copc.laz", str(root / "s.copc.laz")),
           "EPT": (f"{base}/ept/ept.json", str(root / "ept" / "ept.json"))}
    server.shutdown()


def _files(specs):
    return {s.name: (s.n_points, s.points_sha256, Path(s.points_path).read_bytes(),
                     Path(s.occupancy_path).read_bytes()) for s in specs}


def test_url_names_and_siblings():
    url = "https://example.org/lidar/area/ept.json?sig=abc"
    assert url_name(url) == "ept.json"
    assert url_join(url, "ept-data", "0-0-0-0.laz") == "https://example.org/lidar/area/ept-data/0-0-0-0.laz?sig=abc"
    assert shown(url) == "https://example.org/lidar/area/ept.json?..."
    assert shown("https://user:pw@example.org/a.copc.laz") == "https://example.org/a.copc.laz"


def test_remote_file_reads_what_the_file_holds(served):
    url, local = served["COPC"]
    data = Path(local).read_bytes()
    rng = np.random.default_rng(0)
    with RemoteFile(url) as fh:
        assert fh.size == len(data)
        for _ in range(60):
            a = int(rng.integers(0, len(data)))
            n = int(rng.choice([1, 7, 375, 70_000, 200_000]))
            fh.seek(a)
            assert fh.read(n) == data[a:a + n]
        fh.seek(-10, os.SEEK_END)
        assert fh.read() == data[-10:]
        assert fh.read(5) == b""
        fh.seek(-3, os.SEEK_END)
        assert fh.read(1 << 62) == data[-3:]  # a huge length (a damaged header's) reads what is left
        with pytest.raises(ValueError):
            fh.seek(0, 7)
    with pytest.raises(ValueError):
        fh.read(1)  # closed


@pytest.mark.parametrize("kind", ["COPC", "EPT"])
def test_an_index_read_from_a_url_is_the_index_on_disk(served, kind):
    url, local = served[kind]
    a, b = read_index(url), read_index(local)
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.bounds, b.bounds)
    assert a.crs == b.crs and "UTM zone 31N" in a.crs and a.points == b.points == 40000


def test_a_copc_index_from_a_url_asks_for_each_part_once(served):
    # the header checks (CRS from the EVLRs) and the hierarchy share one remote file: one size request, and no
    # block of the header fetched twice
    url, _ = served["COPC"]
    served["server"].asked.clear()
    read_index(url)
    asked = [r for name, r in served["server"].asked if name == "s.copc.laz"]
    assert asked.count("bytes=0-0") == 1, asked
    assert len(asked) == len(set(asked)), asked


def test_a_url_that_is_not_a_copc_file_is_named_without_its_query(served):
    (served["root"] / "junk.copc.laz").write_bytes(b"not a point cloud" * 40)
    with pytest.raises(InputError, match="not a LAS/LAZ file") as err:
        read_index(f"{served['base']}/junk.copc.laz?sig=s3cr3t")
    assert "s3cr3t" not in str(err.value) and "junk.copc.laz?..." in str(err.value)


@pytest.mark.parametrize("kind", ["COPC", "EPT"])
def test_tiles_read_from_a_url_are_the_tiles_of_the_file_and_a_job_resumes(served, tmp_path, kind):
    url, local = served[kind]
    plan, specs, scan = prepare_job([url], TILING, JobPaths(tmp_path / "url"))
    plan_l, specs_l, _ = prepare_job([local], TILING, JobPaths(tmp_path / "local"))
    assert scan["indexed"] == [kind] and len(specs) >= 4
    assert plan.to_dict() == plan_l.to_dict()
    assert _files(specs) == _files(specs_l)
    _, again, scan2 = prepare_job([url], TILING, JobPaths(tmp_path / "url"))
    assert scan2["partition_reused"] and _files(again) == _files(specs)


def test_a_tile_fetches_a_part_of_a_copc_file(served, tmp_path):
    from tiled_gridpull.indexed_inputs import plan_indexed, read_tile

    import laspy
    from laspy.copc import load_octree_for_query

    from tiled_gridpull.indexed_inputs import _read_box
    from tiled_gridpull.io.remote import BLOCK

    url, local = served["COPC"]
    plan, _, _ = plan_indexed([url], TILING)
    tile = (plan.tile_range[0] - 1, 0, 0)  # the far end of the second patch
    lo, hi = _read_box(plan, tile)
    ix = read_index(local)
    lo, hi = np.where(np.isinf(lo), ix.lo.min(0), lo), np.where(np.isinf(hi), ix.hi.max(0), hi)
    with laspy.CopcReader.open(local) as r:
        nodes = [n for n in load_octree_for_query(r.source, r.copc_info, r.root_page) if n.point_count > 0]
    lo_n, hi_n = ix.lo, ix.hi  # same order as ix.keys: by file offset
    nodes.sort(key=lambda n: n.offset)
    overlapping = np.all((lo_n <= hi + 1e-3) & (hi_n >= lo - 1e-3), axis=1)
    needed = sum(n.byte_size for n, o in zip(nodes, overlapping) if o)
    size = Path(local).stat().st_size
    assert needed < 0.7 * size  # the tile's nodes are a part of the file (else the test says nothing)
    served["server"].sent.clear()
    spec, owned = read_tile([url], plan, tile, str(tmp_path))
    assert spec is not None and owned > 0
    # the chunks of the nodes overlapping the tile, plus the header and hierarchy pages in a few blocks
    assert served["server"].sent["s.copc.laz"] <= needed + 4 * BLOCK, (served["server"].sent, needed, size)


def test_a_changed_file_on_the_server_is_read_again(served, tmp_path):
    import shutil

    url, local = served["COPC"]
    copy = served["root"] / "copy.copc.laz"
    shutil.copy(local, copy)
    curl = f"{served['base']}/copy.copc.laz"
    _, first, _ = prepare_job([curl], TILING, JobPaths(tmp_path / "j"))
    xyz = np.random.default_rng(3).uniform(0, 10, (5000, 3)) + ORIGIN
    write_copc(copy, xyz, max_node_points=3000, wkt=WKT)
    os.utime(copy, ns=(copy.stat().st_atime_ns, copy.stat().st_mtime_ns + 10**9))
    _, second, scan = prepare_job([curl], TILING, JobPaths(tmp_path / "j"))
    assert not scan["partition_reused"] and scan["points"] == 5000
    copy.unlink()


def test_server_problems_are_one_line(served, tmp_path):
    base = served["base"]
    with pytest.raises(InputError, match=r"^http://.*/nothing\.copc\.laz: file not found \(HTTP 404\)$"):
        read_index(f"{base}/nothing.copc.laz")
    # an EPT whose hierarchy page is missing names the page
    with pytest.raises(InputError, match=r"ept-hierarchy/0-0-0-0\.json: file not found"):
        import shutil

        shutil.copy(served["root"] / "ept" / "ept.json", served["root"] / "ept.json")
        read_index(f"{base}/ept.json")
    with pytest.raises(InputError, match="cannot reach the server.*after 2 attempts$"):
        with pytest.MonkeyPatch.context() as m:
            m.setattr(remote, "ATTEMPTS", 2)
            read_index("http://127.0.0.1:9/x.copc.laz")  # the discard port: nothing listens
    with pytest.raises(InputError, match="not a valid URL"):
        read_index("http://[::1/x.copc.laz")
    served["server"].ranges = False
    try:
        with pytest.raises(InputError, match="does not answer range requests"):
            read_index(served["COPC"][0])
    finally:
        served["server"].ranges = True


def test_urls_that_would_need_streaming_are_refused(served, tmp_path):
    url = served["COPC"][0]
    with pytest.raises(InputError, match="only COPC files and EPTs are read from a URL"):
        prepare_job([f"{served['base']}/a.laz"], TILING, JobPaths(tmp_path / "a"))
    # a job refuses it before anything (the cell size, the noise measurement) reads the URL
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.tiled_job import reconstruct_scene

    with pytest.raises(InputError, match="only COPC files and EPTs are read from a URL"):
        reconstruct_scene([f"{served['base']}/a.laz"], None, TILING, SolverConfig(), tmp_path / "j")
    with pytest.raises(InputError, match="--trajectory"):
        prepare_job([url], TILING, JobPaths(tmp_path / "b"), trajectory=__file__)
    with pytest.raises(InputError, match="given with it, is not a COPC"):
        prepare_job([url, __file__], TILING, JobPaths(tmp_path / "c"))
    assert not any((tmp_path / d / "points").exists() for d in "abc")


def test_one_shape_read_and_cli_dry_run_from_a_url(served, tmp_path, capsys):
    from tiled_gridpull.io import read_points
    from tiled_gridpull.pipeline.cli import main

    url, local = served["EPT"]
    a, b = read_points(url), read_points(local)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert hashlib.sha256(a.xyz.tobytes()).hexdigest() == hashlib.sha256(b.xyz.tobytes()).hexdigest()
    code = main(["reconstruct", served["COPC"][0], "-o", str(tmp_path / "x.ply"), "--dry-run",
                 "--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "2.4"])
    cap = capsys.readouterr()
    assert code == 0 and "tiles" in cap.out, cap.err
    assert not (tmp_path / "x.ply").exists()


def test_dask_workers_read_the_tiles_from_the_url(served, tmp_path):
    from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions

    url, local = served["EPT"]
    executor = DaskExecutor(JobOptions(workers=1, progress=False))
    try:
        _, specs, scan = prepare_job([url], TILING, JobPaths(tmp_path / "d"),
                                     run_tasks=lambda fn, a: executor.map(fn, a, tmp_path))
        assert executor._client is not None  # the reads ran on the cluster's worker process
    finally:
        executor.close()
    _, specs_l, _ = prepare_job([local], TILING, JobPaths(tmp_path / "l"))
    assert scan["candidate_tiles"] >= len(specs) >= 4
    assert _files(specs) == _files(specs_l)


def test_a_presigned_url_is_read_with_gets_only_resumes_re_signed_and_is_never_recorded(served, tmp_path):
    import json

    url = served["COPC"][0]
    signed = [f"{url}?X-Amz-Signature=secret{k}" for k in (1, 2)]
    _, specs, scan = prepare_job([signed[0]], TILING, JobPaths(tmp_path / "j"))  # HEAD is refused: GETs only
    assert scan["indexed"] == ["COPC"] and len(specs) >= 4
    _, _, scan2 = prepare_job([signed[1]], TILING, JobPaths(tmp_path / "j"))  # the same file, signed again
    assert scan2["partition_reused"]
    written = "".join(p.read_text(errors="replace") for p in (tmp_path / "j").rglob("*.json"))
    assert "secret" not in written and "s.copc.laz" in written
    assert json.loads((tmp_path / "j" / "manifest.json").read_text())["inputs"] == [f"{url}?..."]


def test_transient_server_errors_are_retried(served, tmp_path):
    url, local = served["EPT"]
    served["server"].flaky = {"ept.json", "0-0-0-0.json", "0-0-0-0.laz"}
    served["server"].gets.clear()
    try:
        _, specs, _ = prepare_job([url], TILING, JobPaths(tmp_path / "u"))
    finally:
        served["server"].flaky = set()
    assert served["server"].gets["0-0-0-0.laz"] >= 2  # refused once (503), then read
    _, specs_l, _ = prepare_job([local], TILING, JobPaths(tmp_path / "l"))
    assert _files(specs) == _files(specs_l)


def test_a_tile_task_does_not_open_the_inputs_it_does_not_reach(served, tmp_path):
    from tiled_gridpull.indexed_inputs import indexed_sources, plan_indexed, read_tile

    urls = [served["COPC"][0], f"{served['base']}/far.copc.laz"]
    plan, _, _ = plan_indexed(urls, TILING)
    sources = indexed_sources(urls)
    served["server"].sent.clear()
    served["server"].gets.clear()
    spec, owned = read_tile(sources, plan, (0, 0, 0), str(tmp_path))
    assert spec is not None and owned > 0
    assert "far.copc.laz" not in served["server"].gets and "s.copc.laz" in served["server"].sent


def test_job_messages_name_urls_without_their_query(served, tmp_path):
    other = 'PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84"],UNIT["metre",1]]'
    write_copc(served["root"] / "utm32.copc.laz", np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]) + ORIGIN, wkt=other)
    urls = [f"{served['COPC'][0]}?sig=s3cr3t", f"{served['base']}/utm32.copc.laz?sig=s3cr3t"]
    with pytest.raises(InputError, match="different coordinate reference systems") as err:
        prepare_job(urls, TILING, JobPaths(tmp_path / "job"))
    assert "s3cr3t" not in str(err.value) and "utm32.copc.laz?..." in str(err.value)


def test_a_job_asks_each_input_its_version_once(served, tmp_path, monkeypatch):
    # the plan and the tile tasks use the versions the driver asked for: one request per input, not one per use
    from tiled_gridpull import indexed_inputs

    asked = []
    real = indexed_inputs.source_version
    monkeypatch.setattr(indexed_inputs, "source_version", lambda p: asked.append(p) or real(p))
    indexed_inputs._index.cache_clear()
    urls = [served["COPC"][0], served["EPT"][0]]
    _, specs, _ = prepare_job(urls, TILING, JobPaths(tmp_path / "job"))
    assert specs and sorted(asked) == sorted(urls), asked


def test_a_server_error_on_a_dask_worker_reaches_the_driver_as_one_line(served, tmp_path):
    import shutil

    from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions

    e = served["root"] / "ept_gone"
    shutil.copytree(served["root"] / "ept", e)
    victim = sorted((e / "ept-data").iterdir())[-1]
    victim.unlink()  # a node file missing on the server
    url = f"{served['base']}/ept_gone/ept.json?sig=secret"
    executor = DaskExecutor(JobOptions(workers=1, progress=False))
    try:
        with pytest.raises(InputError) as info:
            prepare_job([url], TILING, JobPaths(tmp_path / "d"), run_tasks=lambda fn, a: executor.map(fn, a, tmp_path))
    finally:
        executor.close()
    msg = str(info.value)
    assert type(info.value) is InputError and len(msg.splitlines()) == 1, msg
    assert f"ept-data/{victim.name}?...: file not found (HTTP 404)" in msg and "secret" not in msg
    assert not (tmp_path / "d" / "points").exists()


def test_a_url_input_does_not_clash_with_the_work_directory(served, tmp_path, monkeypatch):
    from tiled_gridpull.io.outputs import check_outputs

    monkeypatch.chdir(tmp_path)
    check_outputs([served["COPC"][0]], tmp_path / "x.ply", work_dir=".")


class _Odd(http.server.BaseHTTPRequestHandler):
    """A misbehaving server: ``/loop/...`` redirects to itself; ``/trickle/...`` sends a header promising 100 kB,
    then 10 bytes a second (until the client gives up, or 30 s at most)."""

    def log_message(self, *args):
        pass

    def do_GET(self):
        if self.path.startswith("/loop/"):
            self.send_response(302)
            self.send_header("Location", self.path)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        size = 100_000
        rng = self.headers.get("Range")
        self.send_response(206 if rng else 200)
        if rng:
            self.send_header("Content-Range", f"bytes 0-{size - 1}/{size}")
        self.send_header("Content-Length", str(size))
        self.end_headers()
        import time

        end = time.monotonic() + 30
        try:
            while time.monotonic() < end:
                self.wfile.write(b"x" * 10)
                self.wfile.flush()
                time.sleep(1.0)
        except OSError:  # the client hung up
            pass


@pytest.fixture
def odd_server():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Odd)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_a_redirect_loop_is_one_line(odd_server, tmp_path, capsys):
    from tiled_gridpull.pipeline.cli import main

    url = f"{odd_server}/loop/area.copc.laz?sig=secret"
    with pytest.raises(InputError) as exc:
        read_index(url)
    assert "\n" not in str(exc.value) and "redirect" in str(exc.value) and "secret" not in str(exc.value)
    code = main(["reconstruct", url, "-o", str(tmp_path / "x.ply"), "--dry-run", "--voxel-size", "0.2"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 3 and len(err) == 1 and "redirect" in err[0], err


def test_a_trickling_server_is_refused_at_the_minimum_transfer_rate(odd_server, tmp_path, capsys, monkeypatch):
    """10 bytes a second never trips the per-read timeout: a job on such a server ran indefinitely. A transfer
    below the minimum rate (settable: --min-transfer-rate, or the environment a local cluster's workers inherit)
    after the grace period is a failed attempt, retried, then one line and exit 3."""
    import time

    from tiled_gridpull.pipeline.cli import main

    monkeypatch.setattr(remote, "RATE_GRACE_S", 1.0, raising=False)  # the default 10 s grace, shortened
    monkeypatch.setattr(remote, "ATTEMPTS", 2)
    monkeypatch.setenv("TILED_GRIDPULL_MIN_TRANSFER_RATE", "1000")  # restored after the test (main sets it)
    url = f"{odd_server}/trickle/area.copc.laz"
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"below the minimum transfer rate of 1000 bytes/s .*after 2 attempts$"):
        read_index(url)
    assert time.monotonic() - t0 < 15
    t0 = time.monotonic()
    code = main(["reconstruct", url, "-o", str(tmp_path / "x.ply"), "--dry-run", "--voxel-size", "0.2",
                 "--min-transfer-rate", "500"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 3 and len(err) == 1 and "below the minimum transfer rate of 500 bytes/s" in err[0], err
    assert time.monotonic() - t0 < 15
    assert not (tmp_path / "x.ply").exists()
    # a bad setting is the user's: exit 2 before anything is read
    code = main(["reconstruct", url, "-o", str(tmp_path / "x.ply"), "--dry-run", "--voxel-size", "0.2",
                 "--min-transfer-rate", "fast"])
    assert code == 2 and "--min-transfer-rate" in capsys.readouterr().err


@pytest.fixture(params=["http", "https"])
def dribbling_server(request, tmp_path, monkeypatch):
    """A raw server that trickles one byte a second: ``/header/...`` inside its headers (``X-Slow: aaa...``),
    ``/chunk/...`` inside the first chunk-size line of a chunked body; over TLS too (a self-signed certificate,
    trusted through ``SSL_CERT_FILE``: TLS takes over the connection's socket). It stops by itself after 30 s."""
    import shutil
    import socket
    import ssl
    import subprocess
    import time

    tls = None
    if request.param == "https":
        if not shutil.which("openssl"):
            pytest.skip("no openssl to make a certificate")
        subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1",
                        "-addext", "subjectAltName=IP:127.0.0.1", "-days", "1", "-keyout", str(tmp_path / "k.pem"),
                        "-out", str(tmp_path / "c.pem")], check=True, capture_output=True, timeout=60)
        tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        tls.load_cert_chain(tmp_path / "c.pem", tmp_path / "k.pem")
        monkeypatch.setenv("SSL_CERT_FILE", str(tmp_path / "c.pem"))
    end = time.monotonic() + 30
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    listener.settimeout(0.5)

    def answer(conn):
        try:
            if tls is not None:
                conn = tls.wrap_socket(conn, server_side=True)
            request = conn.recv(65536)
            if b" /header/" in request:
                conn.sendall(b"HTTP/1.1 206 Partial Content\r\nX-Slow: ")
            else:
                conn.sendall(b"HTTP/1.1 206 Partial Content\r\nContent-Range: bytes 0-0/100000\r\n"
                             b"Transfer-Encoding: chunked\r\n\r\n")
            while time.monotonic() < end:
                conn.sendall(b"0" if b" /chunk/" in request else b"a")
                time.sleep(1.0)
        except OSError:  # the client hung up
            pass
        finally:
            conn.close()

    def serve():
        while time.monotonic() < end:
            try:
                conn, _ = listener.accept()
            except OSError:  # the accept timed out
                continue
            threading.Thread(target=answer, args=(conn,), daemon=True).start()
        listener.close()

    threading.Thread(target=serve, daemon=True).start()
    yield f"{request.param}://127.0.0.1:{listener.getsockname()[1]}"


@pytest.mark.parametrize("where", ["header", "chunk"])
def test_a_server_trickling_its_headers_or_a_chunk_size_is_refused(dribbling_server, tmp_path, capsys,
                                                                     monkeypatch, where):
    """One byte a second inside the headers or a chunk-size line held one blocking read of http.client: neither
    the socket's timeout nor the check between body reads fired, and the job hung. The minimum rate holds for
    the whole request: a watchdog shuts the socket down, the attempt fails, then one line and exit 3."""
    import time

    from tiled_gridpull.pipeline.cli import main

    monkeypatch.setattr(remote, "RATE_GRACE_S", 1.0)  # the default 10 s grace, shortened
    monkeypatch.setattr(remote, "ATTEMPTS", 2)
    monkeypatch.setenv("TILED_GRIDPULL_MIN_TRANSFER_RATE", "1000")
    url = f"{dribbling_server}/{where}/area.copc.laz"
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"below the minimum transfer rate of 1000 bytes/s .*after 2 attempts$"):
        read_index(url)
    assert time.monotonic() - t0 < 10
    t0 = time.monotonic()
    code = main(["reconstruct", url, "-o", str(tmp_path / "x.ply"), "--dry-run", "--voxel-size", "0.2"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 3 and len(err) == 1 and "below the minimum transfer rate" in err[0], err
    assert time.monotonic() - t0 < 10
    assert not (tmp_path / "x.ply").exists()
