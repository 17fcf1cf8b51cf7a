import hashlib
import os
import re
import subprocess
from pathlib import Path

import pytest

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


INTEL = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R)  Processor
flags\t\t: fpu sse sse2 sse4_2 avx avx2 fma avx512f avx512_bf16 amx_bf16

processor\t: 1
model name\t: Intel(R) Xeon(R)  Processor
flags\t\t: fpu sse sse2
"""
EPYC = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: sse4_2 avx avx2 fma\n"
ARM = "processor\t: 0\nBogoMIPS\t: 50.00\nFeatures\t: fp asimd\n"


@pytest.mark.parametrize("info, cores, fallback, expected", [
    (INTEL, 2, "", "Intel(R) Xeon(R) Processor (AVX-512, 2 cores)"),  # the first CPU's line, spaces collapsed
    (EPYC, 2, "", "AMD EPYC 7B13 (AVX2, 2 cores)"),
    ("model name: Old\nflags: sse sse2\n", 4, "", "Old (4 cores)"),
    (ARM, 8, "aarch64", "aarch64 (8 cores)"),
    ("", None, "", "unknown CPU"),
])
def test_machine_text_names_the_cpu_its_widest_vector_set_and_cores(info, cores, fallback, expected):
    assert provenance.machine_text(info, cores, fallback) == expected


def test_machine_is_this_cpu():
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    names = re.findall(r"^model name\s*:\s*(.+)$", text, flags=re.M)
    here = provenance.machine()
    assert here.endswith(f"{os.cpu_count()} cores)")
    if names:
        assert here.startswith(" ".join(names[0].split()) + " (")


def test_trained_on_counts_epochs_per_machine_in_their_order():
    history = [{"epoch": 1}, {"epoch": 2, "machine": "B"}, {"epoch": 3, "machine": "A"}, {"epoch": 4, "machine": "B"}]
    assert list(provenance.trained_on(history).items()) == [("", 1), ("B", 2), ("A", 1)]
    assert provenance.trained_on(None) == {} and provenance.trained_on([]) == {}


def _history(epochs):
    """A ``val_history`` of ``{machine: epochs}`` ("": entries that name none)."""
    return [{"epoch": 1, **({"machine": m} if m else {})} for m, n in epochs.items() for _ in range(n)]


def _summary(trainings, timed=("X",), draws=None):
    models = {name: {"train": {"val_history": _history(on)}, "runtime": {"machine": t}}
              for (name, on), t in zip(trainings.items(), list(timed) + [None] * len(trainings))}
    draws = {name: [{"tag": tag, "val_history": _history(on)} for tag, on in d] for name, d in (draws or {}).items()}
    return {"models": models, **({"draws": draws} if draws else {})}


def test_machine_note_says_where_every_draw_trained_and_where_latency_was_timed():
    one = provenance.machine_note(_summary({"a": {"X": 2}, "b": {"X": 3}}))
    assert one == ("trained (every epoch of the 2 trainings) and latency timed on X. A training rerun on another "
                   "CPU is another draw; latency holds for the CPU that timed it.")
    assert provenance.machine_note(_summary({"a": {"X": 2}})).startswith("trained (every epoch of the training) and")
    timed_elsewhere = provenance.machine_note(_summary({"a": {"X": 2}, "b": {"X": 3}}, timed=("Y",)))
    assert timed_elsewhere.startswith("trained on X (every epoch of the 2 trainings); latency timed on Y.")
    draws = {"a": [("a", {"X": 2}), ("a.seed1", {"Y": 2}), ("a.seed2", {"": 1, "Y": 1}), ("a.seed3", {"": 2})]}
    mixed = provenance.machine_note(_summary({"a": {"X": 2}, "imported": {}}, timed=("X", "Y"), draws=draws))
    assert mixed.startswith("trained on X: a; trained on Y: a.seed1; a.seed2 (1 of 2 epochs on a machine not "
                            "recorded, 1 of 2 epochs on Y); where a.seed3 trained is not recorded")
    assert "latency timed on X and Y." in mixed and "imported" not in mixed  # an imported model trained nowhere here
    assert provenance.machine_note({"models": {"a": {"train": None}}}) is None  # an old run: no line
