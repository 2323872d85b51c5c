"""rtsgt.io.output_dir: directories written whole, replaced only when rtsgt wrote them."""

from __future__ import annotations

import json
import os

import pytest

from rtsgt.errors import InputError
from rtsgt.io.output_dir import (
    MANIFEST,
    OutputDir,
    check_output_file,
    check_target,
    foreign_files,
    record_files,
)


def write_output(target, files: dict[str, str], *, force: bool = False, kind: str = "test"):
    with OutputDir(target, kind, force=force) as tmp:
        for name, text in files.items():
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp / name).write_text(text)
    return target


def test_manifest_lists_every_file_written(tmp_path):
    out = write_output(tmp_path / "o", {"a.txt": "1", "sub/b.txt": "2"})
    doc = json.loads((out / MANIFEST).read_text())
    assert doc["written_by"] == "rtsgt" and doc["kind"] == "test"
    assert doc["files"] == ["a.txt", "sub/b.txt"]
    assert foreign_files(out) == []


def test_a_failure_leaves_nothing_and_keeps_the_earlier_output(tmp_path):
    out = write_output(tmp_path / "o", {"a.txt": "old"})
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with OutputDir(out, "test", force=True) as tmp:
                (tmp / "a.txt").write_text("new")
                raise exc
        assert (out / "a.txt").read_text() == "old"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]


def test_force_replaces_only_what_rtsgt_wrote(tmp_path):
    out = write_output(tmp_path / "o", {"a.txt": "1"})
    with pytest.raises(InputError, match="not empty; use --force"):
        write_output(out, {"a.txt": "2"})
    write_output(out, {"b.txt": "2"}, force=True)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "b.txt"]
    (out / "sub").mkdir()
    (out / "sub" / "user.dat").write_text("x")
    assert foreign_files(out) == [out / "sub" / "user.dat"]
    with pytest.raises(InputError, match="sub/user.dat, which rtsgt did not write"):
        write_output(out, {"c.txt": "3"}, force=True)
    assert (out / "sub" / "user.dat").read_text() == "x"


def test_nested_outputs_count_as_rtsgt_files(tmp_path):
    out = write_output(tmp_path / "o", {"a.txt": "1"})
    write_output(out / "analysis", {"fig.png": "png"})  # written later, into the output
    assert foreign_files(out) == []
    write_output(out, {"a.txt": "2"}, force=True)
    assert not (out / "analysis").exists()


def test_a_manifest_that_is_not_rtsgt_protects_nothing(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "data.csv").write_text("1")
    for text in ("not json", json.dumps({"written_by": "someone", "files": ["data.csv"]}),
                 json.dumps({"written_by": "rtsgt", "files": "data.csv"})):
        (out / MANIFEST).write_text(text)
        assert out / "data.csv" in foreign_files(out)
        with pytest.raises(InputError, match="which rtsgt did not write"):
            check_target(out, force=True)


def test_symbolic_links_are_foreign_and_never_followed(tmp_path):
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("x")
    out = write_output(tmp_path / "o", {"a.txt": "1"})
    (out / "link").symlink_to(precious, target_is_directory=True)
    assert foreign_files(out) == [out / "link"]
    with pytest.raises(InputError, match="link, which rtsgt did not write"):
        check_target(out, force=True)
    assert (precious / "thesis.tex").read_text() == "x"
    target = tmp_path / "to-precious"
    target.symlink_to(precious, target_is_directory=True)
    with pytest.raises(InputError, match="not a directory"):
        check_target(target, force=True)


def test_working_directory_and_inputs_are_never_replaced(tmp_path, monkeypatch):
    out = write_output(tmp_path / "o", {"a.txt": "1", "sub/b.txt": "2"})
    monkeypatch.chdir(out / "sub")
    with pytest.raises(InputError, match="current working directory"):
        check_target(out, force=True)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="holds an input"):
        check_target(out, force=True, inputs=[out / "a.txt"])
    assert check_target(out, force=True) == out


def test_empty_directory_and_missing_parents(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    write_output(empty, {"a.txt": "1"})  # an empty directory needs no --force
    deep = tmp_path / "x" / "y" / "z"
    write_output(deep, {"a.txt": "1"})
    assert (deep / "a.txt").is_file()
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        write_output(f, {"a.txt": "1"}, force=True)


def test_record_files_and_single_file_outputs(tmp_path):
    out = write_output(tmp_path / "o", {"a.txt": "1"})
    (out / "report.html").write_text("<p>report</p>")
    assert foreign_files(out) == [out / "report.html"]
    record_files(out, [out / "report.html"])
    assert foreign_files(out) == []

    def never(head: str) -> bool:
        return False

    # a file listed in its folder's manifest may be replaced; an unknown one may not
    assert check_output_file(out / "report.html", option="--out", written_by_rtsgt=never)
    user = tmp_path / "user.html"
    user.write_text("<p>mine</p>")
    with pytest.raises(InputError, match="not an output of rtsgt"):
        check_output_file(user, option="--out", written_by_rtsgt=never)
    assert check_output_file(user, option="--out", written_by_rtsgt=lambda h: "mine" in h)
    with pytest.raises(InputError, match="names an input"):
        check_output_file(user, option="--out", written_by_rtsgt=lambda h: True, inputs=[user])
    with pytest.raises(InputError, match="names a directory"):
        check_output_file(out, option="--out", written_by_rtsgt=never)


def test_directories_are_made_with_the_umask(tmp_path):
    old = os.umask(0o077)
    try:
        out = write_output(tmp_path / "o", {"sub/a.txt": "1"})
    finally:
        os.umask(old)
    assert out.stat().st_mode & 0o777 == 0o700
    old = os.umask(0o002)
    try:
        out = write_output(tmp_path / "p", {"a.txt": "1"})
    finally:
        os.umask(old)
    assert out.stat().st_mode & 0o777 == 0o775


def test_a_table_is_written_in_pieces_with_the_text_of_the_whole(tmp_path):
    """``write_csv`` streams a large table a few thousand rows at a time
    (:func:`rtsgt.io._parse.table_chunks`): the file holds exactly the whole table's text,
    and a failing piece leaves nothing (the target untouched, no temporary file)."""
    import numpy as np

    from rtsgt.io._parse import atomic_write_bytes, table_chunks, table_text
    from rtsgt.io.run_dir import write_csv

    a = np.random.default_rng(3).standard_normal((10_001, 5)) * 1e-7
    pieces = list(table_chunks(a, header="a,b,c,d,e", fmt="%.17g", rows=4096))
    assert len(pieces) == 1 + 3  # the header, then ceil(10001 / 4096) blocks
    assert "".join(table_chunks(a, header="a,b,c,d,e", fmt="%.17g")) == "".join(pieces)
    path = tmp_path / "t.csv"
    write_csv(path, list("abcde"), [a[:, :2], a[:, 2], a[:, 3:]])  # columns in three parts
    assert path.read_text() == "".join(pieces) == table_text(a, header="a,b,c,d,e",
                                                             fmt="%.17g")
    np.testing.assert_array_equal(np.loadtxt(path, delimiter=",", skiprows=1), a)

    def failing():
        yield b"1,2\n"
        raise OSError("disk full")

    with pytest.raises(OSError):
        atomic_write_bytes(path, failing())
    assert path.read_text() == "".join(pieces)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]
