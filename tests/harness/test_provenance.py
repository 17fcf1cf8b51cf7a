import hashlib
import subprocess

from harness import provenance


def _tree(root):
    for pkg in provenance.PACKAGES:
        (root / pkg / "__pycache__").mkdir(parents=True)
        (root / pkg / "__init__.py").write_text(f"# {pkg}\n")
        (root / pkg / "__pycache__" / "x.cpython-311.pyc").write_bytes(b"\0compiled")
    (root / "harness" / "templates").mkdir()
    (root / "harness" / "templates" / "a.j2").write_text("{{ x }}")
    (root / "README.md").write_text("not a package file")


def test_digest_covers_the_packages_files_by_path_and_bytes(tmp_path):
    _tree(tmp_path)
    files = ["harness/__init__.py", "harness/templates/a.j2", "models/__init__.py", "simulator/__init__.py"]
    assert [p.as_posix() for p in provenance.source_files(tmp_path)] == files
    ref = hashlib.sha256()
    for f in files:
        data = (tmp_path / f).read_bytes()
        ref.update(f.encode() + b"\0" + str(len(data)).encode() + b"\0" + data)
    digest = provenance.source_digest(tmp_path)
    assert digest == ref.hexdigest()
    (tmp_path / "README.md").write_text("changed")  # outside the packages
    (tmp_path / "models" / "__pycache__" / "x.cpython-311.pyc").write_bytes(b"other")
    assert provenance.source_digest(tmp_path) == digest
    (tmp_path / "models" / "__init__.py").write_text("# models, changed\n")
    assert provenance.source_digest(tmp_path) != digest


def test_record_and_compare(tmp_path):
    _tree(tmp_path)
    rec = provenance.record(tmp_path)
    assert rec == {"commit": None, "sources_sha256": provenance.source_digest(tmp_path)}  # not a git checkout
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q",
                    "--allow-empty", "-m", "x"], check=True)
    commit = provenance.git_commit(tmp_path)
    assert commit and len(commit) == 40
    rec = provenance.record(tmp_path)
    text = provenance.compare(rec, rec["sources_sha256"])
    assert f"commit {commit[:10]}" in text and "matched" in text and rec["sources_sha256"][:16] in text
    assert "differed" in provenance.compare(rec, "0" * 64)
    assert "does not record" in provenance.compare(None) and "does not record" in provenance.compare({"commit": "a"})
