"""benchmarks.results_data: the results folders' run data packed in data.tar.xz, real files."""

import io
import tarfile
from pathlib import Path

import pytest

from benchmarks import results_data as rd


def make_folder(root: Path) -> Path:
    f = root / "gpu_sX"
    (f / "runs" / "blocks").mkdir(parents=True)
    (f / "runs" / "blocks" / "error_vs_time.json").write_text('{"psnr": 31.5}')
    (f / "runs" / "blocks" / "metrics.jsonl").write_text('{"step": 1}\n{"step": 2}\n')
    (f / "job.log").write_text("[12:00] start\n")
    (f / "README.md").write_text("# kept unpacked\n")
    return f


def test_pack_then_unpack_restores_every_data_file_and_nothing_else(tmp_path, capsys):
    f = make_folder(tmp_path)
    before = {n: p.read_bytes() for n, p in rd.data_files(f).items()}
    assert rd.main(["pack", str(f)]) == 0
    archive = f / rd.ARCHIVE
    assert sorted(rd.read_archive(archive)) == sorted(before)  # README.md is not in it
    first = archive.read_bytes()
    assert rd.main(["pack", str(f)]) == 0 and archive.read_bytes() == first  # deterministic
    for p in rd.data_files(f).values():
        p.unlink()
    assert rd.main(["unpack", "--root", str(tmp_path)]) == 0  # every archived folder
    assert {n: p.read_bytes() for n, p in rd.data_files(f).items()} == before
    assert "3 files written" in capsys.readouterr().out
    assert rd.main(["list", str(f)]) == 0
    assert str(f / "job.log") in capsys.readouterr().out


def test_pack_keeps_archived_files_no_longer_on_disk_and_disk_wins(tmp_path):
    f = make_folder(tmp_path)
    rd.pack(f)
    (f / "job.log").unlink()
    (f / "runs" / "blocks" / "error_vs_time.json").write_text('{"psnr": 32.0}')
    (f / "extra.json").write_text("{}")
    assert rd.pack(f) == 4
    members = rd.read_archive(f / rd.ARCHIVE)
    assert members["job.log"] == b"[12:00] start\n"
    assert members["runs/blocks/error_vs_time.json"] == b'{"psnr": 32.0}'


def test_unpack_never_replaces_a_differing_file_unless_forced(tmp_path, capsys):
    f = make_folder(tmp_path)
    rd.pack(f)
    p = f / "runs" / "blocks" / "error_vs_time.json"
    p.write_text("edited")
    (f / "job.log").unlink()
    assert rd.main(["unpack", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "differs" in err and "--force" in err
    assert p.read_text() == "edited" and not (f / "job.log").exists()  # nothing written
    assert rd.main(["unpack", "--force", str(f)]) == 0
    assert p.read_text() == '{"psnr": 31.5}' and (f / "job.log").exists()


@pytest.mark.parametrize("name", ["../escape.json", "/abs.json"])
def test_a_member_outside_its_folder_is_refused(tmp_path, capsys, name):
    f = tmp_path / "gpu_sY"
    f.mkdir()
    with tarfile.open(f / rd.ARCHIVE, "w:xz") as tar:
        info = tarfile.TarInfo(name)  # as written, leading "/" kept (tar.add would strip it)
        info.size = 2
        tar.addfile(info, io.BytesIO(b"{}"))
    assert rd.main(["unpack", str(f)]) == 2
    assert "outside its folder" in capsys.readouterr().err
    assert not (tmp_path / "escape.json").exists() and not Path("/abs.json").exists()


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    f = tmp_path / "gpu_sZ"
    f.mkdir()
    (f / rd.ARCHIVE).write_bytes(b"not xz")
    cases = [
        ["unpack", str(f)],  # a broken archive
        ["pack"],  # no folder named
        ["pack", str(tmp_path / "missing")],
        ["list", str(tmp_path)],  # a folder without an archive
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    cases.append(["pack", str(empty)])  # nothing to pack: no archive written
    for argv in cases:
        assert rd.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("results_data: error:") and "\n" not in err, argv
    assert not (empty / rd.ARCHIVE).exists()
    assert (f / rd.ARCHIVE).read_bytes() == b"not xz"


def test_the_repositorys_archives_read_and_stay_small():
    archives = sorted(rd.ROOT.glob(f"*/{rd.ARCHIVE}"))
    assert archives, "benchmarks/results has no data archive"
    for a in archives:
        assert a.stat().st_size < 2 * 2**20, a  # the house's 2 MiB rule per data file
        members = rd.read_archive(a)
        assert members and all(Path(n).suffix in rd.SUFFIXES for n in members), a


def test_a_write_that_fails_is_one_line_and_leaves_what_was_there(tmp_path, capsys):
    f = make_folder(tmp_path)
    rd.pack(f)
    before = (f / rd.ARCHIVE).read_bytes()
    p = f / "job.log"
    p.unlink()
    p.mkdir()  # a folder where the archive has a file: the unpack cannot write it
    assert rd.main(["unpack", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("results_data: error:") and "\n" not in err and "job.log" in err
    assert p.is_dir() and not any(p.iterdir()) and (f / rd.ARCHIVE).read_bytes() == before
    assert not list(f.rglob("*.tmp"))  # no temporary file left behind
