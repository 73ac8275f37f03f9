"""The matcher's tables cut by region or joined (:mod:`hdmap.runtime.partition`).

Landmarks belong to the region of their home tile (the tile their id was counted in);
their views, box-range sums, panel scales, facings, tick marks, sightings, existence,
counted misses and pair counts follow them. Pending rays belong to their tile's region, the untried
marks to their pending rays. A vehicle's trust, pass budgets and probation status are
copied to every part (each part goes on counting what it sees of the vehicle), except
the home tiles it has held passes in (each part settles those of its own region);
joined, the first part's record is kept, with the held passes' home tiles of both. A
vehicle's held "not seen" reports go with the landmarks they name; joined, both parts'
are kept. Held links must be in the sums (``MatcherService.before_handover``).
"""

from __future__ import annotations

from hdmap.runtime.partition import Rules

_BY_LANDMARK = (
    "views",
    "box_ranges",
    "second_facings",
    "panel_scales",
    "facings",
    "tick",
    "sightings",
    "existence",
    "misses",
)

RULES = Rules(
    service="matcher",
    split=(
        "DELETE FROM landmarks WHERE NOT in_region(home)",
        "DELETE FROM id_counters WHERE NOT in_region(tile)",
        *(f"DELETE FROM {t} WHERE id NOT IN (SELECT id FROM landmarks)" for t in _BY_LANDMARK),
        *(
            f"DELETE FROM {t} WHERE a NOT IN (SELECT id FROM landmarks) "
            "OR b NOT IN (SELECT id FROM landmarks)"
            for t in ("covis", "copass")
        ),
        "DELETE FROM pending WHERE NOT in_region(tile)",
        "DELETE FROM held_absences WHERE landmark_id NOT IN (SELECT id FROM landmarks)",
        "DELETE FROM untried WHERE NOT EXISTS (SELECT 1 FROM pending p "
        "WHERE p.vehicle = untried.vehicle AND p.obs_id = untried.obs_id)",
        # a vehicle's held passes are settled by each part for its own home tiles
        "UPDATE trust_status SET held_homes = region_words(held_homes)",
    ),
    merge={
        "trust_status": "INSERT INTO trust_status SELECT * FROM b.trust_status WHERE true "
        "ON CONFLICT(vehicle) DO UPDATE SET held_homes = "
        "trim(held_homes || ' ' || excluded.held_homes)",
        "clock": "INSERT INTO clock SELECT * FROM b.clock WHERE true "
        "ON CONFLICT(name) DO UPDATE SET t = MAX(t, excluded.t)",
        # a vehicle's held reports from both parts, the second's after the first's
        "held_absences": "INSERT INTO held_absences SELECT vehicle, seq + "
        "(SELECT COALESCE(MAX(seq), -1) + 1 FROM main.held_absences), pass_id, "
        "landmark_id, t, frames FROM b.held_absences",
    },
    empty=("held_links",),
)
