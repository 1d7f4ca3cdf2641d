"""JSON-lines files and manifests (files.py): the tolerant reader, the appenders that
drop a cut line, atomic replacement, and the training view of a manifest."""

import json
import logging
import multiprocessing

import pytest

from mcdenoise_train.data import manifest_frames
from mcdenoise_train.files import (
    append_jsonl,
    append_manifest,
    atomic_path,
    open_append,
    read_jsonl,
    read_manifest,
    write_jsonl,
)

ROWS = [{"step": 1, "loss": 0.5}, {"step": 2, "loss": 0.25}]


def _lines(*rows) -> str:
    return "".join(json.dumps(r) + "\n" for r in rows)


def test_read_jsonl_round_trip_and_blank_lines(tmp_path):
    p = tmp_path / "log.jsonl"
    write_jsonl(p, ROWS)
    assert read_jsonl(p) == ROWS
    p.write_text(_lines(ROWS[0]) + "\n  \n" + _lines(ROWS[1]))
    assert read_jsonl(p) == ROWS
    p.write_text(_lines(ROWS[0]) + json.dumps(ROWS[1]))  # a whole last record without its newline
    assert read_jsonl(p) == ROWS


def test_read_jsonl_skips_a_cut_last_line(tmp_path, caplog):
    p = tmp_path / "manifest.jsonl"
    p.write_text(_lines(*ROWS) + '{"step": 3, "lo')
    with caplog.at_level(logging.INFO, logger="mcdenoise_train.files"):
        assert read_jsonl(p) == ROWS
    assert "cut last line 3" in caplog.text
    p.write_bytes(_lines(*ROWS).encode() + '{"scene": "caf\u00e9'.encode()[:-1])  # cut inside a UTF-8 character
    assert read_jsonl(p) == ROWS


@pytest.mark.parametrize("bad", ['{"step": 3, "lo', "not json", '{"scene": "a"}{"scene": "b"}'])
def test_read_jsonl_reports_a_corrupt_middle_line(tmp_path, bad):
    p = tmp_path / "manifest.jsonl"
    p.write_text(_lines(ROWS[0]) + bad + "\n" + _lines(ROWS[1]))
    with pytest.raises(ValueError, match=r"manifest\.jsonl, line 2: not a JSON record"):
        read_jsonl(p)
    # a corrupt last line that has its newline was written whole: corruption, not a cut
    p.write_text(_lines(*ROWS) + bad + "\n")
    with pytest.raises(ValueError, match="line 3"):
        read_jsonl(p)


def test_missing_files(tmp_path):
    assert read_jsonl(tmp_path / "none.jsonl", missing_ok=True) == []
    assert read_manifest(tmp_path, missing_ok=True) == []
    with pytest.raises(FileNotFoundError):
        read_jsonl(tmp_path / "none.jsonl")


def test_appenders_drop_a_cut_line_and_keep_a_whole_one(tmp_path):
    p = tmp_path / "val.jsonl"
    p.write_text(_lines(ROWS[0]) + '{"step": 2, "lo')  # interrupted mid-append
    append_jsonl(p, ROWS[1])
    assert p.read_text() == _lines(*ROWS)
    p.write_text(json.dumps(ROWS[0]))  # whole, only the newline missing: kept
    append_jsonl(p, ROWS[1])
    assert read_jsonl(p) == ROWS
    log = tmp_path / "log.jsonl"
    log.write_text(_lines(ROWS[0]) + '{"ste')
    with open_append(log) as f:
        f.write(json.dumps(ROWS[1]) + "\n")
    assert read_jsonl(log) == ROWS
    m = tmp_path / "manifest.jsonl"
    m.write_text(_lines({"scene": "a"}) + '{"scene": "b", "fra')
    append_manifest(m, {"scene": "b", "complete": True})
    assert read_manifest(tmp_path) == [{"scene": "a"}, {"complete": True, "scene": "b"}]


def _append_many(path, worker):
    for i in range(50):
        append_manifest(path, {"worker": worker, "i": i, "pad": "x" * 500})


def test_workers_append_whole_lines(tmp_path):
    p = tmp_path / "manifest.jsonl"
    procs = [multiprocessing.get_context("fork").Process(target=_append_many, args=(p, w)) for w in range(2)]
    for pr in procs:
        pr.start()
    for pr in procs:
        pr.join()
    recs = read_manifest(p)
    assert len(recs) == 100 and sorted((r["worker"], r["i"]) for r in recs) == [(w, i) for w in range(2) for i in range(50)]


def test_atomic_path_keeps_the_old_file_when_the_write_fails(tmp_path):
    p = tmp_path / "f.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("interrupted")
    assert p.read_text() == "old" and [x.name for x in tmp_path.iterdir()] == ["f.txt"]
    with atomic_path(p) as tmp:
        open(tmp, "w").write("new")
    assert p.read_text() == "new" and [x.name for x in tmp_path.iterdir()] == ["f.txt"]


def test_manifest_frames_tolerates_a_cut_line_and_keeps_the_last_record(tmp_path):
    rec = {"scene": "s", "seed": 1, "split": "val", "complete": True,
           "frames": {"4": {"path": "val/s/s-spp4.exr"}, "ref": {"path": "val/s/s-ref.exr"}}}
    again = {**rec, "frames": {**rec["frames"], "8": {"path": "val/s/s-spp8.exr", "renderer": "cycles"}}}
    (tmp_path / "manifest.jsonl").write_text(_lines(rec, again) + '{"scene": "t", "fr')
    frames = manifest_frames(tmp_path)
    assert [(f["scene"], f["spp"], f["split"]) for f in frames] == [("s", 4, "val"), ("s", 8, "val")]
    assert frames[1]["noisy"] == str(tmp_path / "val/s/s-spp8.exr")
    assert frames[1]["reference"] == str(tmp_path / "val/s/s-ref.exr")
    # The frame's renderer where the generator recorded it.
    assert frames[1]["renderer"] == "cycles" and "renderer" not in frames[0]
