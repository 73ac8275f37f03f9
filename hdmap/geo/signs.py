"""Traffic-sign classes: wire codes, names, OpenStreetMap values and panel sizes.

A class has three keys, and a catalogue holds each at most once:

- ``code``: the integer on the wire (``sign_class``, uint16; 1-65535, 0 is no class).
  A code, once given to a class, is never reused for another class nor renumbered:
  stored landmarks, logs and vehicles in the field would read one sign as another.
- ``name``: our snake_case name (``speed_limit_30``), what configs, plots and exports say.
- ``osm``: the OpenStreetMap ``traffic_sign=*`` value mappers tag the sign with
  (``FI:361[30]``), and ``osm_aliases``: other values mappers use for the same panel.
  Names and OSM values are one namespace: a string names at most one class.

The panel height (metres) turns a bounding-box height in pixels into a range
(:mod:`vehicle.geoloc`); ``size_rel_sigma`` is the relative spread of real panels
around it. The default sizes are typical urban sizes of the Vienna-convention signs
used in Finland ("normal" size class, 640 mm discs and squares, 900 mm triangles whose
height is 0.78 m), so the default OSM values are Finnish too, not German ``DE:`` codes:
a code must name the panel whose size we assume, and the OSM data we evaluate on is
Finnish (the Helsinki extract, ``fleetsim/data/helsinki.json``). They are ``FI:`` codes
of the pre-2020 numbering (Tieliikenneasetus 182/1982), the one mappers used there: its
posts carry ``FI:<digits>`` values and none of the letter codes of the 2020 Road Traffic
Act (``docs/helsinki.md`` checks the codes against the road geometry). The 2020 codes
(``FI:B6``) are aliases where we could confirm them. A German deployment gives its
classes, or ``DE:`` values and German sizes for these codes, in its catalogue file.

A deployment's catalogue file (TOML, ``deploy/signs.toml`` lists the defaults) adds
classes and overrides sizes and OSM values of existing codes
(:meth:`SignCatalog.from_toml`); every error names the entry and the field.

>>> CATALOG.by_name("speed_limit_30").height_m
0.64
>>> CATALOG.code_of("stop"), CATALOG.code_of("FI:232"), CATALOG.code_of("FI:B6")
(1, 1, 1)
>>> CATALOG.by_osm("DE:206")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hdmap.geo.signs.UnknownSignClass: unknown sign class OSM value 'DE:206' (known: FI:232 (stop), ...)
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

WIRE_CODE_MAX = 65535
"""The largest wire code (``sign_class`` is a uint16)."""

DEFAULT_SIZE_REL_SIGMA = 0.10

_NAME = re.compile(r"^[a-z][a-z0-9_]{0,63}$")
_SHOWN = 5
"""Known classes listed in an unknown-class error."""


class SignCatalogError(ValueError):
    """A sign class or catalogue entry that breaks a catalogue invariant; the message
    names the entry and the field (``deploy/signs.toml: class[3].code: ...``)."""

    def __init__(self, message: str, code: int | None = None, field: str = "", reason: str = ""):
        super().__init__(message)
        self.code = code
        """Wire code of the offending class, when it has one."""
        self.field = field
        self.reason = reason


class UnknownSignClass(KeyError, ValueError):
    """A code, name or OSM value no class of the catalogue has; the message names it and
    a few known classes. Both a ``KeyError`` (a failed lookup) and a ``ValueError``."""

    def __init__(self, message: str, ref: object):
        super().__init__(message)
        self.ref = ref

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class SignClass:
    """One sign class: wire code, name, OSM values, panel size (checked by the catalogue)."""

    code: int
    name: str
    height_m: float
    size_rel_sigma: float = DEFAULT_SIZE_REL_SIGMA
    """Relative standard deviation of the real panel size around ``height_m``."""
    osm: str = ""
    """The OSM ``traffic_sign=*`` value mappers use for this panel ("" for none)."""
    osm_aliases: tuple[str, ...] = ()
    """Other OSM values of the same panel (another numbering, a zone variant)."""

    @property
    def osm_values(self) -> tuple[str, ...]:
        return ((self.osm,) if self.osm else ()) + tuple(self.osm_aliases)


# Each OSM value below is marked with how it was checked:
#   [H]  in the OSM data of the Helsinki extract (fleetsim/data/helsinki.json), with the
#        meaning docs/helsinki.md checked against the geometry (fleetsim.osm_town.FI_CLASSES);
#   [h]  named in fleetsim.osm_town.FI_CLASSES but absent from, or too rare in, the extract
#        to check; the number is the 1982 decree's as we know it;
#   [L]  the sign code of the 2020 Road Traffic Act (729/2018, annex 3) per Finnish
#        road-traffic sources (liikennemerkkeja.fi, liikenneturva.fi, municipal pages);
#        not checked in OSM data;
#   [?]  not verified: the 1982 number as we recall it, neither in the extract's checked
#        codes nor confirmed by a source we could read.
# Speed limits carry the value in brackets, as the extract does (``FI:361[30]``);
# ``FI:363[..]`` is the zone sign. The 2020 code of a class is left out where we could not
# confirm it (no_entry, one_way, parking, roundabout, keep_right, children, road_works,
# bus_stop, no_turn, cycle_path, dead_end).
def _fi(code: int, name: str, height_m: float, osm: str, *aliases: str) -> SignClass:
    """A default (Finnish) class with the default size spread."""
    return SignClass(code, name, height_m, osm=osm, osm_aliases=aliases)


_DEFAULT_CLASSES: tuple[SignClass, ...] = (
    _fi(1, "stop", 0.75, "FI:232", "FI:B6"),  # [H] (1 post), [L]
    _fi(2, "give_way", 0.78, "FI:231", "FI:B5"),  # [H], [L]
    _fi(3, "no_entry", 0.64, "FI:331"),  # [H]
    _fi(4, "speed_limit_30", 0.64, "FI:361[30]", "FI:363[30]", "FI:C32[30]"),  # [H], [L]
    _fi(5, "speed_limit_40", 0.64, "FI:361[40]", "FI:363[40]", "FI:C32[40]"),  # [H], [L]
    _fi(6, "speed_limit_50", 0.64, "FI:361[50]", "FI:363[50]", "FI:C32[50]"),  # as 30/40, [L]
    _fi(7, "no_parking", 0.64, "FI:372", "FI:373", "FI:C38"),  # [H], [L]
    _fi(8, "no_stopping", 0.64, "FI:371", "FI:C37"),  # [H], [L]
    _fi(9, "pedestrian_crossing", 0.64, "FI:511", "FI:E1"),  # [H], [L]
    _fi(10, "priority_road", 0.64, "FI:211", "FI:B1"),  # [H], [L]
    _fi(11, "one_way", 0.64, "FI:551"),  # [H]
    _fi(12, "parking", 0.64, "FI:521", "FI:521a", "FI:521b", "FI:521c"),  # [H]
    _fi(13, "roundabout", 0.64, "FI:416"),  # [?] no FI:416 in the extract
    _fi(14, "keep_right", 0.64, "FI:417"),  # [H]
    _fi(15, "children", 0.78, "FI:152"),  # [H]
    _fi(16, "road_works", 0.78, "FI:142"),  # [h] 2 posts
    _fi(17, "bus_stop", 0.64, "FI:531"),  # [H]
    _fi(18, "no_turn", 0.64, "FI:332", "FI:333", "FI:334"),  # [H] no left, right, U-turn
    _fi(19, "cycle_path", 0.64, "FI:421", "FI:422", "FI:423", "FI:424"),  # [H]
    _fi(20, "dead_end", 0.64, "FI:651"),  # [?] 2 posts in the extract, meaning not checked
)


def _field_problem(c: SignClass) -> tuple[str, str] | None:
    """(field, reason) of the first field of ``c`` out of its range; None if all fit."""
    code = c.code
    if isinstance(code, bool) or not isinstance(code, int | np.integer):
        return "code", f"expected an integer, got {type(code).__name__}"
    if not 1 <= int(code) <= WIRE_CODE_MAX:
        return "code", f"{code} is not a wire code (1-{WIRE_CODE_MAX}; 0 is no class)"
    if not isinstance(c.name, str) or not _NAME.match(c.name):
        return "name", f"{c.name!r} is not a snake_case name (a-z, 0-9, _; at most 64)"
    for fname, lo, hi in (("height_m", 0.0, math.inf), ("size_rel_sigma", 0.0, 1.0)):
        v = getattr(c, fname)
        if isinstance(v, bool) or not isinstance(v, int | float | np.floating):
            return fname, f"expected a number, got {type(v).__name__}"
        if not (lo < float(v) < hi):
            bound = f"> {lo:g}" if hi == math.inf else f"in ({lo:g}, {hi:g})"
            return fname, f"must be {bound} and finite, got {v!r}"
    if not isinstance(c.osm, str):
        return "osm", f"expected a string, got {type(c.osm).__name__}"
    if not isinstance(c.osm_aliases, tuple):
        return "osm_aliases", f"expected a tuple of strings, got {type(c.osm_aliases).__name__}"
    for i, v in enumerate(c.osm_values):
        fname = "osm" if c.osm and i == 0 else "osm_aliases"
        if not isinstance(v, str) or not v:
            return fname, f"expected a non-empty string, got {v!r}"
        if v != v.strip() or ";" in v or len(v) > 200:
            return fname, f"{v!r}: one traffic_sign value (no ';', no surrounding blanks)"
    return None


def _index(classes: Iterable[SignClass]) -> tuple[dict[int, SignClass], dict[str, SignClass]]:
    """(by code, by name or OSM value), checking every invariant of a catalogue in order:
    a conflict is reported on the later class."""
    by_code: dict[int, SignClass] = {}
    by_ref: dict[str, SignClass] = {}
    for c in classes:
        problem = _field_problem(c)
        if problem is None and int(c.code) in by_code:
            problem = "code", f"{c.code} is already {by_code[int(c.code)].name!r}"
        refs = [("name", c.name)]
        refs += [
            ("osm" if c.osm and i == 0 else "osm_aliases", v) for i, v in enumerate(c.osm_values)
        ]
        own: set[str] = set()
        for fname, ref in refs if problem is None else ():
            other = by_ref.get(ref)
            if other is not None:
                problem = fname, f"{ref!r} already names class {other.code} ({other.name!r})"
            elif ref in own and fname != "name" and ref != c.name:
                problem = fname, f"{ref!r} is given twice"
            if problem is not None:
                break
            own.add(ref)
        if problem is not None:
            fname, why = problem
            raise SignCatalogError(
                f"sign class {c.code} ({c.name!r}): {fname}: {why}", c.code, fname, why
            )
        c = replace(
            c, code=int(c.code), height_m=float(c.height_m), size_rel_sigma=float(c.size_rel_sigma)
        )
        by_code[c.code] = c
        for ref in own:
            by_ref[ref] = c
    return by_code, by_ref


class SignCatalog:
    """Immutable lookup of sign classes by wire code, name and OSM ``traffic_sign`` value."""

    def __init__(self, classes: Iterable[SignClass]):
        self._by_code, self._by_ref = _index(classes)
        self._by_name = {c.name: c for c in self._by_code.values()}
        self._by_osm = {v: c for c in self._by_code.values() for v in c.osm_values}
        max_code = max(self._by_code, default=0)
        self._height = np.zeros(max_code + 1)
        self._rel = np.zeros(max_code + 1)
        for c in self._by_code.values():
            self._height[c.code] = c.height_m
            self._rel[c.code] = c.size_rel_sigma

    def __len__(self) -> int:
        return len(self._by_code)

    def __iter__(self) -> Iterator[SignClass]:
        return iter(sorted(self._by_code.values(), key=lambda c: c.code))

    def __contains__(self, code: object) -> bool:
        return code in self._by_code

    # -- lookups ----------------------------------------------------------------------

    def _unknown(self, what: str, ref: object) -> UnknownSignClass:
        shown = [f"{c.osm or c.code} ({c.name})" for c in list(self)[:_SHOWN]]
        more = f", ... {len(self)} classes" if len(self) > _SHOWN else ""
        known = ", ".join(shown) + more if shown else "none: the catalogue is empty"
        return UnknownSignClass(f"unknown sign class {what} {ref!r} (known: {known})", ref)

    def by_code(self, code: int) -> SignClass:
        c = self._by_code.get(int(code))
        if c is None:
            raise self._unknown("code", int(code))
        return c

    def by_name(self, name: str) -> SignClass:
        c = self._by_name.get(name)
        if c is None:
            raise self._unknown("name", name)
        return c

    def by_osm(self, value: str) -> SignClass:
        """The class an OSM ``traffic_sign=*`` value (primary or alias) names."""
        c = self._by_osm.get(value.strip()) if isinstance(value, str) else None
        if c is None:
            raise self._unknown("OSM value", value)
        return c

    def by_ref(self, ref: str) -> SignClass:
        """The class a name or an OSM value names."""
        c = self._by_ref.get(ref.strip()) if isinstance(ref, str) else None
        if c is None:
            raise self._unknown("name or OSM value", ref)
        return c

    def code_of(self, ref: str) -> int:
        """Wire code of the class a name or an OSM value names."""
        return self.by_ref(ref).code

    def code(self, name: str) -> int:
        """Wire code of the class of this name."""
        return self.by_name(name).code

    @property
    def codes(self) -> NDArray[np.int64]:
        return np.array(sorted(self._by_code), dtype=np.int64)

    # -- vectorised -------------------------------------------------------------------

    def known(self, codes: NDArray) -> NDArray[np.bool_]:
        """Vectorised membership test."""
        c = np.asarray(codes, dtype=np.int64)
        ok = (c >= 0) & (c < self._height.size)
        out = np.zeros(c.shape, bool)
        out[ok] = self._height[c[ok]] > 0
        return out

    def heights(self, codes: NDArray) -> NDArray[np.float64]:
        """Panel heights (m) per code; 0 for unknown codes."""
        c = np.asarray(codes, dtype=np.int64)
        out = np.zeros(c.shape)
        ok = self.known(c)
        out[ok] = self._height[c[ok]]
        return out

    def rel_sigmas(self, codes: NDArray) -> NDArray[np.float64]:
        c = np.asarray(codes, dtype=np.int64)
        out = np.zeros(c.shape)
        ok = self.known(c)
        out[ok] = self._rel[c[ok]]
        return out

    # -- derived catalogues -----------------------------------------------------------

    def with_sizes(self, heights_m: Mapping[str, float]) -> SignCatalog:
        """A copy with some panel heights overridden (by class name or OSM value)."""
        new = {self.by_ref(ref).code: float(h) for ref, h in heights_m.items()}
        return SignCatalog(replace(c, height_m=new.get(c.code, c.height_m)) for c in self)

    @classmethod
    def from_mapping(
        cls, doc: Mapping[str, Any], base: SignCatalog | None = None, source: str = ""
    ) -> SignCatalog:
        """``base`` (default :data:`CATALOG`) with the ``[[class]]`` entries of a decoded
        catalogue file (format in ``deploy/signs.toml``); :class:`SignCatalogError` names
        the entry and the field of the first problem."""
        return _from_doc(doc, CATALOG if base is None else base, f"{source}: " if source else "")

    @classmethod
    def from_toml(cls, path: str | Path, base: SignCatalog | None = None) -> SignCatalog:
        """:meth:`from_mapping` of a TOML file; an unreadable or malformed file is a
        :class:`SignCatalogError` naming it."""
        try:
            with open(path, "rb") as f:
                doc = tomllib.load(f)
        except OSError as exc:
            raise SignCatalogError(f"{path}: cannot read ({exc.strerror or exc})") from exc
        except tomllib.TOMLDecodeError as exc:
            raise SignCatalogError(f"{path}: not valid TOML: {exc}") from exc
        return cls.from_mapping(doc, base, str(path))


# --- the catalogue file --------------------------------------------------------------

FORMAT = 1
_TOP_KEYS = ("format", "class")
_ENTRY_KEYS = ("code", "name", "osm", "osm_aliases", "height_m", "size_rel_sigma")


def _from_doc(doc: Mapping[str, Any], base: SignCatalog, where: str) -> SignCatalog:
    if not isinstance(doc, Mapping):
        raise SignCatalogError(f"{where}expected a table")
    for k in doc:
        if k not in _TOP_KEYS:
            raise SignCatalogError(f"{where}{k}: unknown key (known: {', '.join(_TOP_KEYS)})")
    fmt = doc.get("format", FORMAT)
    if fmt != FORMAT or isinstance(fmt, bool):
        raise SignCatalogError(f"{where}format: {fmt!r} is not a known format ({FORMAT})")
    entries = doc.get("class", [])
    if not isinstance(entries, list):
        raise SignCatalogError(f"{where}class: expected an array of tables ([[class]])")
    changed: dict[int, tuple[int, SignClass]] = {}  # wire code -> (entry index, its class)
    for i, e in enumerate(entries):
        at = f"{where}class[{i}]"
        c = _entry(e, base, at)
        if c.code in changed:
            raise SignCatalogError(
                f"{at}.code: {c.code} is given again (class[{changed[c.code][0]}])"
            )
        changed[c.code] = (i, c)
    entry_of = {code: i for code, (i, _) in changed.items()}
    order = [c for c in base if c.code not in changed] + [c for _, c in changed.values()]
    try:
        return SignCatalog(order)
    except SignCatalogError as exc:
        i = entry_of.get(exc.code) if exc.code is not None else None
        if i is None:  # a conflict inside the base itself (it cannot have been built)
            raise
        raise SignCatalogError(f"{where}class[{i}].{exc.field}: {exc.reason}") from None


def _entry(e: Any, base: SignCatalog, at: str) -> SignClass:
    """One ``[[class]]`` entry: a new class (code, name, osm, height_m required) or, for a
    code of ``base``, that class with the sizes and OSM values given (its name required,
    as a check: a wire code keeps its class)."""
    if not isinstance(e, Mapping):
        raise SignCatalogError(f"{at}: expected a table")
    for k in e:
        if k not in _ENTRY_KEYS:
            raise SignCatalogError(f"{at}.{k}: unknown key (known: {', '.join(_ENTRY_KEYS)})")
    code = _get(e, "code", int, at)
    if not 1 <= code <= WIRE_CODE_MAX:
        raise SignCatalogError(f"{at}.code: {code} is not a wire code (1-{WIRE_CODE_MAX})")
    name = _get(e, "name", str, at)
    if code in base:
        old = base.by_code(code)
        if name != old.name:
            raise SignCatalogError(
                f"{at}.name: code {code} is {old.name!r} in the base catalogue, not {name!r} "
                "(a wire code keeps its class: give a new class a new code)"
            )
    else:
        for k in ("osm", "height_m"):
            if k not in e:
                raise SignCatalogError(f"{at}.{k}: missing (code {code} is a new class)")
        old = SignClass(code, name, 1.0)
    kw: dict[str, Any] = {k: e[k] for k in ("osm", "height_m", "size_rel_sigma") if k in e}
    for k, v in kw.items():
        _check_type(v, str if k == "osm" else float, f"{at}.{k}")
    if kw.get("osm") == "":
        raise SignCatalogError(f"{at}.osm: expected a non-empty string (a traffic_sign value)")
    if "osm_aliases" in e:
        aliases = e["osm_aliases"]
        if not isinstance(aliases, list):
            raise SignCatalogError(f"{at}.osm_aliases: expected a list of strings")
        for j, a in enumerate(aliases):
            _check_type(a, str, f"{at}.osm_aliases[{j}]")
        kw["osm_aliases"] = tuple(aliases)
    c = replace(old, **kw)
    problem = _field_problem(c)
    if problem is not None:
        raise SignCatalogError(f"{at}.{problem[0]}: {problem[1]}")
    return c


def _get(e: Mapping[str, Any], key: str, tp: type, at: str) -> Any:
    if key not in e:
        raise SignCatalogError(f"{at}.{key}: missing")
    _check_type(e[key], tp, f"{at}.{key}")
    return e[key]


def _check_type(v: Any, tp: type, key: str) -> None:
    if tp is int and (isinstance(v, bool) or not isinstance(v, int)):
        raise SignCatalogError(f"{key}: expected an integer, got {type(v).__name__} {v!r}")
    if tp is float and (isinstance(v, bool) or not isinstance(v, int | float)):
        raise SignCatalogError(f"{key}: expected a number, got {type(v).__name__} {v!r}")
    if tp is str and not isinstance(v, str):
        raise SignCatalogError(f"{key}: expected a string, got {type(v).__name__} {v!r}")


CATALOG = SignCatalog(_DEFAULT_CLASSES)
"""The default catalogue (immutable)."""
