"""The streaming partition run in segments (tiled_gridpull.prepare: plan_segments, scan_segment,
partition_segment; partition.merge_segments): the same spill files, byte for byte, as one pass on the driver."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.errors import InputError
from tiled_gridpull.io import iter_point_chunks, iter_row_chunks
from tiled_gridpull.jobdir import JobPaths
from tiled_gridpull.prepare import Segment, plan_segments, prepare_job
from tiled_gridpull.synthetic.lidar_files import write_las
from tiled_gridpull.tiling import TilingConfig

TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
ORIGIN = np.array([500000.0, 4000000.0, 20.0])


def _ground(n, seed, x0=0.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 14.0, size=(n, 2)) + [x0, 0]
    return np.column_stack([xy, 0.3 * np.sin(xy[:, 0]) + 0.1 * np.cos(xy[:, 1])]) + ORIGIN


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("segments")
    n = 23_456
    times = np.repeat(np.arange(4, dtype=np.float64), -(-n // 4))[:n] + 1000.0
    laz = write_las(d / "a.laz", _ground(n, 1), gps_time=times, chunk_size=5000)
    las = write_las(d / "b.las", _ground(9000, 2, x0=10.0), gps_time=np.full(9000, 1002.5))
    np.save(d / "c.npy", _ground(4000, 3, x0=5.0))
    traj = d / "traj.csv"
    traj.write_text("time,x,y,z\n" + "".join(f"{999 + k},{500000 + 3 * k},{4000007},{22}\n" for k in range(8)))
    return {"laz": str(laz), "las": str(las), "npy": str(d / "c.npy"), "traj": str(traj), "n": n}


def _serial_map(fn, args):
    return [fn(*a) for a in args]


def _tiles(specs):
    return {s.name: (s.n_points, s.points_sha256, s.occupied_bricks, Path(s.points_path).read_bytes(),
                     Path(s.occupancy_path).read_bytes()) for s in specs}


def test_row_ranges_of_a_laz_file_join_into_the_file(files):
    whole = np.concatenate([c.xyz for c in iter_point_chunks(files["laz"], 4000)])
    parts = [c.xyz for a, b in ((0, 10_000), (10_000, 20_000), (20_000, files["n"]))
             for c in iter_row_chunks(files["laz"], a, b, 3000)]
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    with pytest.raises(InputError, match=r"rows 0:99999 are outside its 23456 points"):
        list(iter_row_chunks(files["laz"], 0, 99_999))
    with pytest.raises(InputError, match="only LAS/LAZ files are read by row ranges"):
        list(iter_row_chunks(files["npy"], 0, 10))


def test_segments_cut_las_files_at_chunk_multiples_and_keep_other_inputs_whole(files):
    segs = plan_segments([files["laz"], files["npy"], files["las"]], chunk_size=3000, segment_points=7000)
    assert segs[:4] == [Segment(files["laz"], 0, 6000), Segment(files["laz"], 6000, 12000),
                        Segment(files["laz"], 12000, 18000), Segment(files["laz"], 18000, files["n"])]
    assert segs[4] == Segment(files["npy"]) and [s.path for s in segs[5:]] == [files["las"]] * 2


@pytest.mark.parametrize("trajectory,halo", [(False, 0), (True, 0), (True, 12)])
def test_a_partition_in_segments_is_the_one_pass_byte_for_byte(files, tmp_path, trajectory, halo):
    """Also for a denoising job's exact offsets and halo counts (sensor origins included)."""
    inputs = [files["laz"], files["las"]] if trajectory else [files["laz"], files["npy"], files["las"]]
    kw = {"trajectory": files["traj"]} if trajectory else {}
    tiling = dataclasses.replace(TILING, halo=halo)
    plan_a, one, scan_a = prepare_job(inputs, tiling, JobPaths(tmp_path / "one"), **kw)
    calls = []

    def run_tasks(fn, args):
        calls.append(fn.__name__)
        return _serial_map(fn, args)

    plan_b, seg, scan_b = prepare_job(inputs, tiling, JobPaths(tmp_path / "seg"), run_tasks=run_tasks,
                                      chunk_size=2500, segment_points=5000, **kw)
    assert calls == ["scan_segment", "partition_segment"] and scan_b["segments"] >= 7
    assert plan_a.to_dict() == plan_b.to_dict() and scan_a["points"] == scan_b["points"]
    assert scan_a["has_sensor"] == scan_b["has_sensor"] == trajectory
    np.testing.assert_array_equal(scan_a["bounds"], scan_b["bounds"])
    assert len(one) >= 6 and _tiles(one) == _tiles(seg)
    assert [s.halo_points for s in one] == [s.halo_points for s in seg]
    assert all(s.exact_offsets == bool(halo) for s in one + seg) and (sum(s.halo_points for s in seg) > 0) == bool(halo)
    assert not (tmp_path / "seg" / "points" / ".segments").exists()


def test_the_budget_check_sees_the_one_pass_counts_before_anything_is_written(files, tmp_path):
    seen = {}

    def check(specs, occupancy):
        seen[len(seen)] = ({s.name: (s.n_points, s.occupied_bricks) for s in specs},
                           {k: v.tobytes() for k, v in occupancy.items()})
        assert not (tmp_path / f"j{len(seen) - 1}" / "points").exists()  # counted, nothing written

    prepare_job([files["laz"], files["npy"]], TILING, JobPaths(tmp_path / "j0"), check=check)
    prepare_job([files["laz"], files["npy"]], TILING, JobPaths(tmp_path / "j1"), check=check,
                run_tasks=_serial_map, chunk_size=2500, segment_points=5000)
    assert seen[0] == seen[1]


def test_a_damaged_segment_is_one_line_naming_the_file(files, tmp_path):
    bad = tmp_path / "bad.laz"
    data = Path(files["laz"]).read_bytes()
    bad.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match="bad.laz"):
        prepare_job([str(bad), files["npy"]], TILING, JobPaths(tmp_path / "j"), run_tasks=_serial_map,
                    chunk_size=2500, segment_points=5000)
    assert not (tmp_path / "j" / "points").exists()  # no segment's files are left behind


def test_several_files_are_partitioned_as_dask_tasks_into_the_one_pass(files, tmp_path):
    from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions

    inputs = [files["laz"], files["npy"], files["las"]]
    _, one, _ = prepare_job(inputs, TILING, JobPaths(tmp_path / "one"))
    ex = DaskExecutor(JobOptions(workers=2, progress=False))
    try:
        _, seg, scan = prepare_job(inputs, TILING, JobPaths(tmp_path / "dask"),
                                   run_tasks=lambda fn, a: ex.map(fn, a, tmp_path / "dask"))
    finally:
        ex.close()
    assert scan["segments"] == 3  # one per file
    assert _tiles(one) == _tiles(seg)
