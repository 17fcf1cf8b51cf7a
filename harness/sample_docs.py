"""The numbers README.md and docs/results.md quote from the sample, written from the sample's tables.

A document marks each block this module writes with two HTML comments, invisible on GitHub:

    <!-- sample:readme-table -->
    ... written by ``sotif-bench report --docs`` from reports/sample/tables/*.csv ...
    <!-- /sample -->

``render_blocks`` turns the sample's ``tables/*.csv`` into the text of every block (``harness.sample_numbers``
computes the numbers with pandas, the jinja2 macros of ``harness/templates/sample_docs.md.j2`` lay them out);
``update`` replaces the marked blocks of one document and leaves every other line as it was; ``write_docs``
does both for ``DOCUMENTS`` and writes each changed document atomically. A block whose table (or column) is
missing is left as it was and reported with the file it needed, never emptied.

    sotif-bench report --docs [--sample reports/sample]
    python -m harness.sample_docs [--sample DIR] [--root DIR] [--check]
"""
from __future__ import annotations

import argparse
import re
import sys
import textwrap
from pathlib import Path

from jinja2 import Environment, FileSystemLoader, StrictUndefined

from harness import sample_numbers
from harness.core.files import atomic_write_text
from harness.core.kitti import KittiError
from harness.sample_numbers import SampleTables

ROOT = Path(__file__).resolve().parent.parent  # the checkout: README.md, docs/, reports/sample
SAMPLE = Path("reports") / "sample"
TEMPLATE = "sample_docs.md.j2"
DOCUMENTS = {  # document (relative to ROOT) -> the blocks it must hold, each once
    "README.md": ("readme-table", "boundaries", "rankings"),
    "docs/results.md": ("data-sets", "sweep-instances", "preset-verdict", "how-to-read"),
}
BLOCKS = {  # block name -> the function of harness.sample_numbers giving its template's arguments
    "readme-table": sample_numbers.readme_table,
    "boundaries": sample_numbers.boundaries,
    "rankings": sample_numbers.rankings,
    "data-sets": sample_numbers.data_sets,
    "sweep-instances": sample_numbers.sweep_instances,
    "preset-verdict": sample_numbers.preset_verdict,
    "how-to-read": sample_numbers.how_to_read,
}
OPEN = re.compile(r"^<!-- sample:([a-z0-9-]+) -->$")
CLOSE = "<!-- /sample -->"
WIDTH = 105  # the documents' line length


def render_blocks(tables_dir) -> dict:
    """``{block name: text}`` for every block of ``BLOCKS``, or ``{name: KittiError}`` for a block whose table
    or column is missing (the error names the file)."""
    t = SampleTables(tables_dir)
    env = Environment(loader=FileSystemLoader(Path(__file__).parent / "templates"), undefined=StrictUndefined,
                      trim_blocks=True, lstrip_blocks=True, autoescape=False)
    macros = env.get_template(TEMPLATE).module
    out = {}
    for name, numbers in BLOCKS.items():
        try:
            out[name] = _wrap(getattr(macros, name.replace("-", "_"))(**numbers(t)))
        except KittiError as e:
            out[name] = e
    return out


def _wrap(text: str) -> str:
    """Fill each paragraph to ``WIDTH`` (a bullet's lines indented under it); tables stay as they are."""
    out = []
    for para in re.split(r"\n\s*\n", text.strip()):
        if para.lstrip().startswith("|"):
            out.append("\n".join(line.strip() for line in para.strip().splitlines()))
        elif para.lstrip().startswith("- "):
            items = re.split(r"\n\s*(?=- )", para.strip())
            out.append("\n".join(textwrap.fill(" ".join(i[2:].split()), WIDTH, initial_indent="- ",
                                               subsequent_indent="  ", break_on_hyphens=False) for i in items))
        else:
            out.append(textwrap.fill(" ".join(para.split()), WIDTH, break_on_hyphens=False))
    return "\n\n".join(out)


