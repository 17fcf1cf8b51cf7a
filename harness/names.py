"""Names given on the command line (models, weather presets) matched to the valid ones.

A name matches case-insensitively (``clearnoon`` is ``ClearNoon``); one that matches none is refused
with the closest valid names (``difflib``) and the full list.
"""
from __future__ import annotations

import difflib


def resolve_names(given: list[str], valid, option: str, what: str) -> list[str]:
    """``given`` as ``valid`` spells them; ValueError naming ``option``, the first unknown name, a
    "did you mean" suggestion when one is close, and the valid names (``what``: "weather preset")."""
    by_lower = {v.lower(): v for v in valid}
    unknown = [g for g in given if g.lower() not in by_lower]
    if unknown:
        close = difflib.get_close_matches(unknown[0].lower(), list(by_lower), n=3, cutoff=0.6)
        hint = f" (did you mean {' or '.join(by_lower[c] for c in close)}?)" if close else ""
        more = f" and {len(unknown) - 1} more" if len(unknown) > 1 else ""
        raise ValueError(f"{option}: unknown {what} {unknown[0]!r}{hint}{more}; valid: {', '.join(valid)}")
    return [by_lower[g.lower()] for g in given]
