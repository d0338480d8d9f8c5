"""COPC and EPT inputs read by region (tiled_gridpull.io.indexed) and written for tests (io.indexed_write)."""

import json

import numpy as np
import pytest

from tiled_gridpull.errors import InputError
from tiled_gridpull.io import iter_point_chunks, point_count, read_crs, read_points
from tiled_gridpull.io.indexed import indexed_kind, read_box, read_index, read_levels
from tiled_gridpull.io.indexed_write import octree_layout, write_copc, write_ept

pytest.importorskip("copclib", reason="writing COPC test files needs copclib (pip install 'tiled-gridpull[copc]')")

WKT = ('PROJCS["WGS 84 / UTM zone 31N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
       'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
       'UNIT["metre",1],AUTHORITY["EPSG","32631"]]')


@pytest.fixture(scope="module")
def cloud():
    """A ground with walls and a tree-like clump, in UTM-sized coordinates (60,000 points)."""
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(0, 60, 40000), rng.uniform(0, 30, 40000), rng.normal(0, 0.02, 40000)])
    wall = np.column_stack([rng.uniform(0, 60, 15000), np.full(15000, 29.0), rng.uniform(0, 8, 15000)])
    clump = rng.normal([20, 10, 4], 1.0, (5000, 3))
    return np.concatenate([ground, wall, clump]) + [500000.0, 4000000.0, 12.0]


@pytest.fixture(scope="module")
def files(cloud, tmp_path_factory):
    d = tmp_path_factory.mktemp("indexed")
    return {"COPC": write_copc(d / "c.copc.laz", cloud, wkt=WKT, max_node_points=4000),
            "EPT": write_ept(d / "e", cloud, wkt=WKT, max_node_points=4000),
            "EPT binary": write_ept(d / "b", cloud, wkt=WKT, max_node_points=4000, data_type="binary")}


def _sorted_rows(xyz):
    return xyz[np.lexsort(xyz.T[::-1])]


def test_octree_layout_keeps_every_point_once_and_nodes_small(cloud):
    keys, node_of, half, center = octree_layout(cloud, max_node_points=4000)
    counts = np.bincount(node_of, minlength=len(keys))
    assert counts.sum() == len(cloud) and counts.min() > 0
    # every point lies in its node's cube
    edge = 2 * half / 2.0 ** keys[node_of, 0]
    lo = center - half + keys[node_of, 1:] * edge[:, None]
    assert np.all(cloud >= lo - 1e-6) and np.all(cloud <= lo + edge[:, None] + 1e-6)
    assert keys[:, 0].max() >= 2  # 60,000 points in nodes of 4,000 at most need depth


@pytest.mark.parametrize("kind", ["COPC", "EPT", "EPT binary"])
def test_index_is_read_from_the_header_and_hierarchy(files, cloud, kind):
    ix = read_index(files[kind])
    assert ix.kind == kind.split()[0] and ix.points == len(cloud) == ix.counts.sum()
    np.testing.assert_allclose(ix.bounds, [cloud.min(axis=0), cloud.max(axis=0)], atol=1e-3)
    assert "UTM zone 31N" in ix.crs
    assert np.all(ix.lo <= ix.hi) and len(ix.keys) > 8


@pytest.mark.parametrize("kind", ["COPC", "EPT", "EPT binary"])
def test_read_box_gives_exactly_the_points_inside(files, cloud, kind):
    ix = read_index(files[kind])
    stored = read_points(files[kind], clean=False).xyz  # whole input (COPC as the LAZ file it is)
    from pykdtree.kdtree import KDTree

    assert len(stored) == len(cloud)
    assert KDTree(cloud).query(stored, k=1)[0].max() < 1e-3  # every point, stored to 1 mm
    lo, hi = np.array([500010.0, 4000005.0, 10.0]), np.array([500031.5, 4000029.5, 16.0])
    got = np.concatenate([c.xyz for c in read_box(ix, lo, hi)])
    inside = stored[np.all((stored >= lo) & (stored <= hi), axis=1)]
    assert len(got) == len(inside) > 1000
    np.testing.assert_array_equal(_sorted_rows(got), _sorted_rows(inside))
    # in the stream's order: the whole stream filtered to the box
    stream = np.concatenate([c.xyz for c in iter_point_chunks(files[kind], 7000)])
    np.testing.assert_array_equal(got, stream[np.all((stream >= lo) & (stream <= hi), axis=1)])