def _spans(text: str, doc) -> list[tuple[str, int, int]]:
    """(name, first line, closing line) of each marked block of ``text``, line numbers from 0; a marker
    without its partner or an unknown block name raises ``KittiError`` naming ``doc`` and the line."""
    spans, open_at, name = [], None, None
    for i, line in enumerate(text.splitlines()):
        found = OPEN.match(line.strip())
        if found:
            if open_at is not None:
                raise KittiError(doc, f"block {name!r} opened on line {open_at + 1} is not closed ({CLOSE})", i + 1)
            name, open_at = found.group(1), i
            if name not in BLOCKS:
                raise KittiError(doc, f"unknown block {name!r}; known: {', '.join(BLOCKS)}", i + 1)
        elif line.strip() == CLOSE:
            if open_at is None:
                raise KittiError(doc, f"{CLOSE} closes no block", i + 1)
            spans.append((name, open_at, i))
            open_at = None
    if open_at is not None:
        raise KittiError(doc, f"block {name!r} is not closed ({CLOSE})", open_at + 1)
    return spans


def update(text: str, blocks: dict, doc, expected=()) -> tuple[str, list[str]]:
    """``text`` with each marked block replaced by ``blocks[name]``, and the problems: a block left as it
    was because ``blocks[name]`` is an error, an ``expected`` block absent or present twice."""
    lines, problems = text.splitlines(keepends=True), []
    spans = _spans(text, doc)
    names = [s[0] for s in spans]
    problems += [f"{doc}: no block {n!r} (mark it <!-- sample:{n} --> ... {CLOSE})" for n in expected if n not in names]
    problems += [f"{doc}: block {n!r} appears {names.count(n)} times" for n in dict.fromkeys(names)
                 if names.count(n) > 1]
    for name, start, end in reversed(spans):
        new = blocks[name]
        if isinstance(new, Exception):
            problems.append(f"{doc}: block {name!r} left as it was: {new}")
            continue
        lines[start + 1:end] = [new.rstrip("\n") + "\n"]
    return "".join(lines), problems


def generated(root, tables_dir) -> dict:
    """``{document: (committed text, generated text, problems)}`` for each of ``DOCUMENTS`` under ``root``."""
    root, blocks, out = Path(root), render_blocks(tables_dir), {}
    for rel, expected in DOCUMENTS.items():
        path = root / rel
        if not path.is_file():
            raise KittiError(path, "document not found")
        text = path.read_text(encoding="utf-8")
        out[rel] = (text, *update(text, blocks, path, expected))
    return out


def write_docs(root=ROOT, sample=None) -> tuple[list[str], list[str]]:
    """Rewrite the marked blocks of ``DOCUMENTS`` under ``root`` from ``sample``/tables (default
    ``root``/reports/sample); returns (the documents changed, the problems). A document is written only when its
    blocks changed, atomically; a block that could not be made is left as it was and listed in the problems."""
    root = Path(root)
    tables_dir = Path(sample if sample is not None else root / SAMPLE) / "tables"
    if not tables_dir.is_dir():
        raise KittiError(tables_dir, "folder not found: the sample's tables (reports/sample/tables)")
    changed, problems = [], []
    for rel, (old, new, issues) in generated(root, tables_dir).items():
        problems += issues
        if new != old:
            atomic_write_text(root / rel, new)
            changed.append(rel)
    return changed, problems


def report_docs(root=ROOT, sample=None, check: bool = False) -> int:
    """Write (or with ``check`` only compare) the documents and print what happened; 0 when every block is
    current, 2 when a block could not be made (or, with ``check``, differs from the tables)."""
    if check:
        tables_dir = Path(sample if sample is not None else Path(root) / SAMPLE) / "tables"
        docs = generated(root, tables_dir)
        problems = [p for _, _, issues in docs.values() for p in issues]
        stale = [rel for rel, (old, new, _) in docs.items() if new != old]
        problems += [f"{rel}: differs from the sample's tables (sotif-bench report --docs rewrites it)"
                     for rel in stale]
    else:
        changed, problems = write_docs(root, sample)
        for rel in DOCUMENTS:
            print(f"docs: {rel} {'rewritten' if rel in changed else 'unchanged'}")
    for p in problems:
        print(f"docs: {p}", file=sys.stderr)
    return 2 if problems else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m harness.sample_docs", description=__doc__.splitlines()[0])
    p.add_argument("--sample", metavar="DIR", help="the sample folder (default ROOT/reports/sample)")
    p.add_argument("--root", metavar="DIR", default=str(ROOT), help="the checkout holding README.md and docs/")
    p.add_argument("--check", action="store_true", help="write nothing; exit 2 when a block differs from the tables")
    a = p.parse_args(argv)
    try:
        return report_docs(Path(a.root), a.sample, a.check)
    except KittiError as e:
        print(f"docs: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
