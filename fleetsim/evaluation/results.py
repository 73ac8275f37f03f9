"""Evaluation results as files: strict JSON, and the summary of a run over several seeds."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from fleetsim.evaluation.fleet_seeds import format_seed_table


def json_default(o: object) -> object:
    """numpy arrays and scalars as JSON values."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def clean(o: object) -> object:
    """NaN/inf -> None so the file is strict JSON.

    >>> clean({"a": [1.0, float("nan")], "b": (float("inf"),)})
    {'a': [1.0, None], 'b': [None]}
    """
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [clean(v) for v in o]
    return o


def write_json(doc: dict, path: Path) -> None:
    """``doc`` as strict JSON (:func:`clean`, :func:`json_default`) at ``path``."""
    path.write_text(json.dumps(clean(doc), indent=1, default=json_default))


def write_seed_summary(
    summary: dict, path: Path, columns: list[tuple[str, str, str]], prog: str
) -> None:
    """Write a several-seeds summary as JSON and print its table on stderr (``columns``,
    see :func:`fleetsim.evaluation.fleet_seeds.format_seed_table`)."""
    write_json(summary, path)
    print(format_seed_table(summary, columns), file=sys.stderr)
    print(f"{prog}: wrote {path}", file=sys.stderr, flush=True)