@pytest.mark.parametrize("kind", ["COPC", "EPT"])
def test_shallow_levels_are_an_even_subsample(files, cloud, kind):
    ix = read_index(files[kind])
    sample = np.concatenate([c.xyz for c in read_levels(ix, 1)])
    assert 0 < len(sample) < len(cloud) // 4
    # spread over the whole extent, not the first rows of the input
    assert np.all(sample.max(axis=0)[:2] - sample.min(axis=0)[:2] > [50, 25])


def test_ept_is_a_format_like_the_others(files, cloud):
    p = files["EPT"]
    assert indexed_kind(p) == "EPT" and indexed_kind(files["COPC"]) == "COPC" and indexed_kind("a.laz") is None
    assert point_count(p) == len(cloud) and "UTM" in read_crs(p)
    whole = read_points(p, clean=False)
    assert len(whole) == len(cloud)


def test_damaged_indexed_inputs_are_one_line(files, tmp_path):
    for text in ("", "{not json", "[1, 2]"):
        bad = tmp_path / "ept.json"
        bad.write_text(text)
        for call in (read_points, point_count, read_index):
            with pytest.raises(InputError, match=r"ept.json: ") as exc:
                call(bad)
            assert "\n" not in str(exc.value)
    # not an EPT
    bad = tmp_path / "ept.json"
    bad.write_text(json.dumps({"hello": 1}))
    with pytest.raises(InputError, match=r"not an EPT ept.json \(no 'bounds'\)"):
        read_index(bad)
    with pytest.raises(InputError, match="not an EPT"):
        read_points(bad)
    # a node file missing
    import shutil

    e = tmp_path / "e"
    shutil.copytree(files["EPT"].parent, e)
    victim = sorted((e / "ept-data").iterdir())[-1]
    victim.unlink()
    ix = read_index(e / "ept.json")
    with pytest.raises(InputError) as exc:
        list(read_box(ix, ix.bounds[0], ix.bounds[1]))
    assert victim.name in str(exc.value) and "\n" not in str(exc.value)
    # hierarchy counts that disagree with the header
    meta = json.loads((e / "ept.json").read_text())
    meta["points"] += 5
    (e / "ept.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="corrupted EPT"):
        read_index(e / "ept.json")
    # a plain LAZ named like a COPC file; a truncated COPC file
    import laspy

    plain = tmp_path / "plain.copc.laz"
    header = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.arange(10.0), np.arange(10.0), np.arange(10.0)
    las.write(str(plain))
    with pytest.raises(InputError, match="plain.copc.laz: not a readable COPC"):
        read_index(plain)
    cut = tmp_path / "cut.copc.laz"
    cut.write_bytes(files["COPC"].read_bytes()[:2000])
    with pytest.raises(InputError, match="cut.copc.laz"):
        read_index(cut)


@pytest.mark.parametrize("kind", ["COPC", "EPT", "EPT binary"])
def test_absurd_scale_or_offset_of_an_index_is_refused_naming_it(files, tmp_path, kind):
    """The header's (COPC) or ept.json schema's (EPT) scale and offset are applied to every point: non-finite,
    zero or absurd ones are refused when the index is read, in one line naming them, as a LAS header's are."""
    import shutil

    if kind == "COPC":
        p = tmp_path / "c.copc.laz"
        raw = files["COPC"].read_bytes()
        fields = np.frombuffer(raw[131:179], "<f8").copy()  # three scales, then three offsets
        fields[3] = 1e308
        p.write_bytes(raw[:131] + fields.tobytes() + raw[179:])
        needle = r"c\.copc\.laz: the (COPC|LAS) header's offset '1e\+308"  # read whole as the LAZ it is
    else:
        shutil.copytree(files[kind].parent, tmp_path / "e")
        p = tmp_path / "e" / "ept.json"
        meta = json.loads(p.read_text())
        meta["schema"][1]["scale"] = 0.0
        p.write_text(json.dumps(meta))
        needle = r"ept\.json: the ept\.json schema's scale '[^']* 0 "
    for call in (read_index, read_points) if kind == "COPC" else (read_index, point_count, read_points):
        with pytest.raises(InputError, match=needle):
            call(p)


# ------------------------------------------------------------------------------------------ damaged hierarchies


def _within(seconds: float, fn):
    """``fn()``'s exception (or None), failing the test if it has not returned within ``seconds`` (a damaged
    hierarchy used to send the walk round a cycle for ever; the thread is a daemon, so a hang ends with the run)."""
    import threading

    box = {}

    def go():
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - handed back to the test
            box["exc"] = exc

    t = threading.Thread(target=go, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"still running after {seconds} s"
    return box.get("exc")


def _ept_damage(root, how: str) -> None:
    """Damage the EPT under ``root`` (its ept.json and hierarchy pages) as ``how`` says."""
    meta = json.loads((root / "ept.json").read_text())
    pages = root / "ept-hierarchy"
    page = json.loads((pages / "0-0-0-0.json").read_text())
    child = next(k for k in sorted(page) if k.startswith("1-"))
    if how == "page lists itself":
        page["0-0-0-0"] = -1
    elif how == "pages in a cycle":
        page[child] = -1
        (pages / f"{child}.json").write_text(json.dumps({"0-0-0-0": -1}))
    elif how == "page lists its own node again":
        page[child] = -1
        (pages / f"{child}.json").write_text(json.dumps({child: -1}))
    elif how == "absurd depth":
        page["40-0-0-0"] = 1
    elif how == "key outside the cube":
        page["1-2-0-0"] = 1
    elif how == "absurd count":
        page[child] = 10 ** 15
    elif how == "negative count":
        page[child] = -7
    elif how == "span 0":
        meta["span"] = 0
    elif how == "negative span":
        meta["span"] = -128
    elif how == "flat cube":
        meta["bounds"][5] = meta["bounds"][2]
    elif how == "inverted cube":
        meta["bounds"][0], meta["bounds"][3] = meta["bounds"][3], meta["bounds"][0]
    elif how == "infinite bounds":
        (root / "ept.json").write_text(json.dumps(meta).replace(str(meta["bounds"][3]), "1e999", 1))
        return
    elif how == "bounds of 1e308":  # each corner finite, the extent is not
        meta["bounds"] = [-1e308] * 3 + [1e308] * 3
    elif how == "bounds beyond the coordinate limit":
        meta["bounds"] = [-1e200] * 3 + [1e200] * 3
    elif how == "a cube of 1e-300":
        meta["bounds"] = [0.0] * 3 + [1e-300] * 3
        meta.pop("boundsConforming", None)
    elif how == "boundsConforming outside the cube":
        meta["boundsConforming"] = [0.0] * 3 + [1e-300] * 3
    elif how == "srs wkt a list":
        meta["srs"] = {"wkt": ["not", "a", "string"]}
    (pages / "0-0-0-0.json").write_text(json.dumps(page))
    (root / "ept.json").write_text(json.dumps(meta))


EPT_DAMAGE = ["page lists itself", "pages in a cycle", "page lists its own node again", "absurd depth",
              "key outside the cube", "absurd count", "negative count", "span 0", "negative span", "flat cube",
              "inverted cube", "infinite bounds", "bounds of 1e308", "bounds beyond the coordinate limit",
              "a cube of 1e-300", "boundsConforming outside the cube", "srs wkt a list"]


@pytest.mark.parametrize("how", EPT_DAMAGE)
def test_a_damaged_ept_hierarchy_is_one_line_at_once(files, tmp_path, how):
    import shutil

    e = tmp_path / "e"
    shutil.copytree(files["EPT"].parent, e)
    _ept_damage(e, how)
    exc = _within(10, lambda: read_index(e / "ept.json"))
    assert isinstance(exc, InputError), exc
    assert str(exc).startswith(str(e / "ept.json")) and "\n" not in str(exc), exc


def _copc_damage(path, how: str) -> None:
    """Rewrite one entry of the root hierarchy page of the COPC file at ``path`` in place."""
    import struct

    import laspy

    with laspy.CopcReader.open(str(path)) as r:
        root_off, root_size = r.copc_info.hierarchy_root_offset, r.copc_info.hierarchy_root_size
        info = r.header.vlrs[0]
    data = bytearray(path.read_bytes())
    entries = {}
    for at in range(root_off, root_off + root_size, 32):
        key = struct.unpack_from("<iiii", data, at)
        entries[key] = at
    child = next(k for k in sorted(entries) if k[0] == 1)
    if how == "page lists itself":
        struct.pack_into("<Qii", data, entries[(0, 0, 0, 0)] + 16, root_off, root_size, -1)
    elif how == "pages in a cycle":  # a child's page is the root page, which lists the root again
        struct.pack_into("<Qii", data, entries[child] + 16, root_off, root_size, -1)
    elif how == "absurd depth":
        struct.pack_into("<iiii", data, entries[child], 40, 0, 0, 0)
    elif how == "negative count":
        struct.pack_into("<i", data, entries[child] + 28, -9)
    elif how == "absurd page size":
        struct.pack_into("<Qii", data, entries[child] + 16, 0, 2**31 - 32, -1)
    elif how in ("zero halfsize", "zero spacing"):
        # the COPC info VLR's record: center x, y, z, halfsize, spacing (float64 each), after its 54-byte header
        vlr = data.find(b"copc") - 2
        field = 3 if how == "zero halfsize" else 4
        at = vlr + 54 + 8 * field
        assert struct.unpack_from("<d", data, at)[0] == pytest.approx(info.halfsize if field == 3 else info.spacing)
        struct.pack_into("<d", data, at, 0.0)
    elif how.startswith("halfsize "):
        at = data.find(b"copc") - 2 + 54 + 8 * 3
        assert struct.unpack_from("<d", data, at)[0] == pytest.approx(info.halfsize)
        struct.pack_into("<d", data, at, float(how.split()[1]))
    elif how == "centre and halfsize 1e308":  # centre + halfsize is inf
        at = data.find(b"copc") - 2 + 54
        struct.pack_into("<dddd", data, at, 1e308, 0.0, 0.0, 1e308)
    elif how == "a chunk of a sibling":  # another node's offset and size: its points meshed twice, silently
        # (the sibling holds at least as many points, so the chunk decompresses without an error)
        nodes = sorted((struct.unpack_from("<i", data, at + 28)[0], k) for k, at in entries.items()
                       if k[0] == 1 and struct.unpack_from("<i", data, at + 28)[0] > 0)
        (_, victim), (_, other) = nodes[0], nodes[-1]
        offset, size, _ = struct.unpack_from("<Qii", data, entries[other] + 16)
        struct.pack_into("<Qi", data, entries[victim] + 16, offset, size)
    elif how == "a chunk in the header":
        struct.pack_into("<Q", data, entries[child] + 16, 100)
    elif how == "a chunk past the file":
        struct.pack_into("<Q", data, entries[child] + 16, len(data) - 10)
    path.write_bytes(bytes(data))


COPC_DAMAGE = ["page lists itself", "pages in a cycle", "absurd depth", "negative count", "absurd page size",
               "zero halfsize", "zero spacing", "halfsize 1e308", "halfsize 8.9e307", "a chunk of a sibling",
               "a chunk in the header", "a chunk past the file"]


@pytest.mark.parametrize("how", COPC_DAMAGE)
def test_a_damaged_copc_hierarchy_is_one_line_at_once(files, tmp_path, how):
    import shutil

    c = tmp_path / "d.copc.laz"
    shutil.copy(files["COPC"], c)
    _copc_damage(c, how)
    exc = _within(10, lambda: read_index(c))
    assert isinstance(exc, InputError), exc
    assert str(exc).startswith(str(c)) and "\n" not in str(exc), exc


def _damaged(files, tmp_path, kind: str, how: str) -> str:
    """A copy of the test's EPT or COPC file, damaged as ``how`` says; its path."""
    import shutil

    if kind == "EPT":
        shutil.copytree(files["EPT"].parent, tmp_path / "e")
        _ept_damage(tmp_path / "e", how)
        return str(tmp_path / "e" / "ept.json")
    shutil.copy(files["COPC"], tmp_path / "d.copc.laz")
    _copc_damage(tmp_path / "d.copc.laz", how)
    return str(tmp_path / "d.copc.laz")


def _cli(capsys, *args) -> tuple[int, list[str]]:
    from tiled_gridpull.pipeline.cli import main

    code = main(["reconstruct", *args])
    return code, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


@pytest.mark.parametrize("kind, how, says", [
    ("EPT", "bounds of 1e308", "beyond +-1e+150"),
    ("EPT", "bounds beyond the coordinate limit", "beyond +-1e+150"),
    ("EPT", "a cube of 1e-300", "spans 1e-300 units"),
    ("EPT", "boundsConforming outside the cube", "'boundsConforming' reaches outside the cube"),
    ("EPT", "srs wkt a list", "'wkt' is a JSON list, not a string"),
    ("COPC", "halfsize 1e308", "beyond +-1e+150"),
    ("COPC", "halfsize 8.9e307", "beyond +-1e+150"),
    ("COPC", "centre and halfsize 1e308", "not finite"),
    ("COPC", "a chunk of a sibling", "overlap"),
    ("COPC", "a chunk in the header", "not within the point data"),
    ("COPC", "a chunk past the file", "not within the point data"),
])
def test_a_damaged_index_is_refused_alike_by_the_dry_run_and_the_run(files, tmp_path, capsys, kind, how, says):
    """Each of these passed the header checks: the dry run planned (an extent of 1e308 - -1e308 with numpy's
    overflow warnings, a cube of 1e-300) and the run failed with several lines; a chunk shared with a sibling and
    a non-string WKT (written into the PLY as a Python list) went through. Now: one line, exit 3, nothing written,
    in the dry run and the run alike."""
    src = _damaged(files, tmp_path, kind, how)
    out = tmp_path / "x.ply"
    import warnings

    for extra in (["--dry-run"], ["-q", "--workers", "1"]):
        with warnings.catch_warnings(record=True) as seen:  # numpy's overflow warnings are lines on stderr
            warnings.simplefilter("always")
            code, err = _cli(capsys, src, "-o", str(out), "--voxel-size", "0.5", *extra)
        assert not [w for w in seen if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in seen]
        assert code == 3 and len(err) == 1 and says in err[0], (extra, err)
        assert not out.exists() and not list(tmp_path.glob("x.*"))


def test_a_non_string_wkt_beside_another_input_is_one_line(files, tmp_path, capsys):
    """Two inputs compare their CRS: a WKT that is a JSON list made it an internal error (TypeError, exit 1)."""
    src = _damaged(files, tmp_path, "EPT", "srs wkt a list")
    code, err = _cli(capsys, str(files["EPT"]), src, "-o", str(tmp_path / "x.ply"), "--voxel-size", "0.5", "--dry-run")
    assert code == 3 and len(err) == 1 and "'wkt' is a JSON list" in err[0], err


def test_points_outside_the_declared_bounds_are_refused(files, tmp_path, capsys):
    """An EPT's boundsConforming is the extent of its points, and a plan is made from it: shrunk to a tiny box
    inside the cube while the points span 60 m, the dry run and the run both exited 0 and the mesh was cut to
    the tiles around that box. Points read beyond the declared bounds (by more than the coordinates' step) are a
    damaged index: one line, exit 3."""
    import shutil

    e = tmp_path / "e"
    shutil.copytree(files["EPT"].parent, e)
    meta = json.loads((e / "ept.json").read_text())
    c = [(a + b) / 2 for a, b in zip(meta["boundsConforming"][:3], meta["boundsConforming"][3:])]
    meta["boundsConforming"] = c + [v + 1e-300 for v in c]
    (e / "ept.json").write_text(json.dumps(meta))
    read_index(e / "ept.json")  # the header alone is consistent
    out = tmp_path / "x.ply"
    for extra in (["--dry-run"], ["-q", "--workers", "1"]):
        code, err = _cli(capsys, str(e / "ept.json"), "-o", str(out), "--voxel-size", "0.5", *extra)
        assert code == 3 and len(err) == 1 and "lies outside the bounds its header declares" in err[0], (extra, err)
        assert not out.exists()
    # the points of an intact index are all within its bounds, to the step of its coordinates
    for kind in ("EPT", "EPT binary", "COPC"):
        ix = read_index(files[kind])
        assert sum(len(p) for p in read_box(ix, ix.bounds[0] - 1, ix.bounds[1] + 1)) == ix.points
