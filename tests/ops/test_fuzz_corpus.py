"""scripts/fuzz-corpus: the fuzz corpora kept as one archive (fuzz/corpus.zip), which
tests/fuzz_regressions.rs replays and `make fuzz` unpacks."""

from __future__ import annotations

import subprocess
import sys
import zipfile

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "fuzz-corpus"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True)


def test_pack_and_unpack_round_trip_with_the_same_bytes(tmp_path):
    src = tmp_path / "corpus"
    for target, name, data in [("exr_frame", "a", b"\x00\x01"), ("exr_frame", "b", b"x" * 5000),
                               ("http_submit", "c", b"POST")]:
        (src / target).mkdir(parents=True, exist_ok=True)
        (src / target / name).write_bytes(data)
    one, two = tmp_path / "one.zip", tmp_path / "two.zip"
    assert run("pack", str(src), str(one)).returncode == 0
    assert run("pack", str(src), str(two)).returncode == 0
    assert one.read_bytes() == two.read_bytes(), "the same corpus packs to the same bytes"
    with zipfile.ZipFile(one) as z:
        assert z.namelist() == ["exr_frame/a", "exr_frame/b", "http_submit/c"]
    out = tmp_path / "out"
    assert run("unpack", str(one), str(out)).returncode == 0
    assert (out / "exr_frame" / "b").read_bytes() == b"x" * 5000
    assert (out / "http_submit" / "c").read_bytes() == b"POST"


def test_unpack_refuses_entries_outside_the_folder(tmp_path):
    bad = tmp_path / "bad.zip"
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr("../escape", b"x")
    r = run("unpack", str(bad), str(tmp_path / "out"))
    assert r.returncode != 0 and "leaves the corpus folder" in r.stderr
    assert not (tmp_path / "escape").exists()


def test_the_committed_archive_holds_every_target():
    with zipfile.ZipFile(ROOT / "fuzz" / "corpus.zip") as z:
        targets = {n.split("/", 1)[0] for n in z.namelist()}
    assert targets == {"exr_frame", "http_submit", "grpc_chunks"}
