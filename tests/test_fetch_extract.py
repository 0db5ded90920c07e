"""What `seasynth fetch` unpacks (service.fetch.extract): plain relative files only. Members with `..`, absolute or
empty paths, links, directories and devices are refused with the member named, and nothing lands outside OUT."""

import io
import tarfile

import pytest

from service.fetch import IntegrityError, extract


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
], ids=["dotdot", "inner-dotdot", "absolute", "dot", "empty-part", "symlink", "hardlink", "directory", "fifo",
        "device"])
def test_hostile_members_are_refused_and_nothing_lands_outside(tmp_path, member, why):
    tar = tar_with(tmp_path / "bad.tar", member)
    out = tmp_path / "deep" / "out"
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(IntegrityError, match=why) as err:
        extract(tar, out)
    assert repr(member[0].name) in str(err.value)
    after = sorted(tmp_path.rglob("*"))
    assert [p for p in after if p not in before and out not in p.parents and p != out and p not in out.parents] == []
    assert not out.exists() or [p for p in out.rglob("*") if p.is_file()] == []
