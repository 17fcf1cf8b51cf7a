"""The code that made a run: the git commit of the checkout (when there is one) and a SHA-256 digest of the
sources of the three packages (``simulator``, ``models``, ``harness``), so that a report can say whether the
code installed now is the code that made it. The digest covers every file under the packages except
bytecode caches, by relative path and bytes, so it is the same for an installed copy and a checkout.

And the machine that made it (:func:`machine`): a training rerun on another CPU is another draw, so every
training epoch (``val_history``) and every stage record names the CPU it ran on, and the report says where
its models were trained and timed (:func:`machine_note`)."""
from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import subprocess
from collections import Counter
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


# the widest vector instruction set first: what the numerical kernels (GEMM, Embree, numba) dispatch on
_ISA_FLAGS = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sse4_2", "SSE4.2"))


def machine_text(cpuinfo: str, cores: int | None, fallback: str = "") -> str:
    """``/proc/cpuinfo``'s text as one name: the first ``model name``, the widest instruction set of
    the first ``flags`` line (x86), the logical cores, e.g. "Intel(R) Xeon(R) Processor (AVX-512, 2 cores)";
    ``fallback`` names the CPU when ``cpuinfo`` has no model name."""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip().lower(), value.strip())
    name = " ".join(fields.get("model name", "").split()) or fallback or "unknown CPU"
    flags = set(fields.get("flags", "").split())
    isa = next((label for flag, label in _ISA_FLAGS if flag in flags), None)
    parts = [p for p in (isa, f"{cores} cores" if cores else None) if p]
    return f"{name} ({', '.join(parts)})" if parts else name


@functools.lru_cache(maxsize=1)
def machine() -> str:
    """This machine's CPU, as :func:`machine_text` names it (``platform`` where there is no /proc/cpuinfo)."""
    try:
        info = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        info = ""
    return machine_text(info, os.cpu_count(), platform.processor() or platform.machine())


def trained_on(history) -> dict[str, int]:
    """Epochs per machine of a checkpoint's ``val_history`` (as a run's summary carries it per model and per
    draw), in the order they ran; epochs whose entry names no machine (trained before the entry kept it)
    under the key ``""``."""
    return dict(Counter((h.get("machine") if isinstance(h, dict) else None) or "" for h in history or []))


def _trainings_text(trainings: dict[str, dict]) -> str:
    """``{tag: trained_on(...)}`` as a clause per machine, the trainings listed where machines differ."""
    whole: dict[str, list[str]] = {}  # machine -> trainings whose every epoch it ran
    mixed, unknown = [], []
    for tag, epochs in trainings.items():
        if not any(epochs):
            unknown.append(tag)
        elif len(epochs) == 1:
            whole.setdefault(next(iter(epochs)), []).append(tag)
        else:
            total = sum(epochs.values())
            mixed.append(f"{tag} (" + ", ".join(f"{n} of {total} epochs on {m or 'a machine not recorded'}"
                                                for m, n in epochs.items()) + ")")
    if len(whole) == 1 and not mixed and not unknown:
        return f"trained on {next(iter(whole))} (every epoch of {_trainings(len(trainings))})"
    parts = [f"trained on {m}: {', '.join(tags)}" for m, tags in whole.items()] + mixed
    if unknown:
        parts.append(f"where {', '.join(unknown)} trained is not recorded (checkpoints made before their epochs "
                     "named the machine)")
    return "; ".join(parts)


def _trainings(n: int) -> str:
    """"the training" or "the 14 trainings"."""
    return "the training" if n == 1 else f"the {n} trainings"


def machine_note(summary: dict) -> str | None:
    """Where a run's models were trained (every draw's epochs) and their latency timed: the report's
    "Machine" line (None when the run records neither). An imported model trained nowhere here."""
    models = summary.get("models") or {}
    trainings = {}
    for name, m in models.items():
        own = [{"tag": name, "val_history": (m.get("train") or {}).get("val_history")}]
        for d in (summary.get("draws") or {}).get(name) or own:
            if epochs := trained_on(d.get("val_history")):
                trainings[d.get("tag") or name] = epochs
    timed = sorted({(m.get("runtime") or {}).get("machine") for m in models.values()} - {None})
    places = {m for epochs in trainings.values() for m in epochs}
    if len(timed) == 1 and places == set(timed):  # the usual run: one machine did it all
        text = [f"trained (every epoch of {_trainings(len(trainings))}) and latency timed on {timed[0]}"]
    else:
        text = [_trainings_text(trainings)] if trainings else []
        if timed:
            text.append(f"latency timed on {' and '.join(timed)}")
    if not text:
        return None
    return "; ".join(text) + ". A training rerun on another CPU is another draw; latency holds for the CPU that timed it."


if __name__ == "__main__":
    print(json.dumps({**record(), "machine": machine()}, indent=1))
