"""The solver's tables cut by region or joined (:mod:`hdmap.runtime.partition`):
landmarks by the region of their home tile, their views, box-range and looming sums (open
passes too) and existence with them; the event-time clock copied (joined: the latest)."""

from __future__ import annotations

from hdmap.runtime.partition import Rules

RULES = Rules(
    service="solver",
    split=(
        "DELETE FROM landmarks WHERE NOT in_region(home)",
        "DELETE FROM views WHERE id NOT IN (SELECT id FROM landmarks)",
        "DELETE FROM existence WHERE id NOT IN (SELECT id FROM landmarks)",
        "DELETE FROM ranges WHERE id NOT IN (SELECT id FROM landmarks)",
        "DELETE FROM loom_open WHERE id NOT IN (SELECT id FROM landmarks)",
    ),
    merge={
        "clock": "INSERT INTO clock SELECT * FROM b.clock WHERE true "
        "ON CONFLICT(name) DO UPDATE SET t = MAX(t, excluded.t)",
    },
)
