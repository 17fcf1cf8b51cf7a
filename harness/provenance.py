"""The code that made a run: the git commit of the checkout (when there is one) and a SHA-256 digest of the
sources of the three packages (``simulator``, ``models``, ``harness``), so that a report can say whether the
code installed now is the code that made it. The digest covers every file under the packages except
bytecode caches, by relative path and bytes, so it is the same for an installed copy and a checkout."""
from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

PACKAGES = ("simulator", "models", "harness")
ROOT = Path(__file__).resolve().parent.parent  # the folder holding the packages


def source_files(root: Path = ROOT) -> list[Path]:
    """The packages' files (relative to ``root``), sorted; no ``__pycache__`` or compiled files."""
    files = [p.relative_to(root) for pkg in PACKAGES for p in (root / pkg).rglob("*")
             if p.is_file() and "__pycache__" not in p.parts and p.suffix not in (".pyc", ".pyo")]
    return sorted(files, key=lambda p: p.as_posix())


def source_digest(root: Path = ROOT) -> str:
    """SHA-256 over (relative path, NUL, size, NUL, bytes) of every source file, in path order."""
    h = hashlib.sha256()
    for rel in source_files(root):
        data = (root / rel).read_bytes()
        h.update(rel.as_posix().encode() + b"\0" + str(len(data)).encode() + b"\0" + data)
    return h.hexdigest()


def git_commit(root: Path = ROOT) -> str | None:
    """The checkout's HEAD commit, or None outside a git checkout (an installed package) or without git."""
    try:
        done = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None if done.returncode == 0 else None


def record(root: Path = ROOT) -> dict:
    """What a run stores (results.json and config.json key ``code``)."""
    return {"commit": git_commit(root), "sources_sha256": source_digest(root)}


def compare(recorded: dict | None, current: str | None = None) -> str:
    """A sentence saying whether the installed sources are the ones ``recorded`` (``record()``'s dict) when this
    runs (the report says it at rendering; ``sotif-bench report`` prints it)."""
    if not isinstance(recorded, dict) or not recorded.get("sources_sha256"):
        return "the run does not record the code that made it (made before the digest was recorded)."
    commit = recorded.get("commit")
    made = f"commit {commit[:10]}" if commit else "an installation outside git"
    digest = recorded["sources_sha256"]
    same = digest == (current or source_digest())
    return (f"made by {made}, sources SHA-256 {digest[:16]} (python -m harness.provenance prints this installation's); "
            + ("the installed sources matched it when this was rendered." if same else
               "the installed sources differed when this was rendered: a new run may not reproduce these numbers."))


def check_run(run_dir) -> str:
    """``compare`` for a run folder's results.json (already checked by the report)."""
    summary = json.loads((Path(run_dir) / "results.json").read_text(encoding="utf-8"))
    return compare(summary.get("code"))


if __name__ == "__main__":
    print(json.dumps(record(), indent=1))
