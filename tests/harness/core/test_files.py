import hashlib

import pytest

from harness.core.files import atomic_write_text, remove_temp_files, sha256_file


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    p = atomic_write_text(tmp_path / "x.txt", "old")
    import os
    monkeypatch.setattr(os, "replace", lambda *a: (_ for _ in ()).throw(OSError("disk full")))
    with pytest.raises(OSError):
        atomic_write_text(p, "new")
    assert p.read_text() == "old" and len(list(tmp_path.iterdir())) == 1


def test_atomic_write_errors_name_the_target_not_the_temp_file(tmp_path, monkeypatch):
    import errno
    import os
    import tempfile
    target = tmp_path / "results.json"

    def refuse(dir, prefix, suffix):  # as mkstemp in a read-only folder (the tests may run as root)
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(dir, prefix + "abcd1234" + suffix))
    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkstemp", refuse)
        with pytest.raises(PermissionError) as e:
            atomic_write_text(target, "x")
    assert e.value.filename == str(target) and e.value.errno == errno.EACCES
    monkeypatch.setattr(os, "replace", lambda *a: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left")))
    with pytest.raises(OSError) as e:
        atomic_write_text(target, "x")
    assert e.value.filename == str(target) and e.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    import os
    umask = os.umask(0)
    os.umask(umask)
    p = atomic_write_text(tmp_path / "mode.txt", "x")
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask


def test_remove_temp_files_leaves_targets_and_other_hidden_files(tmp_path):
    (tmp_path / "sub").mkdir()
    left = [tmp_path / ".a.json.ab12cd34.tmp", tmp_path / "sub" / ".b.bin.zz_9yx87.tmp"]
    kept = [tmp_path / "a.json", tmp_path / ".lock", tmp_path / ".notes.tmp"]
    for p in left + kept:
        p.write_text("x")
    assert remove_temp_files(tmp_path) == sorted(left)
    assert all(p.is_file() for p in kept) and not any(p.exists() for p in left)


def test_sha256_file_is_the_digest_of_the_bytes(tmp_path):
    data = bytes(range(256)) * 5000  # more than one 1 MiB chunk
    p = tmp_path / "x.bin"
    p.write_bytes(data)
    assert sha256_file(p) == hashlib.sha256(data).hexdigest()
