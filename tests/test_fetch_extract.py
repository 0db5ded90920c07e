"""What `seasynth fetch` unpacks (seasynth.service.fetch.extract): plain relative files only. Members with `..`, absolute or
empty paths, links, directories and devices are refused with the member named, and nothing lands outside OUT."""

import io
import tarfile

import pytest

from seasynth.service.errors import OutputError
from seasynth.service.fetch import IntegrityError, extract


def tar_with(path, *members):
    """members: (TarInfo, bytes | None)."""
    with tarfile.open(path, "w") as tar:
        for info, data in members:
            if data is not None:
                info.size = len(data)
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


def file_member(name: str, data: bytes = b"x"):
    return tarfile.TarInfo(name), data


def special(name: str, kind: bytes, target: str = ""):
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, target
    return info, None


def test_a_plain_tar_extracts_exactly(tmp_path):
    tar = tar_with(tmp_path / "ok.tar", file_member("image_2/000000.png", b"png"), file_member("calib/000000.txt",
                                                                                                 b"P2: 1"))
    out = tmp_path / "out"
    assert extract(tar, out) == 2
    assert (out / "image_2/000000.png").read_bytes() == b"png" and (out / "calib/000000.txt").read_bytes() == b"P2: 1"
    assert sorted(p.name for p in out.rglob("*") if p.is_file()) == ["000000.png", "000000.txt"]  # no .part left


@pytest.mark.parametrize("member, why", [
    (file_member(".seasynth-fetch/shard-000001.tar.done", b"0" * 64), "would overwrite the fetch's own"),
    (file_member("manifest.json", b"{}"), "would overwrite the fetch's own"),
    (file_member("../evil.txt"), "not a plain relative path"),
    (file_member("image_2/../../evil.txt"), "not a plain relative path"),
    (file_member("/tmp/evil.txt"), "not a plain relative path"),
    (file_member("./image_2/a.png"), "not a plain relative path"),
    (file_member("image_2//a.png"), "not a plain relative path"),
    (special("image_2/link.png", tarfile.SYMTYPE, "/etc/passwd"), "not a regular file"),
    (special("image_2/hard.png", tarfile.LNKTYPE, "../../etc/passwd"), "not a regular file"),
    (special("image_2", tarfile.DIRTYPE), "not a regular file"),
    (special("image_2/fifo", tarfile.FIFOTYPE), "not a regular file"),
    (special("image_2/dev", tarfile.CHRTYPE), "not a regular file"),
], ids=["state", "manifest", "dotdot", "inner-dotdot", "absolute", "dot", "empty-part", "symlink", "hardlink", "directory", "fifo",
        "device"])
def test_hostile_members_are_refused_and_nothing_lands_outside(tmp_path, member, why):
    tar = tar_with(tmp_path / "bad.tar", member)
    out = tmp_path / "deep" / "out"
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(IntegrityError, match=why) as err:
        extract(tar, out, "datasets/d/shards/shard-000007.tar")
    assert str(err.value).startswith("datasets/d/shards/shard-000007.tar: member ")  # names the shard
    assert repr(member[0].name) in str(err.value)
    after = sorted(tmp_path.rglob("*"))
    assert [p for p in after if p not in before and out not in p.parents and p != out and p not in out.parents] == []
    assert not out.exists() or [p for p in out.rglob("*") if p.is_file()] == []


def test_a_member_that_cannot_be_written_is_an_output_error_naming_it_and_leaves_no_part(tmp_path):
    tar = tar_with(tmp_path / "ok.tar", file_member("image_2/000000.png", b"png"))
    out = tmp_path / "out"
    (out / "image_2" / "000000.png").mkdir(parents=True)  # in the way: the rename onto it fails
    with pytest.raises(OutputError, match=r"000000.png: cannot write image_2/000000.png of shard-000003.tar"):
        extract(tar, out, "shard-000003.tar")
    assert [p.name for p in (out / "image_2").iterdir()] == ["000000.png"]  # no .part left beside it
